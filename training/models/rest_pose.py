"""Torch twin of minretarget.rest_pose: the reference skeleton SMRM's analytic prior aligns
(fitted by training.rest_pose; used by training.models.smrm)."""
import torch

from minretarget.conventions import PARENTS
from minretarget.rest_pose import _MIRROR_BONE, NUM_BONES


def torch_bone_lengths(joints):
    """(..., J, 3) tensor -> (..., B) bone lengths."""
    return (joints[..., 1:, :] - joints[..., list(PARENTS[1:]), :]).norm(dim=-1)


def torch_prior_reference(directions, target_tpose, source_lengths):
    """Torch twin of ``minretarget.rest_pose.prior_reference``, batched.

    Args:
        directions: (F, B*3) tensor, RestPoseWeights.directions.
        target_tpose: (..., J, 3) target T-pose joints.
        source_lengths: (..., B) source bone lengths (broadcast against the T-pose's batch).
    Returns:
        (..., J, 3) the reference skeleton.
    """
    def predicted(lengths):
        symmetric = 0.5 * (lengths + lengths[..., _MIRROR_BONE.tolist()])
        total = symmetric.sum(-1, keepdim=True).clamp_min(1e-6)
        features = torch.cat([torch.ones_like(total), symmetric / total, total], -1)
        flat = features @ directions
        return torch.nn.functional.normalize(flat.unflatten(-1, (NUM_BONES, 3)), dim=-1,
                                             eps=1e-12)

    bones = target_tpose[..., 1:, :] - target_tpose[..., list(PARENTS[1:]), :]
    target_lengths = bones.norm(dim=-1, keepdim=True)
    source_lengths, target_lengths_ = torch.broadcast_tensors(source_lengths,
                                                              target_lengths[..., 0])
    turned = (bones / target_lengths.clamp_min(1e-12) + predicted(source_lengths)
              - predicted(target_lengths_))
    turned = turned / turned.norm(dim=-1, keepdim=True).clamp_min(1e-12) * target_lengths
    root = target_tpose[..., :1, :].expand(*turned.shape[:-2], 1, 3)
    joints = [root[..., 0, :]]
    for b in range(NUM_BONES):
        joints.append(joints[PARENTS[b + 1]] + turned[..., b, :])
    return torch.stack(joints, dim=-2)
