import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from minretarget.conventions import JOINT_INDEX, NUM_JOINTS
from minretarget.denoise import denoise_joints, hidden_shape
from minretarget.rest_pose import NUM_BONES, NUM_FEATURES, RestPoseWeights
from minretarget.weights import load_weights

GOLDEN = Path(__file__).parent / "golden"
# tests/golden/shipped_presets.npz (tests/make_golden.py --shipped): frames streamed, past the
# source fit's calibration (15), and the stride of the target vertices kept.
SHIPPED_FRAMES, SHIPPED_VERTEX_STRIDE = 24, 97
# A camera 2.5 m in front of the shipped sample's first cloud, a little above its centre: the
# golden's one-sided stream (``one_sided``) is what the fit told this viewpoint reads.
SHIPPED_CAMERA_OFFSET = (0.0, 0.3, 2.5)


def one_sided(clouds, offset=SHIPPED_CAMERA_OFFSET):
    """A crude single view of each cloud (P, 3): its half nearer a camera at the first
    cloud's centre + ``offset`` metres (along the line to that centre) -> the clouds, the
    camera (3,) float32."""
    camera = (clouds[0].mean(axis=0) + np.asarray(offset)).astype(np.float32)
    axis = clouds[0].mean(axis=0) - camera
    kept = []
    for cloud in clouds:
        depth = (cloud - camera) @ axis
        kept.append(np.ascontiguousarray(cloud[depth < np.median(depth)]))
    return kept, camera
# The CMU motion capture (README, Data): MINRETARGET_CMU_DIR, else beside the repository.
CMU_DIR = Path(os.environ.get("MINRETARGET_CMU_DIR")
               or Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu")


def needs_cmu(path):
    """Skip unless the CMU file ``path`` exists, saying where it was looked for."""
    return pytest.mark.skipif(not path.exists(), reason=f"CMU data not found: {path} (set "
                              "MINRETARGET_CMU_DIR to the folder holding cgspeed/)")


@pytest.fixture(scope="session")
def tiny_weights():
    """The tiny random model of tests/golden (made by tests/make_golden.py)."""
    return load_weights(GOLDEN / "tiny_weights.npz")


@pytest.fixture(scope="session")
def tiny_stream():
    """The golden stream: target (V, 3), source frames [(P_t, 3)], torch outputs by name."""
    with np.load(GOLDEN / "tiny_stream.npz") as data:
        arrays = dict(data)
    sources = np.split(arrays.pop("source_points"), np.cumsum(arrays.pop("source_counts"))[:-1])
    return arrays.pop("target"), sources, arrays


def denoised_stream(weights, frames):
    """(T, J, 3) a stream's smoothed source joints -> the runtime denoiser's output (T, J, 3),
    one frame at a time from a stream's start."""
    hidden = np.zeros(hidden_shape(weights), np.float32)
    out, previous_root = [], frames[0, 0]
    for joints in frames:
        denoised, hidden = denoise_joints(weights, hidden, joints, previous_root)
        out.append(denoised)
        previous_root = joints[0]
    return np.stack(out)


def with_rest_pose(weights, seed=0):
    """``weights`` given the analytic prior and a random rest-pose model (the tiny test
    weights have neither)."""
    directions = np.random.default_rng(seed).normal(size=(NUM_FEATURES, 3 * NUM_BONES))
    return weights._replace(
        config=dataclasses.replace(weights.config, smrm_analytic_prior=True, rest_pose=True),
        smrm=weights.smrm._replace(analytic_prior=True),
        rest_pose=RestPoseWeights(directions.astype(np.float32)))


def turned_about_up(points, angles):
    """Points (..., N, 3) turned about +Y by ``angles`` (...,) radians (+Z toward +X)."""
    angles = np.asarray(angles)[..., None]
    cos, sin = np.cos(angles), np.sin(angles)
    x, y, z = np.moveaxis(points, -1, 0)
    return np.stack([cos * x + sin * z, y, cos * z - sin * x], axis=-1)


def facing(angle, seed=0):
    """A (J, 3) float32 skeleton facing ``angle`` radians from +Z about +Y (hips and shoulders
    across its left), the other joints random, pelvis near (0.3, 1, -0.2)."""
    joints = np.random.default_rng(seed).normal(0.0, 0.05, (NUM_JOINTS, 3))
    for name, x in (("left_hip", 0.1), ("right_hip", -0.1), ("left_shoulder", 0.2),
                    ("right_shoulder", -0.2)):
        joints[JOINT_INDEX[name]] = (x, 0.0, 0.0)
    return (turned_about_up(joints, angle) + (0.3, 1.0, -0.2)).astype(np.float32)
