"""SKR's online frames (training.data.online) against the numpy build, and SKR trained from a
data pack (training.data.pack): twin poses, area-uniform points, exact resume. No anny: the
bodies are synthetic meshes, a small triangle riding each joint."""
import dataclasses
import hashlib
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from minretarget.conventions import NUM_JOINTS  # noqa: E402
import training.train  # noqa: E402
from test_training import (TINY_RECIPE, random_quaternions, skeleton,  # noqa: E402
                           write_datasets)
from training.data.bodies import Body, pose_body  # noqa: E402
from training.data.cmu import Motion  # noqa: E402
from training.data.datasets import BuildConfig, Frames, skr_poses  # noqa: E402
from training.data.online import OnlineFrames, surface_points  # noqa: E402
from training.data.pack import load_pack, pack_arrays, write_pack  # noqa: E402
from training.recipe import load_recipe  # noqa: E402
from training.train import (ONLINE_FRAMES, main, online_config,  # noqa: E402
                            online_skr_data, provenance)

ACTOR_HIP_HEIGHT = 0.9
CONFIG = BuildConfig(seated_fraction=0.3, crossed_fraction=0.3)


def synthetic_body(rng, name, height):
    """A skeleton with a 5 cm triangle at each joint, skinned wholly to that joint."""
    joints = skeleton(rng, height)
    corners = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0]], np.float32)
    vertices = (joints[:, None] + corners).reshape(-1, 3)
    faces = np.arange(3 * NUM_JOINTS, dtype=np.int32).reshape(-1, 3)
    weights = np.repeat(np.eye(NUM_JOINTS, dtype=np.float32), 3, axis=0)
    return Body(name=name, phenotype={"height": height}, vertices=vertices, faces=faces,
                joints=joints, weights=weights)


def synthetic_motion(rng, name, frames):
    root = np.cumsum(rng.normal(0, 0.02, (frames, 3)), axis=0) + [0, ACTOR_HIP_HEIGHT, 0]
    return Motion(name=name, rotations=random_quaternions(rng, (frames, NUM_JOINTS)),
                  root=root.astype(np.float32), fps=30, category="walk", source_fps=120.0)


@pytest.fixture(scope="module")
def synthetic():
    rng = np.random.default_rng(0)
    bodies = {"train": [synthetic_body(rng, f"b{i}", 0.8 + 0.1 * i) for i in range(3)],
              "val": [synthetic_body(rng, "v0", 0.95)]}
    bodies["val"][0] = Body(**{**bodies["val"][0].__dict__, "faces": bodies["train"][0].faces,
                               "weights": bodies["train"][0].weights})
    motions = {"train": [synthetic_motion(rng, "t0", 40), synthetic_motion(rng, "t1", 30)],
               "val": [synthetic_motion(rng, "v0", 20)], "test": []}
    return motions, bodies


def test_surface_points_are_area_uniform_on_the_mesh():
    # Two triangles in the z = 0 plane, of areas 0.5 and 1.5.
    vertices = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0],
                              [2, 0, 0], [5, 0, 0], [2, 1, 0]]]).repeat(2, 1, 1)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    points = surface_points(vertices, faces, 20_000, torch.Generator().manual_seed(0))
    assert points.shape == (2, 20_000, 3)
    assert torch.all(points[..., 2] == 0)
    second = points[..., 0] >= 2
    assert abs(float(second.float().mean()) - 0.75) < 0.01
    x, y = points[..., 0], points[..., 1]
    inside_first = (x >= 0) & (y >= 0) & (x + y <= 1 + 1e-6)
    inside_second = (x >= 2) & (y >= 0) & ((x - 2) / 3 + y <= 1 + 1e-6)
    assert torch.all(inside_first | inside_second)
    # Uniform within a triangle: the mean is its centroid.
    np.testing.assert_allclose(points[~second].mean(0).numpy(), [1 / 3, 1 / 3, 0], atol=0.01)
    np.testing.assert_allclose(points[second].mean(0).numpy(), [3, 1 / 3, 0], atol=0.02)


