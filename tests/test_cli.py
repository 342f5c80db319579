"""The command line end to end on tiny inputs (tests/golden/tiny_weights.npz), every output
read back, units and axes, previews, the demo, and the messages for bad input or a missing
``cli`` extra."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

from conftest import CMU_DIR, GOLDEN, needs_cmu, with_rest_pose
from minretarget import PRESETS, Retargeter
from minretarget import cli
from minretarget.bvh import read_bvh, resample, world_transforms
from minretarget.contacts import FootLock
from minretarget.conventions import JOINT_NAMES, NUM_JOINTS
from minretarget import stages as stages_module
from minretarget.formats.glb import accessor_array, read_glb
from minretarget.formats.mesh import read_points, write_mesh
from minretarget.skeletons import depth_first_order
from minretarget.sources import MESH_POINTS, SAMPLE, load_sample, open_source
from minretarget.units import (CANONICAL, from_canonical, make_space, rotations_to_canonical,
                               to_canonical)
from minretarget.weights import load_weights, save_weights
from test_glb import node_world_matrices

trimesh = pytest.importorskip("trimesh")
WEIGHTS = str(GOLDEN / "tiny_weights.npz")
ROOT = Path(__file__).resolve().parent.parent
CMU_WALK = CMU_DIR / "cgspeed" / "08" / "08_01.bvh.gz"
FRAMES, POINTS = 6, 160
# Natural order differs from plain string order here (f10 after f4), and every reader is used.
FOLDER_NAMES = ["f1.npy", "f2.xyz", "f3.ply", "f4.obj", "f10.npy", "f11.xyz"]


def run(*args):
    return cli.main([str(a) for a in args])


def load(path):
    with np.load(path, allow_pickle=False) as data:
        return dict(data)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Canonical target mesh and source frames, and the same frames in every SOURCE kind."""
    folder = tmp_path_factory.mktemp("inputs")
    with np.load(GOLDEN / "tiny_stream.npz") as data:
        counts = data["source_counts"][:FRAMES]
        clouds = np.split(data["source_points"][:counts.sum()], np.cumsum(counts)[:-1])
    # (T, P, 3), scaled from the golden stream's 4.3 m to a person's height
    frames = (np.stack([c[:POINTS] for c in clouds]) * 0.4).astype(np.float32)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    # Body-sized and as wide as tall, like a T-pose, so that no warning fires.
    target = (mesh.vertices * [0.85, 0.9, 0.2] + [0, 0.9, 0]).astype(np.float32)
    write_mesh(folder / "target.ply", target, mesh.faces)
    np.save(folder / "target.npy", target)
    (folder / "frames").mkdir()
    for name, frame in zip(FOLDER_NAMES, frames):
        path = folder / "frames" / name
        if path.suffix == ".npy":
            np.save(path, frame)
        elif path.suffix == ".xyz":
            np.savetxt(path, frame, fmt="%.9g")
        else:
            write_mesh(path, frame)
    (folder / "frames" / "README.txt").write_text("not a frame")
    np.save(folder / "frames.npy", frames)
    np.savez(folder / "frames.npz", points=frames, labels=np.arange(FRAMES))
    return {"dir": folder, "frames": frames, "target": target, "faces": mesh.faces}


@pytest.fixture(scope="module")
def folder_run(inputs):
    out = inputs["dir"] / "out_folder"
    assert run("retarget", inputs["dir"] / "frames", inputs["dir"] / "target.ply", "--out", out,
               "--format", "ply,obj,npz,glb,bvh", "--weights", WEIGHTS) == 0
    return out


def api_result(inputs, frames):
    retargeter = Retargeter.from_weights(WEIGHTS)
    retargeter.set_target(inputs["target"], inputs["faces"])
    return list(retargeter.run(frames))


# ----------------------------------------------------------------------------- sources

def test_folder_source_matches_the_python_api(inputs, folder_run):
    result = load(folder_run / "result.npz")
    expected = api_result(inputs, inputs["frames"])
    assert result["vertices"].shape == (FRAMES, len(inputs["target"]), 3)
    np.testing.assert_allclose(result["vertices"], [f.vertices for f in expected], atol=1e-5)
    np.testing.assert_allclose(result["source_joints"], [f.source_joints for f in expected],
                               atol=1e-5)


@pytest.mark.parametrize("name", ["frames.npy", "frames.npz"])
def test_array_sources_match_the_folder(inputs, folder_run, name):
    out = inputs["dir"] / f"out_{name}"
    assert run("retarget", inputs["dir"] / name, inputs["dir"] / "target.ply", "--out", out,
               "--format", "npz", "--weights", WEIGHTS) == 0
    assert sorted(p.name for p in out.iterdir()) == ["result.npz"]
    np.testing.assert_allclose(load(out / "result.npz")["vertices"],
                               load(folder_run / "result.npz")["vertices"], atol=1e-5)


def test_array_sources_convert_units_at_full_precision(tmp_path):
    """A float64 array's frames are checked, not rounded, before the units' product."""
    frames = np.random.default_rng(0).normal(size=(2, 70, 3)) * 50 + [1e3, 90, 0]     # cm
    np.save(tmp_path / "cm.npy", frames)
    space = make_space("cm")
    for cloud, read in zip(frames, open_source(tmp_path / "cm.npy", space).frames):
        np.testing.assert_array_equal(read, to_canonical(cloud, space))


EAGER = FootLock(plant_speed=50.0, lift_speed=50.0, height_margin=10.0, max_offset=10.0)


