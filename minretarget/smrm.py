"""Stage 2, SMRM: skeletal motion retargeting, one frame at a time with explicit GRU state.

Per frame, with source joints x_t (J, 3) (the stages before it: smoothed, denoised, fitted,
as the pipeline says) and the target's T-pose skeleton s (J, 3):
    1. heading H_t: the turn about +Y from +Z to the way the source faces (hips and shoulders);
       the network sees and predicts everything in this body-aligned frame
    2. features: H_t^T (x_t - x_t[0]) (J*3) and the root velocity H_t^T (x_t[0] - x_{t-1}[0])
    3. encoder GRU over the features; decoder GRU over [encoder output, s - s[0]]
    4. heads: (J, 4) unit quaternions (the root's relative to H_t) and a root offset d_t (3, m);
       with ``smrm_analytic_prior`` weights each quaternion is instead a correction applied
       after the analytic rotation of x_t onto s (``minretarget.analytic``), in the joint's
       frame, and step 5's heading turn is not needed (the analytic root rotation has it);
       with rest-pose weights (``minretarget.rest_pose``) the prior turns onto x_t the bones of
       s as turned by the two bodies' predicted rest poses, from the mean source bone lengths
    5. root rotation H_t q_0; root r_t = k_t * x_t[0] + H_t d_t, where k_t = the target's leg
       length (s's, or as given: the pipeline reads a mesh's from its surface) / the mean
       source leg length over the frames seen so far (the source root scaled to the
       target's size, then corrected). The mean: with the joint refiner (minretarget.refine)
       the source legs are about right on average, and on validation trials the running mean
       is 2.4 % off the true length (unbiased), the running maximum 4.0 % (3.7 % long, which
       sank the body 2.8 cm; with SKR alone, whose legs come out short, the maximum was
       better: 3.6 % against 3.6 % biased 1.9 % short)
Forward kinematics of the quaternions on s at r_t (minretarget.kinematics) poses the target.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .analytic import _analytic_frame
from .kinematics import _quaternion_multiply_one, leg_length
from .conventions import NUM_JOINTS
from .heading import heading_features, turn_about_up
# GRULayer lived here once: numba's on-disk caches from then name it minretarget.smrm.GRULayer
# and must still unpickle (to be found stale) rather than fail the import.
from .nn import Dense, GRULayer, dense, gru_step  # noqa: F401
from .rest_pose import (NUM_BONES, _bone_lengths_kernel, _prior_reference_kernel,
                        check_rest_pose)
from .validation import as_count, as_float32_array


class SMRMWeights(NamedTuple):
    encoder: tuple          # GRULayer per layer
    decoder: tuple          # GRULayer per layer
    rotation_head: Dense    # (H, J*4)
    root_head: Dense        # (H, 3)
    # The config's smrm_analytic_prior, carried with the arrays so no caller can pair the
    # heads with the wrong meaning: the rotations are corrections to the analytic ones (step 4').
    analytic_prior: bool = False


class SMRMState(NamedTuple):
    """What SMRM carries from one frame to the next."""
    encoder_hidden: np.ndarray       # (layers, H) float32
    decoder_hidden: np.ndarray       # (layers, H) float32
    previous_root: np.ndarray        # (3,) float32 the root of the source joints it saw last
    source_bone_lengths: np.ndarray  # (B,) float32 mean source bone lengths over the frames
                                     # seen, metres (``rest_pose.bone_lengths``'s order)
    frames_seen: int


def initial_state(weights, first_joints):
    """The state before a stream whose first source frame has joints ``first_joints`` (J, 3),
    for SMRMWeights ``weights``: zero GRU states and bone lengths, the first root."""
    layers, hidden = len(weights.encoder), weights.encoder[0].hidden_weight.shape[0]
    zeros = np.zeros((layers, hidden), dtype=np.float32)
    return SMRMState(zeros, zeros.copy(), np.array(first_joints[0], dtype=np.float32),
                     np.zeros(NUM_BONES, dtype=np.float32), 0)


def check_state(weights, state):
    """An SMRMState checked against ``weights`` (e.g. one read back from a file): hidden
    states of the right shapes, a finite (3,) root, finite (B,) bone lengths >= 0, a count.
    Returns it with C-contiguous float32 arrays; ValueError names the field."""
    layers, hidden = len(weights.encoder), weights.encoder[0].hidden_weight.shape[0]
    if not isinstance(state, SMRMState):
        raise ValueError(f"SMRM's state must be an SMRMState, got {type(state).__name__}")
    encoder = as_float32_array(state.encoder_hidden, "smrm.encoder_hidden", (layers, hidden))
    decoder = as_float32_array(state.decoder_hidden, "smrm.decoder_hidden", (layers, hidden))
    root = as_float32_array(state.previous_root, "smrm.previous_root", (3,))
    lengths = as_float32_array(state.source_bone_lengths, "smrm.source_bone_lengths",
                               (NUM_BONES,))
    if not (lengths >= 0).all():
        raise ValueError(f"smrm.source_bone_lengths must be >= 0, got {lengths.min()} at "
                         f"bone {int(lengths.argmin())}")
    return SMRMState(encoder, decoder, root, lengths, as_count(state.frames_seen,
                                                               "smrm.frames_seen"))


def retarget_step(weights, state, source_joints, target_tpose, rest_pose=None,
                  target_leg_length=None):
    """Retarget one frame.

    Args:
        weights: SMRMWeights.
        state: SMRMState after the previous frame, or None for a stream's first frame.
        source_joints: (J, 3) float32 source joint positions, metres.
        target_tpose: (J, 3) float32 target T-pose joints, metres.
        rest_pose: ``rest_pose.RestPoseWeights`` for the prior to allow for the two bodies'
            rest poses (step 4), or None (the plain analytic prior).
        target_leg_length: the target's hip-knee-ankle length that scales the root (step 5),
            metres, or None: ``target_tpose``'s (``kinematics.leg_length``).
    Returns:
        rotations (J, 4) float32 unit quaternions (w, x, y, z), root (3,) float32 metres,
        and the new SMRMState.
    """
    source_joints = as_float32_array(source_joints, "source_joints", (NUM_JOINTS, 3))
    target_tpose = as_float32_array(target_tpose, "target_tpose", (NUM_JOINTS, 3))
    if state is not None:
        state = check_state(weights, state)
    rest = _NO_REST_POSE if rest_pose is None else check_rest_pose(rest_pose).directions
    target_leg_length = (float(leg_length(target_tpose)) if target_leg_length is None else
                         check_leg_length(target_leg_length, "target_leg_length"))
    return step_checked(weights, state, source_joints, target_tpose, rest, target_leg_length)


_FLOAT32_RANGE = float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max)


def check_leg_length(value, name):
    """``value`` (a length given, metres) as a float if it is a real number > 0 that float32
    keeps (the kernel's precision), else a ValueError naming ``name``."""
    real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_))
    if not real or not _FLOAT32_RANGE[0] <= float(value) <= _FLOAT32_RANGE[1]:
        raise ValueError(f"{name} must be a finite length > 0 (metres), got {value!r}")
    return float(value)


