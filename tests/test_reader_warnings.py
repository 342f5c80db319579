"""Reading any supported input leaves the process's warnings filters as they were: a reader
neither changes ``warnings.filters`` nor touches them for the time of a call (the filters
are every thread's, so even ``warnings.catch_warnings`` in a reader would change what another
thread sees while it runs)."""
import gzip
import sys
import warnings

import numpy as np
import pytest

from minretarget.bodies import body_names
from minretarget.bvh import format_bvh, read_bvh
from minretarget.conventions import NUM_JOINTS
from minretarget.formats.glb import read_glb, write_glb
from minretarget.formats.mesh import read_points, write_mesh
from minretarget.kinematics import forward_kinematics
from minretarget.skeletons import rig_to_bvh
from minretarget.sources import load_sample, open_source, read_target
from minretarget.units import make_space

pytest.importorskip("trimesh")

METRES = make_space("m", "y")


@pytest.fixture
def files(tmp_path):
    """One file of every readable kind, made by minretarget's writers or by hand."""
    _, target, faces, _ = load_sample()
    rng = np.random.default_rng(0)
    clouds = (target[None, :500] + rng.normal(0, 0.01, (3, 500, 3))).astype(np.float32)
    out = {"ply": tmp_path / "t.ply", "obj": tmp_path / "t.obj", "xyz": tmp_path / "t.xyz",
           "npy": tmp_path / "t.npy", "frames.npy": tmp_path / "frames.npy",
           "frames.npz": tmp_path / "frames.npz", "target.npz": tmp_path / "target.npz",
           "folder": tmp_path / "folder", "bvh": tmp_path / "m.bvh",
           "bvh.gz": tmp_path / "m.bvh.gz", "glb": tmp_path / "r.glb"}
    write_mesh(out["ply"], target, faces)
    write_mesh(out["obj"], target, faces)
    np.savetxt(out["xyz"], clouds[0])
    np.save(out["npy"], clouds[0])
    np.save(out["frames.npy"], clouds)
    np.savez(out["frames.npz"], points=clouds)
    np.savez(out["target.npz"], vertices=target, faces=faces)
    out["folder"].mkdir()
    for t, cloud in enumerate(clouds):
        np.save(out["folder"] / f"{t:03d}.npy", cloud)
    write_mesh(out["folder"] / "003.ply", clouds[0])
    tpose = np.asarray(load_sample()[1][:NUM_JOINTS], np.float32)     # any 22 points
    rotations = np.tile(np.float32([1, 0, 0, 0]), (4, NUM_JOINTS, 1))
    root = np.zeros((4, 3), np.float32)
    text = format_bvh(rig_to_bvh(tpose, rotations, root, 1 / 30))
    out["bvh"].write_text(text)
    out["bvh.gz"].write_bytes(gzip.compress(text.encode()))
    skin = np.eye(NUM_JOINTS, dtype=np.float32)[np.arange(len(target)) % NUM_JOINTS]
    write_glb(out["glb"], target, faces, skin, tpose, rotations, root, 30)
    return out


def read_everything(files):
    """Every reader on every kind of file, every source frame read."""
    for kind in ("ply", "obj", "xyz", "npy"):
        read_points(files[kind])
        read_target(files[kind], METRES)
    read_target(files["target.npz"], METRES)
    read_target(body_names()[0], METRES)
    for kind in ("frames.npy", "frames.npz", "folder", "bvh", "bvh.gz"):
        source = open_source(files[kind], METRES)
        assert len(list(source.frames)) == source.count
    read_bvh(files["bvh"])
    read_glb(files["glb"])
    source, *_ = load_sample()
    next(iter(source.frames))


def test_readers_leave_the_warnings_filters_alone(files, monkeypatch):
    touched = []

    def from_minretarget():
        caller = sys._getframe(2).f_globals.get("__name__", "")
        return caller == "minretarget" or caller.startswith("minretarget.")

    def watch(name):
        original = getattr(warnings, name)

        def watched(*args, **kwargs):
            if from_minretarget():
                touched.append((name, sys._getframe(1).f_globals.get("__name__")))
            return original(*args, **kwargs)
        monkeypatch.setattr(warnings, name, watched)
    for name in ("filterwarnings", "simplefilter", "resetwarnings", "catch_warnings"):
        watch(name)
    before = list(warnings.filters)
    read_everything(files)
    assert list(warnings.filters) == before
    assert touched == []
