"""Property-based tests: random and malformed input to every file parser and public function
gives a result that holds its promises or one of the documented errors (ValueError, its
subclass BVHError, FileNotFoundError), never anything else.
(benchmarks/fuzz_parsers.py runs the parsers for minutes, coverage-guided.)"""
import gzip
import io
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from minretarget import Retargeter
from minretarget.bvh import format_bvh, parse_bvh
from minretarget.config import ModelConfig
from minretarget.conventions import NUM_JOINTS
from minretarget.formats.mesh import read_points
from minretarget.kinematics import forward_kinematics
from minretarget.skeletons import rig_to_bvh
from minretarget.skr import regress_joints
from minretarget.contacts import FeetState
from minretarget.denoise import DenoiseState
from minretarget.facing import FacingState
from minretarget.smoothing import SmoothingState
from minretarget.smrm import SMRMState
from minretarget.sources import open_source
from minretarget.units import CANONICAL
from minretarget.validation import as_float32_array
from minretarget.weights import (FORMAT_VERSION, _leaves, flatten_weights, load_weights,
                                 weight_template, weights_from_arrays)

trimesh = pytest.importorskip("trimesh")
DOCUMENTED = (ValueError, FileNotFoundError)
FOLDER = Path(tempfile.mkdtemp(prefix="minretarget-malformed-"))
QUICK = settings(max_examples=60, deadline=None, derandomize=True,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def npy_bytes(array):
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def npz_bytes(compress=False, **arrays):
    buffer = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buffer, **arrays)
    return buffer.getvalue()


def seed_files():
    """{suffix: [valid small files]} for every parser."""
    rng = np.random.default_rng(0)
    box = trimesh.creation.box()
    frames = rng.normal(size=(2, 6, 3)).astype(np.float32)
    bvh = format_bvh(rig_to_bvh(rng.normal(size=(22, 3)), np.tile([1.0, 0, 0, 0], (2, 22, 1)),
                                rng.normal(size=(2, 3)), 1 / 30)).encode()
    config = ModelConfig((1, 1, 1), (1, 1), 1, 1, (1,))        # every width 1: a few kB
    weights = {key: np.zeros(shape, np.float16) for stage, tree in weight_template(config).items()
               for key, shape in _leaves(tree, stage)}
    weights.update(format_version=np.array(FORMAT_VERSION), config=np.array(config.to_json()),
                   metadata=np.array("{}"))
    return {
        ".ply": [box.export(file_type="ply"), box.export(file_type="ply", encoding="ascii")],
        ".obj": [box.export(file_type="obj").encode()],
        ".xyz": [b"".join(b"%g %g %g 1\n" % tuple(p) for p in frames[0])],
        ".npy": [npy_bytes(frames[0])],
        "frames.npy": [npy_bytes(frames)],
        "frames.npz": [npz_bytes(points=frames), npz_bytes(True, source_points=frames)],
        ".bvh": [bvh], ".bvh.gz": [gzip.compress(bvh, mtime=0)],
        "weights.npz": [npz_bytes(**weights)],
    }


SEEDS = seed_files()