def step_checked(weights, state, source_joints, target_tpose, rest_directions,
                 target_leg_length):
    """``retarget_step`` on checked inputs (``rest_directions``: RestPoseWeights.directions
    or ``_NO_REST_POSE``; ``target_leg_length``, metres): the pipeline's SMRM stage."""
    if state is None:
        state = initial_state(weights, source_joints)
    encoder_hidden = state.encoder_hidden.copy()
    decoder_hidden = state.decoder_hidden.copy()
    lengths = state.source_bone_lengths.copy()
    rotations, root = _retarget_step_kernel(
        weights, source_joints, target_tpose, rest_directions, encoder_hidden, decoder_hidden,
        state.previous_root, lengths, state.frames_seen, np.float32(target_leg_length))
    return rotations, root, SMRMState(encoder_hidden, decoder_hidden, source_joints[0].copy(),
                                      lengths, state.frames_seen + 1)


# The bones (rest_pose.bone_lengths' order) of the hip-knee-ankle chains, left then right
# (``kinematics.leg_length``'s), and no rest-pose model.
LEG_BONES = (3, 6, 4, 7)
_NO_REST_POSE = np.zeros((0, 3 * NUM_BONES), dtype=np.float32)


@kernel
def _leg_from_bones(lengths):
    """Mean hip-knee-ankle chain length from (B,) bone lengths (``kinematics.leg_length``)."""
    total = np.float32(0.0)
    for b in LEG_BONES:
        total += lengths[b]
    return total / np.float32(2.0)


