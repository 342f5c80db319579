"""Stage 2, SMRM: skeletal motion retargeting, one frame at a time with explicit GRU state.

Per frame, with source joints x_t (J, 3) and the target's T-pose skeleton s (J, 3):
    1. heading H_t: the turn about +Y from +Z to the way the source faces (hips and shoulders);
       the network sees and predicts everything in this body-aligned frame
    2. features: H_t^T (x_t - x_t[0]) (J*3) and the root velocity H_t^T (x_t[0] - x_{t-1}[0])
    3. encoder GRU over the features; decoder GRU over [encoder output, s - s[0]]
    4. heads: (J, 4) unit quaternions (the root's relative to H_t) and a root offset d_t (3, m)
    5. root rotation H_t q_0; root r_t = k_t * x_t[0] + H_t d_t, where k_t = leg length of s /
       running mean of the source's leg length (the source root scaled to the target's size,
       then corrected)
Forward kinematics of the quaternions on s at r_t (minretarget.kinematics) poses the target.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import NUM_JOINTS
from .kinematics import leg_length, quaternion_multiply
from .nn import Dense, dense, sigmoid
from .validation import as_float32_array


class GRULayer(NamedTuple):
    input_weight: np.ndarray    # (in, 3H) float32, gates in torch's order: reset, update, new
    hidden_weight: np.ndarray   # (H, 3H)
    input_bias: np.ndarray      # (3H,)
    hidden_bias: np.ndarray     # (3H,)


class SMRMWeights(NamedTuple):
    encoder: tuple          # GRULayer per layer
    decoder: tuple          # GRULayer per layer
    rotation_head: Dense    # (H, J*4)
    root_head: Dense        # (H, 3)


class MotionState(NamedTuple):
    """Everything SMRM carries from one frame to the next."""
    encoder_hidden: np.ndarray   # (layers, H) float32
    decoder_hidden: np.ndarray   # (layers, H) float32
    previous_root: np.ndarray    # (3,) float32 source root of the last frame, metres
    leg_length_sum: float        # sum of the source leg lengths seen, metres
    frames_seen: int


def initial_state(weights, first_joints):
    """The state before a stream whose first source frame has joints ``first_joints`` (J, 3)."""
    layers, hidden = len(weights.encoder), weights.encoder[0].hidden_weight.shape[0]
    zeros = np.zeros((layers, hidden), dtype=np.float32)
    return MotionState(zeros, zeros.copy(), np.array(first_joints[0], dtype=np.float32), 0.0, 0)


def check_state(weights, state):
    """A MotionState checked against ``weights`` (e.g. one read back from a file): hidden
    states (layers, H), a finite (3,) root, a count and a finite sum >= 0. Returns it with
    C-contiguous float32 arrays; ValueError names the field."""
    layers, hidden = len(weights.encoder), weights.encoder[0].hidden_weight.shape[0]
    if not isinstance(state, MotionState):
        raise ValueError(f"state must be a MotionState, got {type(state).__name__}")
    encoder = as_float32_array(state.encoder_hidden, "state.encoder_hidden", (layers, hidden))
    decoder = as_float32_array(state.decoder_hidden, "state.decoder_hidden", (layers, hidden))
    previous_root = as_float32_array(state.previous_root, "state.previous_root", (3,))
    try:
        leg_sum, frames = float(state.leg_length_sum), int(state.frames_seen)
    except (TypeError, ValueError, OverflowError):                  # None, "x", inf
        leg_sum, frames = np.nan, -1
    if frames < 0 or frames != state.frames_seen or not 0 <= leg_sum < np.inf:
        raise ValueError(f"state: frames_seen {state.frames_seen!r} and leg_length_sum "
                         f"{state.leg_length_sum!r} must be a count and a finite sum >= 0")
    return MotionState(encoder, decoder, previous_root, leg_sum, frames)


def retarget_step(weights, state, source_joints, target_tpose):
    """Retarget one frame.

    Args:
        weights: SMRMWeights.
        state: MotionState after the previous frame, or None for a stream's first frame.
        source_joints: (J, 3) float32 source joint positions, metres.
        target_tpose: (J, 3) float32 target T-pose joints, metres.
    Returns:
        rotations (J, 4) float32 unit quaternions (w, x, y, z), root (3,) float32 metres,
        and the new MotionState.
    """
    source_joints = as_float32_array(source_joints, "source_joints", (NUM_JOINTS, 3))
    target_tpose = as_float32_array(target_tpose, "target_tpose", (NUM_JOINTS, 3))
    if state is None:
        state = initial_state(weights, source_joints)
    root = source_joints[0]
    sin, cos = heading(source_joints)
    features = np.concatenate([turn_about_up(source_joints - root, -sin, cos).ravel(),
                               turn_about_up(root - state.previous_root, -sin, cos)])
    skeleton = (target_tpose - target_tpose[0]).ravel()                 # (J*3,)
    encoder_hidden = state.encoder_hidden.copy()
    decoder_hidden = state.decoder_hidden.copy()
    rotations, offset = _retarget_step_kernel(weights, features[None], skeleton[None],
                                              encoder_hidden, decoder_hidden)
    half = np.arctan2(sin, cos) / 2                                     # stable at a half turn
    rotations[0] = quaternion_multiply([np.cos(half), 0.0, np.sin(half), 0.0], rotations[0])
    leg_sum = state.leg_length_sum + float(leg_length(source_joints))
    frames = state.frames_seen + 1
    scale = np.float32(leg_length(target_tpose) / np.float32(leg_sum / frames))
    new_state = MotionState(encoder_hidden, decoder_hidden, root.copy(), leg_sum, frames)
    return rotations, scale * root + turn_about_up(offset, sin, cos), new_state


def heading(joints):
    """(J, 3) joints -> (sin, cos) of the turn about +Y taking +Z to the facing direction.

    Facing = across x up, with across = (left hip - right hip) + (left shoulder - right
    shoulder): in the T-pose, across is +X and the body faces +Z.
    """
    across = joints[1] - joints[2] + joints[16] - joints[17]
    norm = max(float(np.hypot(across[0], across[2])), 1e-8)
    return np.float32(-across[2] / norm), np.float32(across[0] / norm)


def turn_about_up(vectors, sin, cos):
    """Rotate (..., 3) vectors about +Y by the angle with this sine and cosine."""
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    return np.stack([cos * x + sin * z, y, cos * z - sin * x], axis=-1).astype(np.float32)


@kernel
def gru_layer_step(x, hidden, layer):
    """One GRU cell step, torch's equations. x (1, in), hidden (1, H) -> new hidden (1, H)."""
    h = hidden.shape[1]
    gates_x = dense(x, Dense(layer.input_weight, layer.input_bias), False)       # (1, 3H)
    gates_h = dense(hidden, Dense(layer.hidden_weight, layer.hidden_bias), False)
    out = np.empty_like(hidden)
    for k in range(h):
        reset = sigmoid(gates_x[0, k] + gates_h[0, k])
        update = sigmoid(gates_x[0, h + k] + gates_h[0, h + k])
        new = np.tanh(gates_x[0, 2 * h + k] + reset * gates_h[0, 2 * h + k])
        out[0, k] = (np.float32(1.0) - update) * new + update * hidden[0, k]
    return out


@kernel
def _gru_step(x, hidden, layers):
    """Stacked GRU step; updates ``hidden`` (layers, H) in place, returns the top output."""
    for i in range(len(layers)):
        x = gru_layer_step(x, hidden[i:i + 1], layers[i])
        hidden[i] = x[0]
    return x


@kernel
def _retarget_step_kernel(weights, features, skeleton, encoder_hidden, decoder_hidden):
    encoded = _gru_step(features, encoder_hidden, weights.encoder)       # (1, H)
    decoder_input = np.concatenate((encoded, skeleton), axis=1)          # (1, H + J*3)
    decoded = _gru_step(decoder_input, decoder_hidden, weights.decoder)
    q = dense(decoded, weights.rotation_head, False).reshape(-1, 4)      # (J, 4)
    for j in range(q.shape[0]):
        norm = np.sqrt(q[j, 0] ** 2 + q[j, 1] ** 2 + q[j, 2] ** 2 + q[j, 3] ** 2)
        q[j] /= max(norm, np.float32(1e-8))
    offset = dense(decoded, weights.root_head, False)[0]                # (3,)
    return q, offset