def test_online_frames_draw_and_pose_as_the_numpy_build(synthetic):
    motions, bodies = synthetic
    online = OnlineFrames(motions["train"], bodies["train"], ACTOR_HIP_HEIGHT, CONFIG, "cpu")
    body, rotations, root = online.poses(16, np.random.default_rng(5))
    expected = skr_poses(Frames.of(motions["train"]), bodies["train"], 16, ACTOR_HIP_HEIGHT,
                         np.random.default_rng(5), CONFIG.max_shift, CONFIG.category_power,
                         CONFIG.seated_fraction, CONFIG.crossed_fraction)
    for got, want in zip((body, rotations, root), expected):
        np.testing.assert_array_equal(got, want)
    vertices, joints = online.pose(body, rotations, root)
    for i in range(16):
        twin_vertices, twin_joints = pose_body(bodies["train"][body[i]], rotations[i], root[i])
        np.testing.assert_allclose(vertices[i].numpy(), twin_vertices, atol=2e-6)
        np.testing.assert_allclose(joints[i].numpy(), twin_joints, atol=2e-6)
    batch = online.batch(16, 30, np.random.default_rng(5), torch.Generator().manual_seed(1))
    np.testing.assert_array_equal(batch["joints"].numpy(), joints.numpy())
    chunked = online.clouds(body, rotations, root, 30, torch.Generator().manual_seed(1), chunk=5)
    np.testing.assert_array_equal(chunked["joints"].numpy(), joints.numpy())
    # Every point lies on the triangle of some joint: within its 5 cm of that joint.
    distance = (batch["points"][:, :, None] - joints[:, None]).norm(dim=-1).min(-1).values
    assert batch["points"].shape == (16, 30, 3) and float(distance.max()) <= 0.05 + 1e-5


def test_online_frames_need_one_mesh_topology(synthetic):
    motions, bodies = synthetic
    other = Body(**{**bodies["train"][1].__dict__, "weights": bodies["train"][1].weights[::-1]})
    with pytest.raises(ValueError, match="body b1 has other faces or skinning weights"):
        OnlineFrames(motions["train"], [bodies["train"][0], other], ACTOR_HIP_HEIGHT, CONFIG,
                     "cpu")