@kernel
def _retarget_step_kernel(weights, source_joints, target_tpose, rest_directions, encoder_hidden,
                          decoder_hidden, previous_root, source_bone_lengths, frames_seen,
                          target_leg_length):
    """One frame, the module docstring's steps 1-5; updates the hidden states in place, and
    ``source_bone_lengths`` (B,), the mean over ``frames_seen`` frames, to include this one.
    ``rest_directions``: RestPoseWeights.directions, or (0, B*3) for the plain prior.
    ``target_leg_length``: float32, metres, the numerator of step 5's scale.
    Returns rotations (J, 4) and root (3,)."""
    j = source_joints.shape[0]
    root = source_joints[0]
    lengths = np.empty_like(source_bone_lengths)
    _bone_lengths_kernel(source_joints, lengths)
    for b in range(lengths.shape[0]):
        source_bone_lengths[b] += (lengths[b] - source_bone_lengths[b]) / np.float32(
            frames_seen + 1)
    # 1-2. heading, and the features in the heading frame (turned by -heading)
    features, sin, cos = heading_features(source_joints, previous_root)
    # 3. encoder, then decoder over [encoded, T-pose relative to its root]
    encoded = gru_step(features, encoder_hidden, weights.encoder)       # (1, H)
    # (scalar loops, not slice assignments: those compile numba's shape-mismatch error)
    width = encoded.shape[1]
    decoder_input = np.empty((1, width + 3 * j), dtype=np.float32)
    for i in range(width):
        decoder_input[0, i] = encoded[0, i]
    for k in range(j):
        for a in range(3):
            decoder_input[0, width + 3 * k + a] = target_tpose[k, a] - target_tpose[0, a]
    decoded = gru_step(decoder_input, decoder_hidden, weights.decoder)
    # 4. heads: unit quaternions and the root offset
    q = dense(decoded, weights.rotation_head, False).reshape(-1, 4)      # (J, 4)
    for k in range(q.shape[0]):
        norm = max(np.sqrt(q[k, 0] ** 2 + q[k, 1] ** 2 + q[k, 2] ** 2 + q[k, 3] ** 2),
                   np.float32(1e-8))
        for a in range(4):
            q[k, a] /= norm
    offset = dense(decoded, weights.root_head, False)[0]                # (3,)
    if weights.analytic_prior:   # 4'. each a correction after the analytic rotation, in its frame
        reference = target_tpose
        if rest_directions.shape[0] > 0:
            reference = np.empty_like(target_tpose)
            _prior_reference_kernel(rest_directions, target_tpose, source_bone_lengths,
                                    reference)
        prior = np.empty((j, 4), dtype=np.float32)
        _analytic_frame(source_joints, reference, prior, np.empty((j, 3, 3)))
        correction = np.empty(4, dtype=np.float32)
        for k in range(j):
            for a in range(4):
                correction[a] = q[k, a]
            _quaternion_multiply_one(prior[k], correction, q[k])
    else:                # 5. root rotation turned by the heading (half angle: stable at pi)
        half = np.arctan2(sin, cos) / np.float32(2.0)
        hw, hy = np.cos(half), np.sin(half)
        w, x, y, z = q[0, 0], q[0, 1], q[0, 2], q[0, 3]
        q[0, 0], q[0, 1], q[0, 2], q[0, 3] = hw * w - hy * y, hw * x + hy * z, \
            hw * y + hy * w, hw * z - hy * x
    # ... and the root: the source root scaled to the target's size, plus the turned offset
    # (a degenerate source whose legs have no length must not divide by zero)
    scale = np.float32(target_leg_length
                       / max(_leg_from_bones(source_bone_lengths), np.float32(1e-6)))
    out_root = np.empty(3, dtype=np.float32)
    out_root[0], out_root[1], out_root[2] = turn_about_up(offset[0], offset[1], offset[2],
                                                           sin, cos)
    for a in range(3):
        out_root[a] += scale * root[a]
    return q, out_root
