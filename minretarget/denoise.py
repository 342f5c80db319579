"""Stage 1d, skeleton denoising: a small GRU that removes what is left of SKR's jitter, online.

SKR and the joint refiner see each cloud on its own, so their error changes from frame to
frame: the source skeleton shakes by a centimetre or two, and SMRM passes that on to the
target. The smoothing (``minretarget.smoothing``) can only trade that jitter against lag. The
denoiser has learned how bodies move: trained on SKR's own skeletons of whole training
trials against the true joints, it predicts a correction of each joint from the skeletons
seen so far. Per frame, with the smoothed joints s_t (J, 3) and the last frame's root:

    features: s_t - s_t[0] (J*3) and s_t[0] - s_{t-1}[0] (3), turned into the heading frame
              (SMRM's: ``heading.heading_features``)
    GRU (``denoise_layers`` x ``denoise_hidden``) -> Dense -> offsets d (J, 3), heading frame
    denoised joints: s_t + d turned back to the world

The step runs twice, on the skeleton and on its mirror image (x -> -x, left and right joints
swapped), each with its own GRU state, and the second answer, mirrored back, is averaged with
the first: a body and its mirror image then get mirrored corrections, and the average is the
better estimate (on validation trials, in joint and acceleration error; ``training.train``
scores the denoiser this way; the figures: docs/runtime_notes.md). It costs one GRU step more
per frame, small beside SKR.

Causal: only frames seen so far, one at a time; the GRU states and the last root are a
``DenoiseState``. Not in the paper.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import LEFT_AXIS, MIRROR, NUM_JOINTS
from .heading import heading_features, turn_about_up
from .nn import Dense, dense, gru_step
from .validation import as_float32_array

_MIRROR = np.array(MIRROR, dtype=np.int64)


class DenoiserWeights(NamedTuple):
    gru: tuple      # GRULayer per layer, input J*3 + 3
    head: Dense     # (H, J*3): each joint's offset in the heading frame, metres


class DenoiseState(NamedTuple):
    hidden: np.ndarray          # (2, layers, H) float32 the GRU states, the skeleton's and its
                                # mirror image's
    previous_root: np.ndarray   # (3,) float32 the root of the joints it denoised last, metres


def hidden_shape(weights):
    """The shape of the GRU states of DenoiserWeights ``weights``: (2, layers, H), the
    skeleton's and its mirror image's."""
    return 2, len(weights.gru), weights.gru[0].hidden_weight.shape[0]


def initial_state(weights, first_joints):
    """The state before a stream whose first (smoothed) joints are ``first_joints`` (J, 3):
    zero GRU states, and the first root as the last one (the root has not moved yet)."""
    return DenoiseState(np.zeros(hidden_shape(weights), np.float32),
                        np.array(first_joints[0], np.float32))


def check_state(weights, state):
    """A DenoiseState fitting ``weights`` (C-contiguous float32); ValueError names the field."""
    if not isinstance(state, DenoiseState):
        raise ValueError(f"the denoiser's state must be a DenoiseState, got "
                         f"{type(state).__name__}")
    return DenoiseState(as_float32_array(state.hidden, "denoiser.hidden", hidden_shape(weights)),
                        as_float32_array(state.previous_root, "denoiser.previous_root", (3,)))


def denoise_joints(weights, hidden, joints, previous_root):
    """One frame.

    Args:
        weights: DenoiserWeights.
        hidden: (2, layers, H) float32 the GRU states after the last frame, the skeleton's
            and its mirror image's (zeros at a stream's start).
        joints: (J, 3) float32 this frame's (smoothed) source joints, metres.
        previous_root: (3,) float32 the last frame's root (pelvis) of those joints, metres
            (this frame's at a stream's start).
    Returns:
        the denoised joints (J, 3) and the new hidden states (2, layers, H), float32.
    """
    hidden = as_float32_array(hidden, "hidden", hidden_shape(weights)).copy()
    joints = as_float32_array(joints, "joints", (NUM_JOINTS, 3))
    previous_root = as_float32_array(previous_root, "previous_root", (3,))
    return _denoise_mirror_averaged_kernel(weights, joints, previous_root, hidden), hidden


@kernel
def _mirrored(joints):
    """(J, 3) joints of the mirror image: x -> -x, left and right joints swapped."""
    out = joints[_MIRROR]                   # fancy indexing: already a copy
    out[:, LEFT_AXIS] = -out[:, LEFT_AXIS]
    return out


@kernel
def _denoise_mirror_averaged_kernel(weights, joints, previous_root, hidden):
    """The step on the skeleton and on its mirror image, averaged; updates ``hidden``
    (2, layers, H) in place."""
    plain = _denoise_kernel(weights, joints, previous_root, hidden[0])
    root_mirrored = previous_root.copy()
    root_mirrored[LEFT_AXIS] = -root_mirrored[LEFT_AXIS]
    mirrored = _mirrored(_denoise_kernel(weights, _mirrored(joints), root_mirrored, hidden[1]))
    return (plain + mirrored) * np.float32(0.5)


@kernel
def _denoise_kernel(weights, joints, previous_root, hidden):
    """The module docstring's step on one view; updates ``hidden`` (layers, H) in place."""
    features, sin, cos = heading_features(joints, previous_root)
    offsets = dense(gru_step(features, hidden, weights.gru), weights.head, False)   # (1, J*3)
    out = np.empty_like(joints)
    for k in range(joints.shape[0]):
        dx, dy, dz = turn_about_up(offsets[0, 3 * k], offsets[0, 3 * k + 1],
                                   offsets[0, 3 * k + 2], sin, cos)
        out[k, 0], out[k, 1], out[k, 2] = joints[k, 0] + dx, joints[k, 1] + dy, joints[k, 2] + dz
    return out