PIPELINE_OPTIONS = [
    (("--no-smoothing",), {"smoothing": None}),
    (("--no-foot-lock",), {"foot_lock": None}),
    (("--foot-leash", "0.002"), {"foot_lock": EAGER._replace(max_offset=0.002)}),
    (("--mirror-source",), {"mirror_source": True}),
    (("--no-refine",), {"refine": False}),
    (("--no-denoise",), {"denoise": False})]


@pytest.mark.parametrize("option, setting", PIPELINE_OPTIONS,
                         ids=[" ".join(option) for option, _ in PIPELINE_OPTIONS])
def test_pipeline_options_match_the_python_api(inputs, monkeypatch, option, setting):
    """Each option changes the result as the API's setting does. The feet are held by an
    eager lock here: the tiny model's random toes would never plant with the defaults."""
    option_matches_the_api(inputs, monkeypatch, option, setting, WEIGHTS)


def test_no_rest_pose_matches_the_python_api(inputs, monkeypatch, tmp_path):
    """--no-rest-pose, with tiny weights given the analytic prior and a random rest-pose
    model (the golden tiny weights have neither)."""
    save_weights(tmp_path / "rest.npz", with_rest_pose(load_weights(WEIGHTS)))
    option_matches_the_api(inputs, monkeypatch, ("--no-rest-pose",), {"rest_pose": False},
                           str(tmp_path / "rest.npz"))


@pytest.mark.parametrize("base", ["paper", "fitted"])
def test_presets_match_the_python_api(inputs, monkeypatch, base):
    """--preset NAME is the API's preset; an option changes it as the API's setting does."""
    option_matches_the_api(inputs, monkeypatch, ("--mirror-source",), {"mirror_source": True},
                           WEIGHTS, base)


def test_no_facing_check_matches_the_python_api(inputs, monkeypatch):
    """--no-facing-check. The tiny model's skeletons of the test frames never face away from
    each other, so a stand-in check that moves every skeleton shows whether the check ran."""
    monkeypatch.setattr(stages_module, "_check_facing",
                        lambda reading, points, reference, away, skeleton, trigger, confirm:
                        (reading + 0.01, reference, away))
    option_matches_the_api(inputs, monkeypatch, ("--no-facing-check",),
                           {"facing_check": False}, WEIGHTS)


def option_matches_the_api(inputs, monkeypatch, option, setting, weights,
                           base="regressed"):
    monkeypatch.setitem(PRESETS, base, PRESETS[base].replace(foot_lock=EAGER))
    results = {}
    for options in ((), option):
        out = inputs["dir"] / f"out{''.join(options)}"
        assert run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply",
                   "--out", out, "--format", "npz", "--weights", weights, "--overwrite",
                   "--preset", base, *options) == 0
        results[options] = load(out / "result.npz")
    retargeter = Retargeter.from_weights(weights, PRESETS[base].replace(**setting))
    retargeter.set_target(inputs["target"], inputs["faces"])
    expected = list(retargeter.run(inputs["frames"]))
    for field in ("rotations", "vertices"):
        got = results[option][field]
        np.testing.assert_allclose(got, [getattr(f, field) for f in expected], atol=1e-5)
    assert np.abs(results[option]["rotations"] - results[()]["rotations"]).max() > 1e-4


@pytest.mark.parametrize("options, message", [
    (("--foot-leash", "0"), "--foot-leash: must be positive and finite, got 0"),
    (("--foot-leash", "inf"), "--foot-leash: must be positive and finite, got inf"),
    (("--foot-leash", "0.1", "--no-foot-lock"), "not allowed with argument --foot-leash")])
def test_foot_leash_refuses_bad_settings(inputs, tmp_path, capsys, options, message):
    with pytest.raises(SystemExit) as exit_:
        run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply", "--out",
            tmp_path / "o", "--weights", WEIGHTS, *options)
    assert exit_.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_one_frame_is_one_frame(inputs, tmp_path, capsys):
    np.save(tmp_path / "one.npy", inputs["frames"][:1])
    assert run("retarget", tmp_path / "one.npy", inputs["dir"] / "target.ply", "--out",
               tmp_path / "out", "--format", "npz", "--weights", WEIGHTS) == 0
    assert "retargeted 1 frame at 30 fps" in capsys.readouterr().out


def test_points_over_a_cloud_s_size_is_said(inputs, tmp_path, capsys):
    """Issue 41: --points 4096 on smaller clouds silently did nothing."""
    assert run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply", "--out",
               tmp_path / "out", "--format", "npz", "--points", 200, "--weights", WEIGHTS) == 0
    # (the tiny model's readings of these random clouds also lose the source fit: its
    # warnings name their frames)
    [warning] = [line for line in capsys.readouterr().err.splitlines()
                 if "warning" in line and "--points" in line]
    assert warning.endswith(f"frames.npy: frame 0: {POINTS} points, fewer than --points 200: "
                            "clouds that small are used whole")


def test_points_option_takes_a_seeded_subset(inputs):
    out = inputs["dir"] / "out_points"
    for _ in range(2):                                     # twice: the same bytes of arrays
        assert run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply",
                   "--out", out, "--format", "npz", "--points", 100, "--weights", WEIGHTS,
                   "--overwrite") == 0
        result = load(out / "result.npz")
        if _ == 0:
            first = result
    np.testing.assert_array_equal(first["vertices"], result["vertices"])
    subsets = [frame[np.random.default_rng([0, t]).choice(POINTS, 100, replace=False)]
               for t, frame in enumerate(inputs["frames"])]
    np.testing.assert_allclose(result["source_joints"],
                               [f.source_joints for f in api_result(inputs, subsets)], atol=1e-5)


