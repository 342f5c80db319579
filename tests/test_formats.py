"""File formats of the command line: each writer against a reader, units and axes, skeleton
mapping, natural order, the optional-dependency message."""
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minretarget.bvh import (BVHMotion, format_bvh, parse_bvh, read_bvh, world_transforms,
                             write_bvh)
from minretarget.conventions import JOINT_NAMES, NUM_JOINTS
from minretarget.extras import MissingExtra, require
from minretarget.formats.mesh import read_points, write_mesh
from minretarget.formats.npz import NpzFrames, NpzWriter
from minretarget.kinematics import forward_kinematics
from minretarget.skeletons import (MIXAMO_BONES, canonical_world, depth_first_order,
                                   find_skeleton, rig_to_bvh)
from minretarget.sources import frame_files, natural_key
from minretarget.units import (from_canonical, make_space, rotations_from_canonical,
                               rotations_to_canonical, to_canonical)

trimesh = pytest.importorskip("trimesh")


def random_rig(frames=5, seed=0):
    """T-pose joints (J, 3), unit quaternions (T, J, 4), root (T, 3), float32, metres."""
    rng = np.random.default_rng(seed)
    tpose = rng.normal(0, 0.3, (NUM_JOINTS, 3)).astype(np.float32)
    q = rng.normal(size=(frames, NUM_JOINTS, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return tpose, q.astype(np.float32), rng.normal(0, 1, (frames, 3)).astype(np.float32)


# ----------------------------------------------------------------------------- units and axes

@pytest.mark.parametrize("units", ["m", "cm", "mm"])
@pytest.mark.parametrize("up_axis", ["y", "z"])
def test_units_and_axes_round_trip(units, up_axis):
    space = make_space(units, up_axis)
    points = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    np.testing.assert_allclose(to_canonical(from_canonical(points, space), space), points,
                               atol=1e-6)


def test_z_up_means_facing_minus_y_and_scale():
    space = make_space("mm", "z")
    # A file point 1700 mm up and 100 mm toward -Y (the body's front) is 1.7 m up, 0.1 m at +Z.
    np.testing.assert_allclose(to_canonical([[50.0, -100.0, 1700.0]], space),
                               [[0.05, 1.7, 0.1]], atol=1e-6)
    assert np.linalg.det(space.axes) == pytest.approx(1.0)


def test_rotations_follow_the_axes():
    """FK in the file's axes with converted rotations gives the converted joints."""
    tpose, q, root = random_rig()
    space = make_space("cm", "z")
    joints, _ = forward_kinematics(q, root, tpose)
    file_joints, _ = forward_kinematics(rotations_from_canonical(q, space),
                                        from_canonical(root, space), from_canonical(tpose, space))
    np.testing.assert_allclose(file_joints, from_canonical(joints, space), atol=1e-3)  # cm
    np.testing.assert_allclose(rotations_to_canonical(rotations_from_canonical(q, space), space),
                               q, atol=1e-6)


def test_bad_units_name_the_value():
    with pytest.raises(ValueError, match="'km'"):
        make_space("km", "y")
    with pytest.raises(ValueError, match="'x'"):
        make_space("m", "x")


# ----------------------------------------------------------------------------- point files

def test_natural_sort_order(tmp_path):
    names = ["frame10.ply", "frame2.npy", "frame1.xyz", "Frame3.obj", "frame100.npy",
             "frame20.NPY", ".frame0.npy", "notes.txt"]
    for name in names:
        (tmp_path / name).write_text("")
    assert [p.name for p in frame_files(tmp_path)] == [
        "frame1.xyz", "frame2.npy", "Frame3.obj", "frame10.ply", "frame20.NPY", "frame100.npy"]
    assert sorted(["a10b2", "a9b10", "a10b10"], key=natural_key) == ["a9b10", "a10b2", "a10b10"]


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_mesh_round_trip_keeps_order_and_faces(tmp_path, suffix):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(1)
    vertices = (mesh.vertices * 0.8 + rng.normal(0, 0.01, mesh.vertices.shape)).astype(np.float32)
    faces = mesh.faces[rng.permutation(len(mesh.faces))]
    path = tmp_path / f"mesh{suffix}"
    write_mesh(path, vertices, faces)
    points, read_faces = read_points(path)
    np.testing.assert_allclose(points, vertices, atol=1e-7 if suffix == ".obj" else 0)
    np.testing.assert_array_equal(read_faces, faces)


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_point_cloud_round_trip(tmp_path, suffix):
    cloud = np.random.default_rng(2).normal(size=(100, 3)).astype(np.float32)
    write_mesh(tmp_path / f"cloud{suffix}", cloud)
    points, faces = read_points(tmp_path / f"cloud{suffix}")
    assert faces is None
    np.testing.assert_allclose(points, cloud, atol=1e-7)


def test_xyz_and_npy_points(tmp_path):
    cloud = np.random.default_rng(3).normal(size=(10, 3)).astype(np.float32)
    extra = np.concatenate([cloud, np.ones((10, 3))], axis=1)            # normals, ignored
    np.savetxt(tmp_path / "a.xyz", extra, fmt="%.9g", header="x y z nx ny nz")
    np.save(tmp_path / "a.npy", cloud)
    np.testing.assert_array_equal(read_points(tmp_path / "a.xyz")[0], cloud)
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy")[0], cloud)


def test_bad_point_files_name_the_file(tmp_path):
    np.save(tmp_path / "flat.npy", np.zeros((4, 2)))
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    for name, message in (("flat.npy", r"\(N, 3\)"), ("junk.ply", "junk.ply"),
                          ("missing.xyz", "missing.xyz")):
        with pytest.raises(ValueError, match=message):
            read_points(tmp_path / name)
    with pytest.raises(ValueError, match="unknown point file type"):
        read_points(tmp_path / "points.stl")


# ----------------------------------------------------------------------------- npz

def test_streamed_npz_reads_back_with_numpy_and_lazily(tmp_path):
    frames = np.random.default_rng(4).normal(size=(7, 11, 3)).astype(np.float32)
    path = tmp_path / "s.npz"
    with open(path, "wb") as file, NpzWriter(file) as archive:
        with archive.frames("vertices", frames.shape, np.float32) as write:
            for frame in frames:
                write(frame)
        archive.add("names", np.array(JOINT_NAMES))
        archive.add("fps", np.array(30.0))
    with np.load(path, allow_pickle=False) as data:
        np.testing.assert_array_equal(data["vertices"], frames)
        assert tuple(data["names"]) == JOINT_NAMES and data["fps"] == 30.0
    lazy = NpzFrames(path, "vertices")
    assert len(lazy) == 7 and lazy.shape == frames.shape
    np.testing.assert_array_equal(np.stack(list(lazy)), frames)
    assert all(info.date_time == (1980, 1, 1, 0, 0, 0)
               for info in zipfile.ZipFile(path).infolist())


def test_streamed_npz_refuses_a_wrong_frame_count(tmp_path):
    with open(tmp_path / "s.npz", "wb") as file, NpzWriter(file) as archive:
        with pytest.raises(ValueError, match="2 frames written of 3"):
            with archive.frames("v", (3, 2), np.float32) as write:
                write(np.zeros(2))
                write(np.zeros(2))
        with pytest.raises(ValueError, match="does not fit"):
            with archive.frames("w", (1, 2), np.float32) as write:
                write(np.zeros(3))


# ----------------------------------------------------------------------------- BVH writer

@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.integers(0, 6))
def test_bvh_writer_round_trips_bit_for_bit(seed, frames):
    tpose, q, root = random_rig(frames, seed)
    motion = rig_to_bvh(tpose * 100, q, root * 100, 1 / 30)
    again = parse_bvh(format_bvh(motion))
    assert again.names == motion.names and again.channels == motion.channels
    np.testing.assert_array_equal(again.parents, motion.parents)
    np.testing.assert_array_equal(again.offsets, motion.offsets)
    np.testing.assert_array_equal(again.values.reshape(motion.values.shape), motion.values)
    assert again.frame_time == motion.frame_time
    assert again.end_sites.keys() == motion.end_sites.keys()
    for joint, offset in motion.end_sites.items():
        np.testing.assert_array_equal(again.end_sites[joint], offset)


def test_rig_to_bvh_reproduces_fk(tmp_path):
    """Positions of the written BVH (read back, BVH forward kinematics) equal our FK."""
    tpose, q, root = random_rig(frames=9)
    joints, _ = forward_kinematics(q, root, tpose)
    write_bvh(tmp_path / "rig.bvh", rig_to_bvh(tpose, q, root, 1 / 30))
    motion = read_bvh(tmp_path / "rig.bvh")
    positions, _ = world_transforms(motion)
    assert motion.names == tuple(JOINT_NAMES[j] for j in depth_first_order())
    assert motion.fps == 30
    np.testing.assert_allclose(positions, joints[:, depth_first_order()], atol=1e-5)
    # ... and the canonical-name mapping reads our own files back in canonical order.
    np.testing.assert_allclose(canonical_world(motion)[0], joints, atol=1e-5)


def test_bvh_writer_refuses_what_would_not_read_back():
    tpose, q, root = random_rig(frames=2)
    motion = rig_to_bvh(tpose, q, root, 1 / 30)
    later_parent = motion.parents.copy()
    later_parent[1] = 2                            # a parent listed after its child
    bad = [BVHMotion(("a b",) + motion.names[1:], motion.parents, motion.offsets,
                     motion.channels, {}, motion.values, 0.1),
           BVHMotion(motion.names, later_parent, motion.offsets, motion.channels, {},
                     motion.values, 0.1),
           BVHMotion(motion.names, motion.parents, motion.offsets, motion.channels, {},
                     motion.values[:, :-1], 0.1),
           BVHMotion(motion.names, motion.parents, motion.offsets, motion.channels, {},
                     motion.values * np.nan, 0.1)]
    for motion_with_fault, message in zip(bad, ["whitespace", "depth-first", "values must",
                                                "finite"]):
        with pytest.raises(ValueError, match=message):
            format_bvh(motion_with_fault)


# ----------------------------------------------------------------------------- skeletons

def test_skeleton_detection():
    assert find_skeleton(JOINT_NAMES) == "canonical"
    assert find_skeleton(["mixamorig:" + name for name in MIXAMO_BONES.values()]) == "mixamo"
    assert find_skeleton(["root", "spine", "head"]) is None       # map_skeleton's turn then


def test_mixamo_names_map_one_to_one(tmp_path):
    tpose, q, root = random_rig(frames=3)
    motion = rig_to_bvh(tpose, q, root, 1 / 30)
    renamed = {name: "mixamorig:" + MIXAMO_BONES[name] for name in JOINT_NAMES}
    mixamo = BVHMotion(tuple(renamed[n] for n in motion.names), motion.parents, motion.offsets,
                       motion.channels, motion.end_sites, motion.values, motion.frame_time)
    joints, _ = forward_kinematics(q, root, tpose)
    np.testing.assert_allclose(canonical_world(mixamo)[0], joints, atol=1e-5)


# ----------------------------------------------------------------------------- extras

def test_missing_extra_names_the_package_and_the_install_command():
    with pytest.raises(MissingExtra, match=r'pip install "minretarget\[cli\]"') as error:
        require("surely_not_an_installed_module", "reading frobs")
    assert "reading frobs" in str(error.value)
    assert isinstance(error.value, ImportError)


def test_atomic_write_gives_the_usual_mode_without_touching_the_umask(tmp_path, monkeypatch):
    import os
    from minretarget.atomic import atomic_write
    previous = os.umask(0o027)
    try:
        monkeypatch.setattr(os, "umask", lambda *_: pytest.fail("atomic_write set the umask"))
        with atomic_write(tmp_path / "out.bin") as file:
            file.write(b"x")
    finally:
        monkeypatch.undo()
        os.umask(previous)
    assert (tmp_path / "out.bin").stat().st_mode & 0o777 == 0o640
