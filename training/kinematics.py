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


def quaternion_multiply(a, b):
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z): rotate by b, then by a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def normalize_quaternions(quaternions, eps=1e-8):
    """(..., 4) -> (..., 4) unit quaternions."""
    return quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(eps)


def matrix_to_quaternion(m):
    """(..., 3, 3) rotations -> (..., 4) unit quaternions (w, x, y, z), w >= 0; the branch of
    the largest squared component (minretarget.kinematics.matrix_to_quaternion's twin)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    squares = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                           1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    candidates = torch.stack([
        torch.stack([squares[..., 0], m[..., 2, 1] - m[..., 1, 2],
                     m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], squares[..., 1],
                     m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1],
                     squares[..., 2], m[..., 2, 1] + m[..., 1, 2]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                     m[..., 2, 1] + m[..., 1, 2], squares[..., 3]], -1)], -2)
    best = squares.argmax(-1)[..., None, None].expand(squares.shape[:-1] + (1, 4))
    q = normalize_quaternions(torch.gather(candidates, -2, best)[..., 0, :])
    return torch.where(q[..., :1] < 0, -q, q)


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