def test_bvh_source_skips_skr(inputs, folder_run, capsys):
    """Our own result.bvh as a SOURCE: its (canonical-name) joints are the source skeleton
    (the tiny model's, about 3 m tall: --force)."""
    out = inputs["dir"] / "out_bvh"
    assert run("retarget", folder_run / "result.bvh", inputs["dir"] / "target.ply", "--out", out,
               "--format", "npz", "--weights", WEIGHTS, "--force") == 0
    result, previous = load(out / "result.npz"), load(folder_run / "result.npz")
    np.testing.assert_allclose(result["source_joints"], previous["joints"], atol=1e-4)
    capsys.readouterr()
    assert run("retarget", folder_run / "result.bvh", inputs["dir"] / "target.ply", "--out", out,
               "--points", 100, "--weights", WEIGHTS) == 1
    assert "--points applies to point-cloud sources" in capsys.readouterr().err


@needs_cmu(CMU_WALK)
def test_cmu_bvh_source_in_centimetres(inputs, capsys):
    out = inputs["dir"] / "out_cmu"
    assert run("retarget", CMU_WALK, inputs["dir"] / "target.ply", "--out", out, "--format",
               "npz", "--fps", 120, "--weights", WEIGHTS) == 0
    assert f"source: centimetres (detected), Y up (detected), body 1.45 m tall ({CMU_WALK}: " \
        "frame 0)" in capsys.readouterr().out
    result = load(out / "result.npz")
    expected_frames = resample(read_bvh(CMU_WALK), fps=30, source_fps=120).num_frames
    assert result["source_joints"].shape == (expected_frames, NUM_JOINTS, 3)
    assert result["fps"] == 30 and result["units"] == "m"
    assert 0.7 < np.median(result["source_joints"][:, 0, 1]) < 1.0              # pelvis, m


@needs_cmu(CMU_WALK)
@pytest.mark.parametrize("up_axis", ["y", "z"])
def test_cmu_bvh_onto_a_metre_body_with_no_options(tmp_path, capsys, up_axis):
    """Issue 41's first job: a CMU walk (centimetres) onto the sample's target (metres, as a
    Y-up or a Z-up mesh), with the shipped weights and no option: each file's units and axes
    are told apart, the feet stay on the target's floor and the target keeps its height
    (read as one setting, the source was 145 m tall and the result floated 0.44 m up)."""
    _, target, faces, _ = load_sample()
    write_mesh(tmp_path / "target.obj", from_canonical(target, make_space("m", up_axis)), faces)
    assert run("retarget", CMU_WALK, tmp_path / "target.obj", "--out", tmp_path / "out",
               "--format", "npz,bvh") == 0
    out = capsys.readouterr().out
    assert f"target: metres (detected), {up_axis.upper()} up (detected), body 1.50 m" in out
    assert "source: centimetres (detected), Y up (detected), body 1.45 m tall" in out
    result = load(tmp_path / "out" / "result.npz")
    assert result["units"] == "m" and result["up_axis"] == "y"
    np.testing.assert_allclose(result["target_points"], target, atol=1e-6)
    lowest = np.abs(result["vertices"][..., 1].min(axis=1))                 # (T,) metres
    assert np.median(lowest) < 0.03 and lowest.max() < 0.08, lowest
    heights = np.ptp(result["vertices"][..., 1], axis=1)                    # (T,) walking
    assert 0.93 < heights.min() / np.ptp(target[:, 1]) and heights.max() < np.ptp(target[:, 1])
    positions, _ = world_transforms(read_bvh(tmp_path / "out" / "result.bvh"))    # m, Y up
    np.testing.assert_allclose(positions, result["joints"][:, depth_first_order()], atol=1e-4)


def test_a_body_out_of_scale_is_refused_before_writing(inputs, tmp_path, capsys):
    """--units cm on a metre target: refused, nothing written; --force goes on, warning."""
    args = ("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply", "--out",
            tmp_path / "out", "--format", "npz", "--units", "cm", "--weights", WEIGHTS)
    assert run(*args) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "target.ply: the body is 0.018 m (1.8 cm) tall" in err
    assert "looks like metres (use --target-units m" in err and "--force goes on" in err
    assert not (tmp_path / "out").exists()
    assert run(*args, "--force") == 0
    assert "minretarget: warning: " in capsys.readouterr().err
    assert (tmp_path / "out" / "result.npz").exists()


def test_a_mesh_frame_is_a_seeded_even_sample_of_its_surface(tmp_path):
    """A unit square of two triangles whose vertices crowd in a corner (tiny triangles there):
    its points spread evenly, MESH_POINTS of them or --points, the same for a frame however
    a pass starts (--resume)."""
    corner = np.random.default_rng(0).uniform(0, 0.05, (300, 3)) * [1, 1, 0]
    vertices = np.concatenate([[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], corner])
    faces = np.concatenate([[[0, 1, 2], [0, 2, 3]], 4 + np.arange(300).reshape(100, 3)])
    (tmp_path / "frames").mkdir()
    for name in ("a.ply", "b.ply"):
        write_mesh(tmp_path / "frames" / name, vertices, faces)
    clouds = list(open_source(tmp_path / "frames", CANONICAL).frames)
    assert clouds[0].shape == (MESH_POINTS, 3)
    np.testing.assert_allclose(clouds[0].mean(axis=0), [0.5, 0.5, 0], atol=0.03)
    assert not np.array_equal(clouds[0], clouds[1])                 # a fresh draw a frame
    [second] = open_source(tmp_path / "frames", CANONICAL, start=1).frames
    np.testing.assert_array_equal(second, clouds[1])
    assert next(open_source(tmp_path / "frames", CANONICAL, points=100).frames).shape == (100, 3)


