"""Torch twins of minretarget.kinematics and minretarget.skin's LBS, differentiable for training.

Same conventions (minretarget.conventions): quaternions (w, x, y, z), local rotations in the
T-pose's world-aligned frames, metres. Any number of leading batch dimensions ``...``.
"""
import torch

from minretarget.conventions import NUM_JOINTS, PARENTS


def quaternion_to_matrix(quaternions):
    """(..., 4) quaternions (w, x, y, z), not necessarily unit -> (..., 3, 3) rotations."""
    w, x, y, z = quaternions.unbind(-1)
    s = 2.0 / (quaternions * quaternions).sum(-1)                   # 2 / |q|^2 normalises
    rows = (1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y),
            s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x),
            s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y))
    return torch.stack(rows, -1).reshape(quaternions.shape[:-1] + (3, 3))


def normalize_quaternions(quaternions, eps=1e-8):
    """(..., 4) -> (..., 4) unit quaternions."""
    return quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(eps)


def forward_kinematics(rotations, root, tpose_joints):
    """rotations (..., J, 4), root (..., 3), tpose_joints (..., J, 3) broadcastable
    -> joints (..., J, 3) metres, global_rotations (..., J, 3, 3)."""
    local = quaternion_to_matrix(rotations)                         # (..., J, 3, 3)
    tpose_joints = tpose_joints.expand(rotations.shape[:-1] + (3,))
    globals_, joints = [local[..., 0, :, :]], [root]
    for j in range(1, NUM_JOINTS):
        p = PARENTS[j]
        offset = tpose_joints[..., j, :] - tpose_joints[..., p, :]
        joints.append(joints[p] + (globals_[p] @ offset[..., None])[..., 0])
        globals_.append(globals_[p] @ local[..., j, :, :])
    return torch.stack(joints, -2), torch.stack(globals_, -3)


def skinning_transforms(joints, global_rotations, tpose_joints):
    """(..., J, 3), (..., J, 3, 3), (..., J, 3) -> (..., J, 3, 4) maps T-pose -> posed space."""
    translation = joints - (global_rotations @ tpose_joints[..., None])[..., 0]
    return torch.cat([global_rotations, translation[..., None]], -1)


def linear_blend_skinning(points, skin_weights, transforms):
    """Pose T-pose points.

    Args:
        points: (..., V, 3) T-pose points, metres.
        skin_weights: (..., V, J) non-negative, rows sum to one.
        transforms: (..., J, 3, 4) from ``skinning_transforms``.
    Returns:
        (..., V, 3) posed points, metres.
    """
    blended = torch.einsum("...vj,...jab->...vab", skin_weights, transforms)  # (..., V, 3, 4)
    return (blended[..., :3] @ points[..., None])[..., 0] + blended[..., 3]
