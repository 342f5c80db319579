"""Stage 1c: online smoothing of the source skeleton, between SKR (and the refiner) and SMRM.

SKR's joints jitter by a centimetre or two from one frame to the next (its error changes
with the pose and the point sample), and SMRM passes that jitter on to the target. Each joint
goes through an alpha-beta filter: a tracker that predicts the joint from its last position
and velocity (constant velocity over one frame), then moves the prediction part of the way to
the measured joint. Per frame, for a joint measured at x_t with the filter's last output y and
velocity v (m/s):
    p = y + v / fps                 the prediction
    y <- p + alpha (x_t - p)        position gain alpha: 1 passes x_t through
    v <- v + beta fps (x_t - p)     velocity gain beta
Because it predicts with the velocity, a joint moving steadily is followed with no lag (a
plain exponential filter, or a One-Euro filter, lags by v (1 - a) / (a fps)), so it can smooth
harder for the same lag. The defaults are near Benedict and Bordner's relation
beta = alpha^2 / (2 - alpha) (0.38 for alpha = 0.7). Causal and one frame at a time: the
state (y, v) is a ``SmoothingState``.

The defaults were chosen on validation trials (held-out subjects on held-out bodies): the
least Acc error among a grid of gains whose target PA-MPJPE is no worse than the One-Euro
filter this replaced (min cutoff 8 Hz, beta 4). Smoothing trades jitter (Acc) against lag
(MPJPE); the figures of the choice, with and without it: docs/runtime_notes.md.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import FPS, NUM_JOINTS
from .validation import as_float32_array


class Smoothing(NamedTuple):
    position_gain: float = 0.7     # alpha in (0, 1]: the share of the prediction's error taken
    velocity_gain: float = 0.35    # beta in [0, alpha]: the same for the velocity, per frame


def check_smoothing(smoothing):
    """A Smoothing with 0 < position_gain <= 1 and 0 <= velocity_gain <= position_gain (the
    filter is then stable; small gains overshoot a step more), or None (no smoothing)."""
    if smoothing is None:
        return None
    try:
        if len(smoothing) != len(Smoothing._fields):
            raise ValueError
        smoothing = Smoothing(*map(float, smoothing))
    except (TypeError, ValueError):
        raise ValueError(f"smoothing must be Smoothing(position_gain, velocity_gain) or None, "
                         f"got {smoothing!r}") from None
    if not (0 < smoothing.position_gain <= 1
            and 0 <= smoothing.velocity_gain <= smoothing.position_gain):
        raise ValueError(f"smoothing: need 0 < position_gain <= 1 and 0 <= velocity_gain <= "
                         f"position_gain, got {smoothing}")
    return smoothing


class SmoothingState(NamedTuple):
    joints: np.ndarray      # (J, 3) float32 the filter's last output y, metres
    velocity: np.ndarray    # (J, 3) float32 its velocity estimate v, m/s


def check_smoothing_state(state):
    """A SmoothingState of finite (J, 3) arrays (C-contiguous float32); ValueError names the
    field."""
    if not isinstance(state, SmoothingState):
        raise ValueError(f"the smoothing's state must be a SmoothingState, got "
                         f"{type(state).__name__}")
    return SmoothingState(*(as_float32_array(value, f"smoothing.{name}", (NUM_JOINTS, 3))
                            for name, value in state._asdict().items()))


def smooth_joints(joints, previous, velocity, smoothing=Smoothing()):
    """One filter step.

    Args:
        joints: (J, 3) float32 this frame's source joints, metres.
        previous: (J, 3) float32 the filter's output at the last frame, metres.
        velocity: (J, 3) float32 its velocity estimate at the last frame, metres per second.
        smoothing: Smoothing, or None to pass the joints through (the velocity is then the
            last frame-to-frame difference, so smoothing can be switched on mid-stream).
    Returns:
        the smoothed joints (J, 3) and the new velocity (J, 3), float32.
    """
    joints = as_float32_array(joints, "joints", (NUM_JOINTS, 3))
    previous = as_float32_array(previous, "previous", (NUM_JOINTS, 3))
    velocity = as_float32_array(velocity, "velocity", (NUM_JOINTS, 3))
    smoothing = check_smoothing(smoothing)
    return _smooth_kernel(joints, previous, velocity, *_parameters(smoothing))


def _parameters(smoothing):
    """(position_gain, velocity_gain) for the kernel: gains of 1 pass every frame through
    and make the velocity the frame-to-frame difference."""
    return (1.0, 1.0) if smoothing is None else smoothing


@kernel
def _smooth_kernel(joints, previous, velocity, position_gain, velocity_gain):
    smoothed = np.empty_like(joints)
    new_velocity = np.empty_like(velocity)
    alpha, beta = np.float32(position_gain), np.float32(velocity_gain)
    for j in range(joints.shape[0]):
        for c in range(3):
            predicted = previous[j, c] + velocity[j, c] / np.float32(FPS)
            error = joints[j, c] - predicted
            # alpha = 1 passes the joint through exactly, not up to rounding
            smoothed[j, c] = joints[j, c] if alpha >= 1 else predicted + alpha * error
            new_velocity[j, c] = velocity[j, c] + beta * np.float32(FPS) * error
    return smoothed, new_velocity