def test_mesh_frames_are_sampled_over_their_surface(tmp_path):
    """Issue 41: the demo's own output meshes fed back as a source (vertices crowded at the
    hands and head) had their legs swapped in frames 1 to 6 (ankles 0.2 to 0.6 m from the
    truth, nearer the other ankle's), the vertices taken as an even sampling."""
    source, target, faces, _ = load_sample()
    retargeter = Retargeter.from_weights(warn=False)
    retargeter.set_target(target, faces)
    truth = [frame for frame, _ in zip(retargeter.run(source.frames), range(8))]
    (tmp_path / "meshes").mkdir()
    for t, frame in enumerate(truth):
        write_mesh(tmp_path / "meshes" / f"frame_{t:06d}.ply", frame.vertices, faces)
    write_mesh(tmp_path / "target.ply", target, faces)
    assert run("retarget", tmp_path / "meshes", tmp_path / "target.ply", "--out",
               tmp_path / "out", "--format", "npz") == 0
    seen = load(tmp_path / "out" / "result.npz")["source_joints"]              # (T, J, 3)
    ankles = [JOINT_NAMES.index("left_ankle"), JOINT_NAMES.index("right_ankle")]
    errors = np.linalg.norm(seen[:, ankles] - [frame.joints[ankles] for frame in truth], axis=-1)
    assert errors.max() < 0.1, errors


def test_npz_targets(inputs, folder_run, tmp_path, capsys):
    """Issue 41: a .npz was refused as a target (though a source): a result's target, a
    body's points and faces, one array; the body and faces as from the .ply. One array (no
    faces) gives the same rig, its legs' length (the root's scale) read from its skeleton
    instead of its surface."""
    np.savez(tmp_path / "body.npz", vertices=inputs["target"], faces=inputs["faces"])
    np.savez(tmp_path / "one.npz", inputs["target"])
    np.savez(tmp_path / "two.npz", a=inputs["target"], b=inputs["target"])
    expected = load(folder_run / "result.npz")
    for target in (folder_run / "result.npz", tmp_path / "body.npz", tmp_path / "one.npz"):
        out = tmp_path / target.stem
        assert run("retarget", inputs["dir"] / "frames.npy", target, "--out", out,
                   "--format", "npz", "--weights", WEIGHTS) == 0
        result = load(out / "result.npz")
        for key in ("target_tpose_joints", "target_skin_weights"):
            np.testing.assert_array_equal(result[key], expected[key])
        mesh = target.stem != "one"
        assert np.allclose(result["vertices"], expected["vertices"], atol=1e-5) == mesh
        assert len(result["target_faces"]) == (len(inputs["faces"]) if mesh else 0)
    assert run("retarget", inputs["dir"] / "frames.npy", tmp_path / "two.npz", "--out",
               tmp_path / "x", "--weights", WEIGHTS) == 1
    assert "two.npz: holds a, b; a target .npz holds one (V, 3) array" in capsys.readouterr().err


# ----------------------------------------------------------------------------- outputs

def test_every_output_reads_back(inputs, folder_run):
    result = load(folder_run / "result.npz")
    names = sorted(p.name for p in folder_run.iterdir())
    assert names == sorted([f"frame_{t:06d}.{s}" for t in range(FRAMES) for s in ("ply", "obj")]
                           + ["result.npz", "result.glb", "result.bvh"])
    # PLY and OBJ: the posed target, its faces and vertex order kept.
    for t in range(FRAMES):
        for suffix, tolerance in (("ply", 0), ("obj", 1e-6)):
            vertices, faces = read_points(folder_run / f"frame_{t:06d}.{suffix}")
            np.testing.assert_allclose(vertices, result["vertices"][t], atol=tolerance)
            np.testing.assert_array_equal(faces, inputs["faces"])
    # NPZ: every array, shaped as documented.
    shapes = {"joints": (FRAMES, 22, 3), "rotations": (FRAMES, 22, 4), "root": (FRAMES, 3),
              "source_joints": (FRAMES, 22, 3), "target_points": inputs["target"].shape,
              "target_faces": inputs["faces"].shape, "target_tpose_joints": (22, 3),
              "target_skin_weights": (len(inputs["target"]), 22), "joint_names": (22,)}
    for key, shape in shapes.items():
        assert result[key].shape == shape, key
    np.testing.assert_array_equal(result["target_points"], inputs["target"])
    np.testing.assert_allclose(result["target_skin_weights"].sum(axis=1), 1, atol=1e-5)
    assert tuple(result["joint_names"]) == JOINT_NAMES and result["fps"] == 30
    # BVH: read by our parser, its forward kinematics gives the result's joints.
    motion = read_bvh(folder_run / "result.bvh")
    positions, _ = world_transforms(motion)
    assert motion.num_frames == FRAMES and motion.fps == 30
    np.testing.assert_allclose(positions, result["joints"][:, depth_first_order()], atol=1e-4)
    # GLB: 22 joints, weights summing to 1, one animation, node FK = the result's joints.
    gltf, binary = read_glb(folder_run / "result.glb")
    assert len(gltf["skins"][0]["joints"]) == 22 and len(gltf["animations"]) == 1
    attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
    np.testing.assert_allclose(accessor_array(gltf, binary, attributes["WEIGHTS_0"]).sum(1), 1,
                               atol=1e-6)
    paths = {c["target"]["path"] for c in gltf["animations"][0]["channels"]}
    assert paths == {"rotation", "translation"}
    for t in range(FRAMES):
        world = node_world_matrices(gltf, binary, t)
        np.testing.assert_allclose(world[:, :3, 3], result["joints"][t], atol=1e-5)
    assert len(trimesh.load(folder_run / "result.glb").geometry) == 1


