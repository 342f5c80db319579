"""The analytic baseline: bone directions of the result equal the source's."""
import numpy as np

import twins
from minretarget.analytic import analytic_rotations
from minretarget.conventions import NUM_JOINTS, PARENTS
from minretarget.kinematics import forward_kinematics, quaternion_to_matrix


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


def test_kernel_matches_the_numpy_twin():
    rng = np.random.default_rng(4)
    tpose, target = skeleton(rng), skeleton(rng)
    source, _ = posed(rng, tpose, 12)
    rotations = quaternion_to_matrix(analytic_rotations(source, target))
    np.testing.assert_allclose(rotations, twins.analytic_rotations(source, target), atol=2e-5)


def test_torch_reference_matches_the_runtime_and_has_finite_gradients():
    import torch
    from training.analytic import analytic_rotations as torch_analytic
    rng = np.random.default_rng(5)
    tpose, target = skeleton(rng), skeleton(rng)
    source, _ = posed(rng, tpose, 12)
    joints = torch.tensor(source, requires_grad=True)
    reference = torch_analytic(joints, torch.tensor(target))
    runtime = analytic_rotations(source, target)
    # q and -q are the same rotation; both conventions give w >= 0, but compare safely.
    np.testing.assert_allclose(np.abs((reference.detach().numpy() * runtime).sum(-1)), 1.0,
                               atol=1e-5)
    (reference * torch.randn(reference.shape, generator=torch.Generator().manual_seed(0))
     ).sum().backward()
    assert torch.isfinite(joints.grad).all() and joints.grad.abs().sum() > 0