def test_skr_trains_on_a_pack_and_resumes_to_the_same_weights(synthetic, tmp_path,
                                                             monkeypatch, capsys):
    motions, bodies = synthetic
    monkeypatch.setattr(training.train, "VALIDATION_LIMIT", 100)   # frames drawn to validate
    write_pack(tmp_path / "pack.npz", pack_arrays(motions, ACTOR_HIP_HEIGHT, bodies, False))
    write_datasets(tmp_path, np.random.default_rng(0))     # the T-pose frames (skr_tpose_*)
    for name in ("skr_train", "skr_val"):                  # never read with a pack
        (tmp_path / f"{name}.npz").unlink()
    (tmp_path / "tiny.json").write_text(json.dumps(TINY_RECIPE))

    def train(out, *extra):
        main(["skr", "--recipe", str(tmp_path / "tiny.json"), "--data", str(tmp_path),
              "--pack", str(tmp_path / "pack.npz"), "--out", str(tmp_path / out),
              "--threads", "1", *extra])
        return torch.load(tmp_path / out / "skr.pt", weights_only=True)
    whole = train("whole")
    assert whole["step"] == 6 and len(whole["rows"]) == 2
    assert all(np.isfinite(row["val_mpjpe"]) and row["val_mpjpe"] > 0 for row in whole["rows"])
    train("resumed", "--stop-at", "4")
    resumed = train("resumed", "--resume")
    for key, value in whole["modules"]["skr"].items():
        torch.testing.assert_close(resumed["modules"]["skr"][key], value, msg=key)
    # A resume on other frames than the checkpoint's (here: the built ones) is refused.
    train("switched", "--stop-at", "4")
    (tmp_path / "built").mkdir()
    write_datasets(tmp_path / "built", np.random.default_rng(0))
    with pytest.raises(SystemExit):
        main(["skr", "--recipe", str(tmp_path / "tiny.json"), "--data", str(tmp_path / "built"),
              "--out", str(tmp_path / "switched"), "--resume"])
    assert "skr.pt trained on frames drawn from pack" in capsys.readouterr().err
    for stage, pack in (("skr", "tiny.json"), ("smrm", "pack.npz")):
        with pytest.raises(SystemExit):
            main([stage, "--recipe", str(tmp_path / "tiny.json"), "--data", str(tmp_path),
                  "--pack", str(tmp_path / pack), "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad" / "smrm.pt").exists()


def test_weights_trained_on_a_pack_record_it(synthetic, tmp_path):
    motions, bodies = synthetic
    write_pack(tmp_path / "pack.npz", pack_arrays(motions, ACTOR_HIP_HEIGHT, bodies, False))
    recorded = provenance(load_recipe("cpu"), tmp_path, pack=load_pack(tmp_path / "pack.npz"))
    digest = hashlib.sha256((tmp_path / "pack.npz").read_bytes()).hexdigest()
    assert recorded["data"]["skr_online_pack"] == {
        "sha256": digest, "motions": {"train": 2, "val": 1}, "bodies": {"train": 3, "val": 1},
        "include_broken": False, "keep_broken_ankles": False,
        "config": dataclasses.asdict(BuildConfig())}


def test_online_config_changes_only_the_named_draws():
    config = online_config(["crossed_fraction=0.15", "category_power=0.5"])
    assert config == dataclasses.replace(ONLINE_FRAMES, crossed_fraction=0.15,
                                         category_power=0.5)
    assert online_config([]) == ONLINE_FRAMES
    for bad, message in (("frames=10", "KEY one of max_shift"), ("crossed_fraction", "KEY=VALUE"),
                         ("crossed_fraction=lots", "'lots' is not a number"),
                         ("crossed_fraction=1.5", "crossed_fraction must be in")):
        with pytest.raises(ValueError, match=message):
            online_config([bad])


def test_online_draws_change_training_frames_and_never_validation(synthetic, tmp_path,
                                                                 monkeypatch, capsys):
    """--online crossed_fraction=1: the training draws cross legs, validation's frames stay
    the default's, the weights record it, and a resume without it is refused."""
    motions, bodies = synthetic
    monkeypatch.setattr(training.train, "VALIDATION_LIMIT", 50)
    write_pack(tmp_path / "pack.npz", pack_arrays(motions, ACTOR_HIP_HEIGHT, bodies, False))
    pack = load_pack(tmp_path / "pack.npz")
    crossed = online_config(["crossed_fraction=1"])
    plain_train, plain_val = online_skr_data(pack, "cpu")
    crossed_train, crossed_val = online_skr_data(pack, "cpu", crossed)
    for key in ("points", "joints"):
        torch.testing.assert_close(crossed_val[key], plain_val[key])
    assert (crossed_train.config, plain_train.config) == (crossed, ONLINE_FRAMES)
    draws = [frames.poses(20, np.random.default_rng(5))[1] for frames in (plain_train,
                                                                          crossed_train)]
    assert not np.allclose(*draws)
    recorded = provenance(load_recipe("cpu"), tmp_path, pack=pack, online=crossed)
    assert recorded["data"]["skr_online_pack"]["config"]["crossed_fraction"] == 1.0

    write_datasets(tmp_path, np.random.default_rng(0))     # the T-pose frames (skr_tpose_*)
    (tmp_path / "tiny.json").write_text(json.dumps(TINY_RECIPE))
    common = ["skr", "--recipe", str(tmp_path / "tiny.json"), "--data", str(tmp_path),
              "--pack", str(tmp_path / "pack.npz"), "--out", str(tmp_path / "run"),
              "--threads", "1"]
    main(common + ["--online", "crossed_fraction=1", "--stop-at", "2"])
    with pytest.raises(SystemExit):
        main(common + ["--resume"])
    assert "with crossed_fraction=1, this run on frames drawn from pack" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(common[:5] + common[7:] + ["--online", "crossed_fraction=1"])   # no --pack
    assert "--online changes the frames drawn from a pack" in capsys.readouterr().err


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (a GPU session)")
def test_online_frames_on_cuda_match_the_cpu(synthetic):
    """Run first on a GPU machine: the same draws posed on CUDA and on the CPU."""
    motions, bodies = synthetic
    on = {device: OnlineFrames(motions["train"], bodies["train"], ACTOR_HIP_HEIGHT, CONFIG,
                               device) for device in ("cpu", "cuda")}
    poses = on["cpu"].poses(16, np.random.default_rng(3))
    vertices = {device: frames.pose(*poses)[0].cpu() for device, frames in on.items()}
    torch.testing.assert_close(vertices["cuda"], vertices["cpu"], atol=1e-5, rtol=0)
    batch = on["cuda"].clouds(*poses, 30, torch.Generator("cuda").manual_seed(0), chunk=5)
    assert batch["points"].device.type == "cuda" and batch["points"].shape == (16, 30, 3)
