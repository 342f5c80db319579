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


# The kernels below are written with scalar loops: numba compiles array expressions, slice
# assignments and its BLAS wrappers slowly, and SMRM's kernel takes them all in (issue 40).

@kernel
def _bone_lengths_kernel(joints, out):
    """(J, 3) joints -> out (B,) bone lengths."""
    for b in range(out.shape[0]):
        child, parent = b + 1, _PARENTS[b + 1]
        x = joints[child, 0] - joints[parent, 0]
        y = joints[child, 1] - joints[parent, 1]
        z = joints[child, 2] - joints[parent, 2]
        out[b] = np.sqrt(x ** 2 + y ** 2 + z ** 2)


@kernel
def _rest_directions_kernel(directions, lengths, out):
    """(F, B*3) map, (B,) bone lengths -> out (B, 3) unit rest bone directions: the module
    docstring's features of the lengths, through the map."""
    total = np.float32(0.0)
    for b in range(lengths.shape[0]):
        total += lengths[b]
    total = max(total, np.float32(1e-6))
    features = np.empty(directions.shape[0], dtype=np.float32)
    features[0] = 1.0
    for b in range(lengths.shape[0]):
        features[1 + b] = np.float32(0.5) * (lengths[b] + lengths[_MIRROR_BONE[b]]) / total
    features[-1] = total
    flat = np.empty(directions.shape[1], dtype=np.float32)            # features @ directions
    flat[:] = 0.0
    for f in range(directions.shape[0]):
        for c in range(directions.shape[1]):
            flat[c] += features[f] * directions[f, c]
    for b in range(out.shape[0]):
        x, y, z = flat[3 * b], flat[3 * b + 1], flat[3 * b + 2]
        norm = max(np.sqrt(x ** 2 + y ** 2 + z ** 2), np.float32(1e-12))
        out[b, 0], out[b, 1], out[b, 2] = x / norm, y / norm, z / norm


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
    turned = np.empty(3, dtype=np.float32)
    for a in range(3):
        out[0, a] = tpose[0, a]
    for b in range(bones):
        child, parent = b + 1, _PARENTS[b + 1]
        length = target_lengths[b]
        for a in range(3):
            turned[a] = ((tpose[child, a] - tpose[parent, a]) / max(length, np.float32(1e-12))
                         + predicted_source[b, a] - predicted_target[b, a])
        norm = np.sqrt(turned[0] ** 2 + turned[1] ** 2 + turned[2] ** 2)
        scale = length / max(norm, np.float32(1e-12))
        for a in range(3):
            out[child, a] = out[parent, a] + turned[a] * scale