def test_units_and_up_axis_convert_inputs_and_outputs(inputs, folder_run, capsys):
    """The same inputs as millimetre, Z-up files give the same motion: told from the bodies
    with no option, written in metres and +Y up; with the options, written back in
    millimetres and Z-up (the glb stays metres and Y-up)."""
    space = make_space("mm", "z")
    folder = inputs["dir"] / "mm_z"
    folder.mkdir()
    write_mesh(folder / "target.ply", from_canonical(inputs["target"], space), inputs["faces"])
    np.save(folder / "frames.npy", from_canonical(inputs["frames"], space))
    assert run("retarget", folder / "frames.npy", folder / "target.ply", "--out",
               folder / "detected", "--format", "npz,bvh", "--weights", WEIGHTS) == 0
    assert capsys.readouterr().out.splitlines()[:2] == [
        f"target: millimetres (detected), Z up (detected), body 1.80 m tall "
        f"({folder / 'target.ply'})",
        f"source: millimetres (detected), Z up (detected), body "
        f"{np.ptp(inputs['frames'][0, :, 1]):.2f} m tall "
        f"({folder / 'frames.npy'}: frame 0)"]
    detected = load(folder / "detected" / "result.npz")
    assert detected["units"] == "m" and detected["up_axis"] == "y"
    positions, _ = world_transforms(read_bvh(folder / "detected" / "result.bvh"))  # m, Y up
    np.testing.assert_allclose(positions, detected["joints"][:, depth_first_order()],
                               atol=1e-4)               # issue 41: written Z-up like its input
    np.testing.assert_allclose(detected["vertices"], load(folder_run / "result.npz")["vertices"],
                               atol=1e-4)
    out = folder / "out"
    assert run("retarget", folder / "frames.npy", folder / "target.ply", "--out", out,
               "--format", "ply,npz,glb,bvh", "--units", "mm", "--up-axis", "z",
               "--out-units", "mm", "--out-up", "z", "--weights", WEIGHTS) == 0
    assert "target: millimetres (given), Z up (given)" in capsys.readouterr().out
    metres, mm = load(folder_run / "result.npz"), load(out / "result.npz")
    assert mm["units"] == "mm" and mm["up_axis"] == "z"
    for key in ("vertices", "joints", "root", "source_joints", "target_points",
                "target_tpose_joints"):
        np.testing.assert_allclose(to_canonical(mm[key], space), metres[key], atol=1e-4,
                                   err_msg=key)
    np.testing.assert_allclose(rotations_to_canonical(mm["rotations"], space),
                               metres["rotations"], atol=1e-4)
    np.testing.assert_allclose(read_points(out / "frame_000003.ply")[0], mm["vertices"][3],
                               atol=1e-3)
    positions, _ = world_transforms(read_bvh(out / "result.bvh"))            # mm, Z up
    np.testing.assert_allclose(positions, mm["joints"][:, depth_first_order()], atol=0.1)
    glb_mm, glb_m = read_glb(out / "result.glb"), read_glb(folder_run / "result.glb")
    position = glb_m[0]["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    np.testing.assert_allclose(accessor_array(*glb_mm, position),
                               accessor_array(*glb_m, position), atol=1e-6)


@pytest.mark.parametrize("command", ["retarget", "demo"])
def test_blas_runs_one_thread_unless_told(monkeypatch, command):
    """Every BLAS library, SciPy's that the kernels call included, for the command's run only
    (issue 41: two busy-waiting threads made a run on a shared machine 3 to 4 times slower)."""
    from threadpoolctl import threadpool_info

    def blas():
        return {(info["filepath"], info["num_threads"]) for info in threadpool_info()
                if info["user_api"] == "blas"}
    seen = []
    monkeypatch.setattr(cli, f"_{command}", lambda args: seen.append(blas()))
    before = blas()
    inputs = ("a.npy", "b.ply", "--out", "o") if command == "retarget" else ()
    for extra in ((), ("--threads", "3")):
        assert run(command, *inputs, *extra) == 0
    assert [{threads for _, threads in libraries} for libraries in seen] == [{1}, {3}]
    import scipy.linalg.cython_blas  # noqa: F401  (numba's BLAS: loaded, and limited, by then)
    after = blas()
    assert {path for path, _ in seen[0]} == {path for path, _ in after}
    assert after >= before                                     # the limits are lifted


