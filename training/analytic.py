"""Torch twin of minretarget.analytic: rotate each target bone onto its source bone.

Differentiable in the source joints, so SMRM's analytic prior (``smrm_analytic_prior``) passes
the cycle loss's gradient back through the A -> B result. Same steps as the runtime: the
smallest turn for joints with one child, Kabsch's rotation (as Horn's quaternion) for the
pelvis and spine3, the parent's rotation for leaf joints.
"""
import torch
import torch.nn.functional as F

from minretarget.analytic import CHILDREN, SQUARINGS
from minretarget.conventions import NUM_JOINTS, PARENTS
from training.kinematics import matrix_to_quaternion, quaternion_to_matrix


def _rotation_between(a, b):
    """(..., 3) unit a, b -> (..., 3, 3) the smallest rotations taking a to b."""
    cross = torch.linalg.cross(a, b)
    dot = (a * b).sum(-1)
    # Opposite vectors: a half turn about an axis perpendicular to a.
    helper = torch.where(a[..., :1].abs() < 0.9, a.new_tensor([1.0, 0, 0]),
                         a.new_tensor([0, 1.0, 0]))
    perpendicular = F.normalize(torch.linalg.cross(a, helper), dim=-1, eps=1e-12)
    opposite = (dot < -1 + 1e-6)[..., None]
    cross = torch.where(opposite, perpendicular, cross)
    w = torch.where(opposite[..., 0], torch.zeros_like(dot), 1 + dot)
    return quaternion_to_matrix(torch.cat([w[..., None], cross], -1))


def _best_rotation(a, b):
    """(..., K, 3) unit a, b -> (..., 3, 3) the rotations R maximising sum_k b_k . R a_k,
    as the runtime finds them: Horn's quaternion by repeated squaring (no SVD: ONNX has none,
    and its gradient is unstable where singular values meet)."""
    s = a.transpose(-1, -2) @ b                                         # sum_k a_k b_k^T
    n = torch.stack([
        torch.stack([s[..., 0, 0] + s[..., 1, 1] + s[..., 2, 2], s[..., 1, 2] - s[..., 2, 1],
                     s[..., 2, 0] - s[..., 0, 2], s[..., 0, 1] - s[..., 1, 0]], -1),
        torch.stack([s[..., 1, 2] - s[..., 2, 1], s[..., 0, 0] - s[..., 1, 1] - s[..., 2, 2],
                     s[..., 0, 1] + s[..., 1, 0], s[..., 2, 0] + s[..., 0, 2]], -1),
        torch.stack([s[..., 2, 0] - s[..., 0, 2], s[..., 0, 1] + s[..., 1, 0],
                     s[..., 1, 1] - s[..., 0, 0] - s[..., 2, 2], s[..., 1, 2] + s[..., 2, 1]], -1),
        torch.stack([s[..., 0, 1] - s[..., 1, 0], s[..., 2, 0] + s[..., 0, 2],
                     s[..., 1, 2] + s[..., 2, 1], s[..., 2, 2] - s[..., 0, 0] - s[..., 1, 1]], -1),
    ], -2)
    power = n + a.shape[-2] * torch.eye(4, dtype=n.dtype, device=n.device)
    for _ in range(SQUARINGS):
        power = power @ power
        power = power / power.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    best = power.diagonal(dim1=-2, dim2=-1).argmax(-1)                 # (...,)
    column = torch.gather(power, -1, best[..., None, None].expand(power.shape[:-1] + (1,)))
    return quaternion_to_matrix(column[..., 0])


def analytic_rotations(source_joints, target_tpose):
    """source_joints (..., J, 3), target_tpose (..., J, 3) broadcastable, metres
    -> (..., J, 4) local unit quaternions that pose the target like the source."""
    shape = torch.broadcast_shapes(source_joints.shape, target_tpose.shape)
    source, tpose = source_joints.expand(shape), target_tpose.expand(shape)
    eye = torch.eye(3, dtype=source.dtype, device=source.device).expand(shape[:-2] + (3, 3))
    world = []
    for j in range(NUM_JOINTS):
        parent = world[PARENTS[j]] if j else eye
        children = list(CHILDREN[j])
        if not children:
            world.append(parent)
            continue
        rest = F.normalize((parent[..., None, :, :] @ (tpose[..., children, :]
                            - tpose[..., j:j + 1, :])[..., None])[..., 0], dim=-1, eps=1e-12)
        posed = F.normalize(source[..., children, :] - source[..., j:j + 1, :], dim=-1,
                            eps=1e-12)
        turn = (_rotation_between(rest[..., 0, :], posed[..., 0, :]) if len(children) == 1
                else _best_rotation(rest, posed))
        world.append(turn @ parent)
    world = torch.stack(world, -3)                                     # (..., J, 3, 3)
    parents = [0] + list(PARENTS[1:])
    local = world[..., parents, :, :].transpose(-1, -2) @ world
    local = torch.cat([world[..., :1, :, :], local[..., 1:, :, :]], -3)
    return matrix_to_quaternion(local)
