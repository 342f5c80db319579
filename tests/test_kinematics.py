"""Quaternions and forward kinematics: against NumPy twins and by their properties."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import twins
from minretarget.conventions import NUM_JOINTS, PARENTS
from minretarget.kinematics import (forward_kinematics, leg_length, matrix_to_quaternion,
                                    quaternion_multiply, quaternion_to_matrix,
                                    skinning_transforms)


def random_quaternions(rng, shape):
    return rng.normal(size=shape + (4,)).astype(np.float32)


def random_skeleton(rng):
    return (rng.normal(size=(NUM_JOINTS, 3)) * 0.3).astype(np.float32)


def test_quaternion_to_matrix_matches_twin_and_is_a_rotation():
    q = random_quaternions(np.random.default_rng(0), (7, 5))
    r = quaternion_to_matrix(q)
    assert r.shape == (7, 5, 3, 3) and r.dtype == np.float32
    np.testing.assert_allclose(r, twins.quaternion_to_matrix(q), atol=1e-6)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape),
                               atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-5)


def test_quaternion_to_matrix_hand_computed():
    half = np.sqrt(0.5)
    # 90 degrees about +Z maps +X to +Y.
    r = quaternion_to_matrix([half, 0, 0, half])
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(quaternion_to_matrix([2, 0, 0, 0]), np.eye(3), atol=1e-7)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 1e-2))
def test_matrix_to_quaternion_round_trips(values):
    q = np.asarray(values, np.float32) / np.linalg.norm(values)
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    # q and -q are the same rotation; the inverse returns the one with w >= 0.
    assert back[0] >= 0
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-3
    np.testing.assert_allclose(quaternion_to_matrix(back), quaternion_to_matrix(q), atol=1e-5)


def test_quaternion_multiply_composes_rotations():
    rng = np.random.default_rng(1)
    a, b = random_quaternions(rng, (10,)), random_quaternions(rng, (10,))
    np.testing.assert_allclose(quaternion_to_matrix(quaternion_multiply(a, b)),
                               quaternion_to_matrix(a) @ quaternion_to_matrix(b), atol=1e-5)


def test_fk_of_identity_returns_the_tpose():
    tpose = random_skeleton(np.random.default_rng(2))
    identity = np.tile(np.float32([1, 0, 0, 0]), (NUM_JOINTS, 1))
    joints, rotations = forward_kinematics(identity, tpose[0], tpose)
    np.testing.assert_allclose(joints, tpose, atol=1e-6)
    np.testing.assert_allclose(rotations, np.broadcast_to(np.eye(3), rotations.shape), atol=1e-7)


def test_fk_matches_twin_and_keeps_bone_lengths():
    rng = np.random.default_rng(3)
    tpose = random_skeleton(rng)
    q, root = random_quaternions(rng, (NUM_JOINTS,)), rng.normal(size=3).astype(np.float32)
    joints, rotations = forward_kinematics(q, root, tpose)
    want_joints, want_rotations = twins.forward_kinematics(q, root, tpose)
    np.testing.assert_allclose(joints, want_joints, atol=1e-5)
    np.testing.assert_allclose(rotations, want_rotations, atol=1e-5)
    bones = lambda x: np.linalg.norm(x[1:] - x[list(PARENTS[1:])], axis=-1)  # noqa: E731
    np.testing.assert_allclose(bones(joints), bones(tpose), atol=1e-5)


def test_fk_batch_equals_per_item_calls():
    rng = np.random.default_rng(4)
    tpose = random_skeleton(rng)
    q, root = random_quaternions(rng, (2, 3, NUM_JOINTS)), rng.normal(size=(2, 3, 3))
    joints, _ = forward_kinematics(q, root, tpose)
    for index in np.ndindex(2, 3):
        np.testing.assert_allclose(joints[index], forward_kinematics(q[index], root[index],
                                                                     tpose)[0], atol=1e-6)


def test_skinning_transforms_map_tpose_joints_to_posed_joints():
    rng = np.random.default_rng(5)
    tpose = random_skeleton(rng)
    joints, rotations = forward_kinematics(random_quaternions(rng, (NUM_JOINTS,)),
                                           np.zeros(3), tpose)
    transforms = skinning_transforms(joints, rotations, tpose)
    mapped = np.einsum("jab,jb->ja", transforms[..., :3], tpose) + transforms[..., 3]
    np.testing.assert_allclose(mapped, joints, atol=1e-5)


def test_leg_length_hand_computed():
    joints = np.zeros((NUM_JOINTS, 3), np.float32)
    joints[[1, 2], 0] = [0.1, -0.1]
    joints[[4, 5]] = joints[[1, 2]] - [0, 0.4, 0]
    joints[[7, 8]] = joints[[4, 5]] - [0, 0.3, 0]
    assert leg_length(joints) == pytest.approx(0.7)


def test_bad_shapes_raise_value_errors():
    with pytest.raises(ValueError, match="rotations must have shape"):
        forward_kinematics(np.zeros((21, 4)), np.zeros(3), np.zeros((22, 3)))
    with pytest.raises(ValueError, match="root"):
        forward_kinematics(np.ones((22, 4)), np.zeros(2), np.zeros((22, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        quaternion_to_matrix([np.nan, 0, 0, 1])