@st.composite
def damaged(draw, kind):
    """A seed file of ``kind``, cut short and with some bytes overwritten, or random bytes."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=600))
    data = bytearray(draw(st.sampled_from(SEEDS[kind])))
    for _ in range(draw(st.integers(0, 6))):
        position = draw(st.integers(0, len(data) - 1))
        data[position] = draw(st.integers(0, 255))
    return bytes(data[:draw(st.integers(0, len(data)))]) if draw(st.booleans()) else bytes(data)


def parse(kind, data):
    """Read ``data`` as the command line reads a file of ``kind``."""
    path = FOLDER / ("input" + kind[kind.index("."):])
    path.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kind in (".ply", ".obj", ".xyz", ".npy"):
            points, faces = read_points(path)
            assert points.dtype == np.float32 and points.shape[1:] == (3,)
            assert np.isfinite(points).all()
            assert faces is None or (faces.min() >= 0 and faces.max() < len(points))
        elif kind == "weights.npz":
            load_weights(path)
        else:
            source = open_source(path, CANONICAL)
            frames = [as_float32_array(f, "frame", (None, 3)) for f in source.frames]
            assert len(frames) == source.count


@pytest.mark.parametrize("kind", sorted(SEEDS))
def test_seed_files_parse(kind):
    for data in SEEDS[kind]:
        parse(kind, data)


@pytest.mark.parametrize("kind", sorted(SEEDS))
@QUICK
@given(data=st.data())
def test_damaged_files_give_documented_errors_only(kind, data):
    try:
        parse(kind, data.draw(damaged(kind)))
    except DOCUMENTED:
        pass


@QUICK
@given(st.lists(st.sampled_from(
    ["HIERARCHY", "ROOT pelvis", "JOINT spine1", "{", "}", "OFFSET 0 1 2", "OFFSET nan 0 0",
     "CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 6 Xposition Yposition Zposition "
     "Zrotation Xrotation Yrotation", "CHANNELS 1 Xrotation", "CHANNELS -1", "End Site",
     "MOTION", "Frames: 2", "Frames: 99999999", "Frame Time: 0.0333", "Frame Time: 0",
     "0 0 0", "0 0 0 0 0 0", "1e400 0 0", "", "\r", "\x85"]), max_size=30))
def test_bvh_token_soup(lines):
    try:
        motion = parse_bvh("\n".join(lines))
        assert np.isfinite(motion.values).all() and motion.frame_time > 0
    except ValueError:
        pass


# ----------------------------------------------------------------------------- functions

DTYPES = st.sampled_from([np.float16, np.float32, np.float64, np.int32, np.int64, np.uint8,
                          np.bool_, np.complex64])


def arrays(shape=None):
    shapes = hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=80) \
        if shape is None else st.just(shape)
    return DTYPES.flatmap(lambda dtype: hnp.arrays(
        dtype, shapes, elements=None if dtype in (np.bool_, np.uint8, np.int32, np.int64)
        else {"allow_nan": True, "allow_infinity": True}))


def moderate(array):
    """Finite real numbers of magnitude <= 1e3: where outputs must be finite too."""
    return array.dtype.kind in "fiu" and np.isfinite(array).all() and \
        (array.size == 0 or np.abs(array.astype(np.float64)).max() <= 1e3)


@pytest.fixture(scope="module")
def retargeter(tiny_weights):
    retargeter = Retargeter(tiny_weights, warn=False)
    retargeter.set_target(np.random.default_rng(0).normal(size=(100, 3)))
    return retargeter


@QUICK
@given(points=st.one_of(arrays(), arrays((70, 3)), arrays((64, 3))))
def test_step_and_set_target(retargeter, points):
    for function in (retargeter.step, regress_joints):
        try:
            out = function(points, retargeter.weights.skr) if function is regress_joints \
                else function(points)
        except ValueError:
            continue
        joints = out if function is regress_joints else out.joints
        if moderate(points):
            assert np.isfinite(joints).all()
    other = Retargeter(retargeter.weights, warn=False)
    try:
        other.set_target(points)
    except ValueError:
        return
    if moderate(points):
        assert np.isfinite(other.target.skin_weights).all()


@QUICK
@given(joints=st.one_of(arrays(), arrays((NUM_JOINTS, 3))))
def test_step_skeleton(retargeter, joints):
    retargeter.reset()
    try:
        frame = retargeter.step_skeleton(joints)
    except ValueError:
        return
    if moderate(joints):
        assert np.isfinite(frame.vertices).all()


@QUICK
@given(rotations=st.one_of(arrays(), arrays((NUM_JOINTS, 4)), arrays((2, NUM_JOINTS, 4))),
       root=st.one_of(arrays(), arrays((3,)), arrays((2, 3))),
       tpose=st.one_of(arrays((NUM_JOINTS, 3)), arrays()))
def test_forward_kinematics(rotations, root, tpose):
    try:
        joints, rotation_matrices = forward_kinematics(rotations, root, tpose)
    except ValueError:
        return
    if moderate(rotations) and moderate(root) and moderate(tpose):
        assert np.isfinite(joints).all() and np.isfinite(rotation_matrices).all()


@QUICK
@given(data=st.data())
def test_weights_with_wrong_entries(tiny_weights, data):
    arrays_ = dict(flatten_weights(tiny_weights))
    key = data.draw(st.sampled_from(sorted(arrays_)))
    change = data.draw(st.sampled_from(["drop", "array", "config", "metadata"]))
    if change == "drop":
        del arrays_[key]
    elif change == "array":
        arrays_[key] = data.draw(arrays())
    elif change == "config":
        arrays_["config"] = np.array(data.draw(st.one_of(
            st.text(max_size=40), st.dictionaries(st.sampled_from(
                ["smrm_hidden", "smrm_layers", "skin_widths", "skr_point_widths", "x"]),
                st.one_of(st.integers(-3, 3), st.lists(st.integers(-1, 4), max_size=4),
                          st.text(max_size=3)), max_size=5).map(json.dumps))))
    else:
        arrays_["metadata"] = np.array(data.draw(st.text(max_size=20)))
    try:
        weights_from_arrays(arrays_)
    except ValueError:
        pass


# (stage, field) of every stage state the regressed preset keeps, and the stream's count.
STATE_FIELDS = [(None, "frames_seen")] + [
    (stage, field) for stage, kind in (("smrm", SMRMState), ("facing_check", FacingState),
                                       ("smoothing", SmoothingState), ("denoiser", DenoiseState),
                                       ("foot_lock", FeetState))
    for field in kind._fields]


@QUICK
@example(stage_field=("smrm", "frames_seen"), value=float("inf"))  # found: OverflowError
@given(stage_field=st.sampled_from(STATE_FIELDS), value=st.one_of(
    arrays(), st.integers(-5, 5), st.floats(allow_nan=True), st.none(), st.text(max_size=3)))
def test_state_setter(retargeter, stage_field, value):
    stage, field = stage_field
    retargeter.config = "regressed"
    try:
        retargeter.reset()
        retargeter.step(np.random.default_rng(0).normal(size=(70, 3)))
        state = retargeter.state
        if stage is None:
            state = state._replace(frames_seen=value)
        else:
            state = state._replace(stages={**state.stages, stage: state.stages[stage]._replace(
                **{field: value})})
        try:
            retargeter.state = state
        except ValueError:
            return
        if all(moderate(np.asarray(value, np.float64))
               for stage in retargeter.state.stages.values() for value in stage):
            frame = retargeter.step(np.random.default_rng(1).normal(size=(70, 3)))
            assert np.isfinite(frame.vertices).all()
    finally:
        retargeter.config = "default"