def test_first_compile_is_said_once_before_the_progress_bar(inputs, monkeypatch, tmp_path,
                                                             capsys):
    """Issue 41: a cold cache showed as "1/68 [00:57<1:03:50, 57.17s/frame]" and no word.
    Here the warm-up compiles two new kernels (cached or not, numba compiles those)."""
    assert run("warmup", "--weights", WEIGHTS) == 0
    assert "kernels ready in" in capsys.readouterr().out
    warm_up = Retargeter.warm_up

    def compiling_warm_up(self, skeleton=False):
        numba.njit(lambda x: x + 1)(1)
        numba.njit(lambda x: x + 2)(1)
        warm_up(self, skeleton)
    args = ("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply",
            "--format", "npz", "--weights", WEIGHTS)
    assert run(*args, "--out", tmp_path / "warm") == 0
    assert cli.COMPILING not in capsys.readouterr().err
    monkeypatch.setattr(Retargeter, "warm_up", compiling_warm_up)
    assert run(*args, "--out", tmp_path / "cold") == 0
    err = capsys.readouterr().err
    assert err.count(cli.COMPILING) == 1
    assert err.index(cli.COMPILING) < err.index("retargeting:")


# ----------------------------------------------------------------------------- render, demo

def test_render_png_and_gif(folder_run, capsys):
    from PIL import Image
    assert run("render", folder_run / "result.npz", "--out", folder_run / "strip.png") == 0
    assert run("render", folder_run / "result.npz", "--out", folder_run / "anim.gif") == 0
    with Image.open(folder_run / "strip.png") as image:
        assert image.format == "PNG" and image.width > image.height
    with Image.open(folder_run / "anim.gif") as image:
        assert image.format == "GIF" and image.n_frames == FRAMES
    assert "drew 6 frames" in capsys.readouterr().out


def test_render_shades_the_surface(folder_run, tmp_path):
    """Issue 41: the preview drew the result's vertices as dots; a mesh is now a surface (a
    point cloud still dots), filling its outline."""
    from PIL import Image
    with np.load(folder_run / "result.npz", allow_pickle=False) as data:
        result = dict(data)                     # the target standing still (the tiny model's
    result["vertices"][:] = result["target_points"]            # poses crumple it), its
    result["joints"][:] = result["target_tpose_joints"]        # skeleton in it
    np.savez(tmp_path / "mesh.npz", **result)
    np.savez(tmp_path / "cloud.npz", **{**result, "target_faces": np.empty((0, 3), np.int64)})

    def inked(name):                  # the fraction of the result row in grey (not skeleton)
        assert run("render", tmp_path / name, "--out", tmp_path / "strip.png") == 0
        with Image.open(tmp_path / "strip.png") as image:
            rgb = np.asarray(image.convert("RGB"), dtype=int)[image.height // 2:]
        return ((np.ptp(rgb, axis=-1) < 12) & (rgb.max(axis=-1) < 235)).mean()
    assert inked("mesh.npz") > inked("cloud.npz") + 0.05         # about 0.13 against 0.05


def test_render_refuses_a_malformed_result(folder_run, tmp_path, capsys):
    with np.load(folder_run / "result.npz", allow_pickle=False) as data:
        good = {key: data[key] for key in data.files}
    cases = {"fps": (dict(fps=np.array(0.0)), "fps must be positive and finite, got 0.0"),
             "flat": (dict(joints=good["joints"][..., :2]),
                      r"joints must have shape (any, 22, 3), got (6, 22, 2)"),
             "short": (dict(joints=good["joints"][:3]), "with one T"),
             "units": (dict(units=np.array("furlong")), "units must be one of m, cm, mm"),
             "faces": (dict(target_faces=good["target_faces"] + 10**6),
                       "target_faces must be (F, 3) indices of its vertices")}
    for name, (change, message) in cases.items():
        np.savez(tmp_path / f"{name}.npz", **{**good, **change})
        assert run("render", tmp_path / f"{name}.npz", "--out", tmp_path / "x.png") == 1
        err = capsys.readouterr().err
        assert err.startswith(f"minretarget: error: {tmp_path / name}.npz: ") and message in err
        assert err.count("\n") == 1, err
    (tmp_path / "text.npz").write_text("not an archive")
    assert run("render", tmp_path / "text.npz", "--out", tmp_path / "x.png") == 1
    assert "not a readable .npz (File is not a zip file)" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_negative_seed_is_refused_by_name(inputs, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply", "--out",
            tmp_path / "o", "--seed", "-1")
    assert exit_.value.code == 2
    assert capsys.readouterr().err == ("minretarget retarget: error: argument --seed: must be at "
                                       "least 0, got -1 (see minretarget retarget --help)\n")
    assert not (tmp_path / "o").exists()
    with pytest.raises(SystemExit):                  # --points, not the source, is too small
        run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply", "--out",
            tmp_path / "o", "--points", "10")
    assert "argument --points: must be at least 64, got 10" in capsys.readouterr().err


@pytest.fixture
def tiny_sample(inputs, tmp_path, monkeypatch):
    """The demo on a 4-frame sample of the shipped sample's layout."""
    path = tmp_path / "sample.npz"
    np.savez(path, source_points=inputs["frames"][:4].astype(np.float16),
             target_points=inputs["target"], target_faces=inputs["faces"].astype(np.uint16),
             fps=np.array(30), metadata=np.array(json.dumps({"description": "tiny"})))
    monkeypatch.setattr(cli, "load_sample", lambda start=0: load_sample(path, start=start))
    return path


def test_demo_writes_every_output_and_a_preview(tiny_sample, tmp_path, capsys):
    out = tmp_path / "demo"
    assert run("demo", "--out", out, "--weights", WEIGHTS) == 0
    names = {p.name for p in out.iterdir()}
    assert {"result.npz", "result.glb", "result.bvh", "preview.png", "frame_000003.ply",
            "frame_000003.obj", cli.DEMO_MARK} <= names and len(names) == 4 * 2 + 5
    assert "demo: tiny" in capsys.readouterr().out


