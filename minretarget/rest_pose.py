"""Stage 2a, the rest poses: what SMRM's analytic prior aligns the source bones with.

Retargeting keeps each joint's local rotation and puts it on the target's own rest skeleton.
Rest skeletons differ with the body's proportions, in bone directions as well as lengths (a
wider pelvis slants the thighs, a heavier chest bends the spine), so turning each target bone
onto the source bone, as the analytic retargeting does, is exact only between bodies whose rest
poses agree. Retargeting relative to the source's rest skeleton instead removes most of that
error, and the predicted one below much of it, even with exact source joints (so clean
skeleton sources such as BVH files keep it too; the figures: docs/runtime_notes.md).

The source is never seen at rest, so its rest skeleton is predicted: a linear map, fitted on
anny bodies (``training.rest_pose``), from a body's bone lengths to its rest bone directions.
Both bodies' directions are predicted the same way, and the target's T-pose bones are turned
by the difference (source minus target) to give the reference skeleton SMRM's prior aligns
with the source bones; its bone lengths stay the target's. When the two bodies have the same
proportions the reference is the target's T-pose, and the prior is the plain analytic one.
Taking the difference, rather than the source's predicted skeleton, keeps the bias that SKR
puts into both skeletons (the target's T-pose comes from SKR too) on both sides.

The source's bone lengths are the mean over the frames seen so far of the (denoised) source
skeleton's (``smrm.SMRMState.source_bone_lengths``); SKR's lengths are noisy (several per
cent per bone: docs/runtime_notes.md), so the map is fitted on lengths with noise of that size
added, which shrinks it towards what the noise leaves predictable. Not in the paper.

Features of a body (F = 2 + B, B = J - 1 bones): 1, each bone's length averaged with its
mirror image's (anny bodies are symmetric) over the sum of all bone lengths, and that sum.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import MIRROR, NUM_JOINTS, PARENTS
from .validation import as_float32_array

NUM_BONES = NUM_JOINTS - 1        # bone b ends at joint b + 1, starts at PARENTS[b + 1]
NUM_FEATURES = 2 + NUM_BONES
_PARENTS = np.asarray(PARENTS, dtype=np.int64)
_MIRROR_BONE = np.asarray(MIRROR[1:], dtype=np.int64) - 1


class RestPoseWeights(NamedTuple):
    directions: np.ndarray   # (F, B*3) float32: features -> rest bone directions (unnormalised)


def check_rest_pose(weights):
    """RestPoseWeights with a finite (F, B*3) float32 C-contiguous map, or ValueError."""
    if not isinstance(weights, RestPoseWeights):
        raise ValueError(f"rest_pose must be RestPoseWeights, got {type(weights).__name__}")
    return RestPoseWeights(as_float32_array(weights.directions, "rest_pose.directions",
                                            (NUM_FEATURES, 3 * NUM_BONES)))


def bone_lengths(joints):
    """(..., J, 3) float32 joints, metres -> (..., B) float32 bone lengths, metres."""
    joints = as_float32_array(joints, "joints", (..., NUM_JOINTS, 3))
    bones = joints[..., 1:, :] - joints[..., _PARENTS[1:], :]
    return np.linalg.norm(bones, axis=-1).astype(np.float32)


def rest_pose_features(lengths):
    """(..., B) float32 bone lengths, metres -> (..., F) float32 features (module docstring)."""
    lengths = as_float32_array(lengths, "lengths", (..., NUM_BONES))
    total = np.maximum(lengths.sum(axis=-1, keepdims=True), np.float32(1e-6))
    symmetric = 0.5 * (lengths + lengths[..., _MIRROR_BONE])
    return np.concatenate([np.ones_like(total), symmetric / total, total], axis=-1)


def prior_reference(weights, target_tpose, source_lengths):
    """The skeleton SMRM's analytic prior turns onto the source bones.

    Args:
        weights: RestPoseWeights.
        target_tpose: (J, 3) float32 the target's T-pose joints, metres.
        source_lengths: (B,) float32 the source's bone lengths (a mean over frames), metres.
    Returns:
        (J, 3) float32: the target's T-pose with each bone turned by the predicted rest
        direction of the source's minus the target's, lengths kept, root in place.
    """
    weights = check_rest_pose(weights)
    tpose = as_float32_array(target_tpose, "target_tpose", (NUM_JOINTS, 3))
    lengths = as_float32_array(source_lengths, "source_lengths", (NUM_BONES,))
    if not (lengths > 0).all():
        raise ValueError(f"source_lengths must be positive, got {lengths.min()} at bone "
                         f"{int(lengths.argmin())}")
    out = np.empty((NUM_JOINTS, 3), dtype=np.float32)
    _prior_reference_kernel(weights.directions, tpose, lengths, out)
    return out


@kernel
def _bone_lengths_kernel(joints, out):
    """(J, 3) joints -> out (B,) bone lengths."""
    for b in range(out.shape[0]):
        v = joints[b + 1] - joints[_PARENTS[b + 1]]
        out[b] = np.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)


@kernel
def _features_kernel(lengths, out):
    """(B,) bone lengths -> out (F,), the module docstring's features."""
    total = np.float32(0.0)
    for b in range(lengths.shape[0]):
        total += lengths[b]
    total = max(total, np.float32(1e-6))
    out[0] = 1.0
    for b in range(lengths.shape[0]):
        out[1 + b] = np.float32(0.5) * (lengths[b] + lengths[_MIRROR_BONE[b]]) / total
    out[-1] = total


@kernel
def _rest_directions_kernel(directions, lengths, out):
    """(F, B*3) map, (B,) bone lengths -> out (B, 3) unit rest bone directions."""
    features = np.empty(directions.shape[0], dtype=np.float32)
    _features_kernel(lengths, features)
    flat = features @ directions                                       # (B*3,)
    for b in range(out.shape[0]):
        v = flat[3 * b:3 * b + 3]
        out[b] = v / max(np.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2), np.float32(1e-12))


@kernel
def _prior_reference_kernel(directions, tpose, source_lengths, out):
    """The wrapper's work, written into ``out`` (J, 3)."""
    bones = tpose.shape[0] - 1
    target_lengths = np.empty(bones, dtype=np.float32)
    _bone_lengths_kernel(tpose, target_lengths)
    predicted_source = np.empty((bones, 3), dtype=np.float32)
    predicted_target = np.empty((bones, 3), dtype=np.float32)
    _rest_directions_kernel(directions, source_lengths, predicted_source)
    _rest_directions_kernel(directions, target_lengths, predicted_target)
    out[0] = tpose[0]
    for b in range(bones):
        child, parent = b + 1, _PARENTS[b + 1]
        length = target_lengths[b]
        turned = ((tpose[child] - tpose[parent]) / max(length, np.float32(1e-12))
                  + predicted_source[b] - predicted_target[b])
        norm = np.sqrt(turned[0] ** 2 + turned[1] ** 2 + turned[2] ** 2)
        out[child] = out[parent] + turned * (length / max(norm, np.float32(1e-12)))
