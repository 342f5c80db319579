"""The analytic baseline: bone directions of the result equal the source's."""
import numpy as np

from minretarget.analytic import analytic_rotations
from minretarget.conventions import NUM_JOINTS, PARENTS
from minretarget.kinematics import forward_kinematics


def skeleton(rng):
    joints = np.zeros((NUM_JOINTS, 3))
    for j in range(1, NUM_JOINTS):
        joints[j] = joints[PARENTS[j]] + rng.normal(0, 0.15, 3)
    return joints.astype(np.float32)


def posed(rng, tpose, frames):
    q = rng.normal(size=(frames, NUM_JOINTS, 4)) * [1, 0.5, 0.5, 0.5] + [1.5, 0, 0, 0]
    root = rng.normal(size=(frames, 3))
    return forward_kinematics(q.astype(np.float32), root.astype(np.float32), tpose)[0], root


def test_same_skeleton_reproduces_the_source_pose():
    rng = np.random.default_rng(0)
    tpose = skeleton(rng)
    source, root = posed(rng, tpose, 20)
    rotations = analytic_rotations(source, tpose)
    assert rotations.shape == (20, NUM_JOINTS, 4)
    joints, _ = forward_kinematics(rotations, source[:, 0], tpose)
    np.testing.assert_allclose(joints, source, atol=1e-4)


def test_other_skeleton_gets_the_source_bone_directions():
    rng = np.random.default_rng(1)
    source, _ = posed(rng, skeleton(rng), 10)
    target = skeleton(rng)
    joints, _ = forward_kinematics(analytic_rotations(source, target), source[:, 0], target)
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
    # Single-child joints align exactly; multi-child joints (0, 9) only best-fit.
    for child in range(1, NUM_JOINTS):
        if PARENTS[child] in (0, 9):
            continue
        parent = PARENTS[child]
        np.testing.assert_allclose(unit(joints[:, child] - joints[:, parent]),
                                   unit(source[:, child] - source[:, parent]), atol=1e-4)


def test_tpose_source_gives_identity():
    tpose = skeleton(np.random.default_rng(2))
    rotations = analytic_rotations(tpose * 1.3, tpose)   # the same T-pose, larger
    np.testing.assert_allclose(np.abs(rotations[:, 0]), 1.0, atol=1e-5)


def test_opposite_bones_are_handled():
    tpose = skeleton(np.random.default_rng(3))
    source = tpose.copy()
    source[5] = 2 * source[2] - source[5]   # right knee flipped through the right hip
    source[8] = source[5] + (tpose[8] - tpose[5])
    source[11] = source[8] + (tpose[11] - tpose[8])
    joints, _ = forward_kinematics(analytic_rotations(source, tpose), source[0], tpose)
    np.testing.assert_allclose(joints[5], source[5], atol=1e-4)
    assert np.isfinite(joints).all()