def test_demo_replaces_a_demo_only(inputs, tiny_sample, tmp_path, capsys):
    out = tmp_path / "demo"
    assert run("demo", "--out", out, "--weights", WEIGHTS) == 0
    first = (out / "result.npz").read_bytes()
    (out / "result.npz").write_bytes(b"spoilt")
    assert run("demo", "--out", out, "--weights", WEIGHTS) == 0       # its own: replaced
    assert (out / "result.npz").read_bytes() == first
    assert not (out / ".previous_run").exists()

    def refused(folder, holding, named=None):
        assert run("demo", "--out", folder, "--weights", WEIGHTS) == 1
        err = capsys.readouterr().err
        assert f"{named or folder}: holds the files of a run that is not a demo's ({holding})" \
            in err

    other = tmp_path / "other"
    other.mkdir()
    (other / "result.npz").write_bytes(b"a user's result")
    refused(other, "result.npz")
    assert [p.name for p in other.iterdir()] == ["result.npz"]
    assert (other / "result.npz").read_bytes() == b"a user's result"
    # A run that replaced a demo's is not a demo's, nor is one a failed replacement kept.
    assert run("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply",
               "--out", out, "--format", "npz", "--weights", WEIGHTS, "--overwrite") == 0
    replaced = (out / "result.npz").read_bytes()
    refused(out, "result.npz")
    (out / ".previous_run").mkdir()
    (out / "result.npz").rename(out / ".previous_run" / "result.npz")
    refused(out, "result.npz", named=out / ".previous_run")
    assert (out / ".previous_run" / "result.npz").read_bytes() == replaced


def test_demo_without_default_weights_says_what_to_do(tiny_sample, tmp_path, monkeypatch,
                                                       capsys):
    monkeypatch.setattr(cli, "DEFAULT_WEIGHTS", tmp_path / "absent.npz")
    assert run("demo", "--out", tmp_path / "demo") == 1
    err = capsys.readouterr().err
    assert "default weights are not installed" in err and "--weights" in err
    assert "Traceback" not in err


def test_shipped_sample():
    assert SAMPLE.stat().st_size < 3_000_000
    source, target_points, target_faces, metadata = load_sample()
    assert source.count >= 60 and source.fps == 30 and source.kind == "points"
    frames = list(source.frames)
    assert len(frames) == source.count and frames[0].shape == (2048, 3)
    assert frames[0].dtype == np.float32 and np.isfinite(frames).all()
    assert target_faces.max() < len(target_points) and target_points[:, 1].min() == 0
    assert "mocap.cs.cmu.edu" in metadata["licences"] and metadata["description"]


# ----------------------------------------------------------------------------- messages

def test_bad_input_gives_one_line_naming_the_file(inputs, tmp_path, capsys):
    np.save(tmp_path / "flat.npy", np.zeros((5, 3)))
    (tmp_path / "broken.npz").write_bytes(b"PK not really a zip")
    np.savez(tmp_path / "two.npz", a=np.zeros((2, 70, 3)), b=np.zeros((2, 70, 3)))
    cases = [(["retarget", tmp_path / "nowhere", inputs["dir"] / "target.ply"], "nowhere"),
             (["retarget", inputs["dir"] / "frames.npy", tmp_path / "flat.npy"],
              "flat.npy: the target has 5 points"),
             (["retarget", tmp_path / "flat.npy", inputs["dir"] / "target.ply"], "flat.npy"),
             (["retarget", tmp_path / "broken.npz", inputs["dir"] / "target.ply"],
              "broken.npz: not a readable .npz"),
             (["retarget", tmp_path / "two.npz", inputs["dir"] / "target.ply"],
              "holds a, b; expected one array"),
             (["retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply",
               "--format", "ply,fbx"], "fbx"),
             (["render", tmp_path / "flat.npy", "--out", tmp_path / "x.jpg"], ".png or a .gif")]
    for args, message in cases:
        code = run(*args, *(["--out", tmp_path / "o", "--weights", WEIGHTS]
                            if args[0] == "retarget" else []))
        err = capsys.readouterr().err
        assert code == 1 and message in err and "Traceback" not in err, (args, err)
        assert err.startswith("minretarget: error:") and err.count("\n") == 1


def test_out_naming_a_file_and_a_failure_before_and_after_frames(inputs, tmp_path, capsys,
                                                                  monkeypatch):
    """Issue 41: --out naming a file printed "[Errno 17]"; a failure at frame 0 left an empty
    --out; a failure midway did not say --resume."""
    (tmp_path / "file").write_text("a user's")
    args = ("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply", "--format",
            "npz", "--weights", WEIGHTS, "--out")
    assert run(*args, tmp_path / "file") == 1
    assert "file: is a file; --out names the folder the outputs go into" in \
        capsys.readouterr().err
    step = Retargeter.step

    def failing(after):
        def fail(self, points):
            if (0 if self.state is None else self.state.frames_seen) >= after:
                raise ValueError("a damaged frame")
            return step(self, points)
        return fail
    monkeypatch.setattr(Retargeter, "step", failing(0))
    assert run(*args, tmp_path / "new") == 1
    assert "frame 0: a damaged frame" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    monkeypatch.setattr(Retargeter, "step", failing(3))
    assert run(*args, tmp_path / "new") == 1
    assert capsys.readouterr().err.endswith("frame 3: a damaged frame; the 3 frames done are "
                                            "kept: fix it, then add --resume to continue\n")
    monkeypatch.setattr(Retargeter, "step", step)
    assert run(*args, tmp_path / "new", "--resume") == 0


MISSING_EXTRA = """
import runpy, sys
# A None entry makes every import of the module fail, importlib's included.
for name in ("trimesh", "matplotlib", "torch", "training"):
    sys.modules[name] = None
sys.argv = ["minretarget"] + sys.argv[1:]
runpy.run_module("minretarget", run_name="__main__")
"""


def test_missing_cli_extra_is_a_message_not_a_traceback(inputs, tmp_path):
    def command(*args):
        return subprocess.run([sys.executable, "-c", MISSING_EXTRA, *map(str, args)],
                              capture_output=True, text=True, cwd=ROOT, timeout=300,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})

    # .npy in, npz/glb/bvh out: none of the extra's file libraries, no torch, no training/.
    ok = command("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.npy",
                 "--out", tmp_path / "a", "--format", "npz,glb,bvh", "--weights", WEIGHTS)
    assert ok.returncode == 0, ok.stderr
    assert {p.name for p in (tmp_path / "a").iterdir()} == {"result.npz", "result.glb",
                                                            "result.bvh"}
    blocked = command("retarget", inputs["dir"] / "frames.npy", inputs["dir"] / "target.ply",
                      "--out", tmp_path / "b", "--weights", WEIGHTS)
    assert blocked.returncode == 3
    assert "'trimesh'" in blocked.stderr and 'pip install "minretarget[cli]"' in blocked.stderr
    assert "Traceback" not in blocked.stderr
    assert not (tmp_path / "b").exists() or not any((tmp_path / "b").iterdir())


def test_shipped_bodies_are_listed_and_taken_by_name(inputs, tmp_path, capsys):
    """Issue 41: nothing shipped a body to retarget onto."""
    from minretarget.bodies import BODIES, body_names, shipped_body
    from minretarget.validation import body_problems
    assert BODIES.stat().st_size < 1_500_000
    assert run("bodies") == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == list(body_names()) and len(lines) >= 4
    for name in body_names():
        points, faces = shipped_body(name)
        assert body_problems(points, name, tpose=True) == [], name     # human, Y up, T-pose
        assert points[:, 1].min() == pytest.approx(0, abs=1e-6) and faces.max() < len(points)
    assert run("retarget", inputs["dir"] / "frames.npy", "child", "--out", tmp_path / "out",
               "--format", "npz", "--weights", WEIGHTS) == 0
    np.testing.assert_array_equal(load(tmp_path / "out" / "result.npz")["target_points"],
                                  shipped_body("child")[0])
    assert run("retarget", inputs["dir"] / "frames.npy", "chlid", "--out", tmp_path / "x",
               "--weights", WEIGHTS) == 1
    assert "chlid: no such file, nor a shipped body (child, " in capsys.readouterr().err


def test_viewpoint_is_the_api_s_in_the_source_s_units(inputs, tmp_path, capsys):
    """--viewpoint X,Y,Z, in the source's units and axes as its points are, is
    ``Retargeter.step``'s viewpoint in canonical metres; the fitted preset (the default)."""
    centimetres = make_space("cm", "y")
    frames = inputs["frames"].astype(np.float64) * 100
    camera = frames[0].mean(axis=0) + [30.0, 20.0, 250.0]
    np.save(tmp_path / "cm.npy", frames.astype(np.float32))
    results = {}
    for options in ((), ("--viewpoint", ",".join(f"{v:.9g}" for v in camera))):
        out = tmp_path / f"out{len(options)}"
        assert run("retarget", tmp_path / "cm.npy", inputs["dir"] / "target.ply", "--out", out,
                   "--format", "npz", "--weights", WEIGHTS, "--source-units", "cm",
                   *options) == 0
        results[len(options)] = load(out / "result.npz")
    retargeter = Retargeter.from_weights(WEIGHTS)
    retargeter.set_target(inputs["target"], inputs["faces"])
    viewpoint = to_canonical(np.array([f"{v:.9g}" for v in camera], np.float64), centimetres)
    expected = [retargeter.step(to_canonical(frame.astype(np.float32), centimetres), viewpoint)
                for frame in frames]
    np.testing.assert_allclose(results[2]["vertices"], [f.vertices for f in expected],
                               atol=1e-5)
    assert np.abs(results[2]["source_joints"] - results[0]["source_joints"]).max() > 1e-4


@pytest.mark.parametrize("options, source, message", [
    (("--viewpoint", "0,1,2.5", "--preset", "regressed"), "frames.npy",
     "--viewpoint is read by the source fit, which --preset regressed does not run"),
    (("--viewpoint", "0,1,2.5", "--force"), "result.bvh", "and this source is a skeleton"),
    (("--viewpoint", "0,1"), "frames.npy", "--viewpoint: must be three numbers X,Y,Z"),
    (("--viewpoint", "0,1,nan"), "frames.npy", "--viewpoint: must be three numbers X,Y,Z")])
def test_viewpoint_refuses_what_cannot_use_it(inputs, folder_run, tmp_path, capsys, options,
                                              source, message):
    source = folder_run / source if source.endswith(".bvh") else inputs["dir"] / source
    try:
        code = run("retarget", source, inputs["dir"] / "target.ply", "--out",
                   tmp_path / "o", "--weights", WEIGHTS, *options)
    except SystemExit as exit_:
        code = exit_.code
    assert code in (1, 2) and message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
