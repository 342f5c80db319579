"""Stage 1b: online smoothing of the source skeleton, between SKR and SMRM.

SKR sees a fresh random sample of the source surface every frame, so the joints it finds
jitter by a centimetre or two from one frame to the next, and SMRM passes that jitter on to
the target. Each joint goes through a One-Euro filter (Casiez, Roussel and Vogel, CHI 2012):
exponential smoothing whose cutoff frequency rises with the joint's speed, so a joint at rest
is smoothed hard (no jitter) and a fast one hardly at all (little lag). Per frame, for a joint
at x_t with the filter's last output y and speed estimate v (m/s):
    v   <- v + a(f_d) (fps (x_t - y) - v)          a(f) = 1 - 1 / (1 + 2 pi f / fps)
    y   <- y + a(f_min + beta |v|) (x_t - y)
Causal and one frame at a time: the state (y, v) lives in ``smrm.MotionState``.

The defaults were chosen on validation trials (held-out subjects on held-out bodies, SKR of
the shipped weights, 12 trials x 150 frames) before looking at the test benchmark: the least
jitter error among a grid of (f_min, beta) whose source-joint MPJPE stays within 5 % of the
raw joints': Acc error 0.0248 -> 0.0186 m/frame^2, MPJPE 0.0482 -> 0.0504 m.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import FPS, NUM_JOINTS
from .validation import as_float32_array


class Smoothing(NamedTuple):
    min_cutoff: float = 8.0         # Hz: cutoff of a joint at rest
    beta: float = 4.0               # Hz per m/s: how fast the cutoff rises with speed
    derivative_cutoff: float = 1.0  # Hz: cutoff of the speed estimate


def check_smoothing(smoothing):
    """A Smoothing with finite cutoffs > 0 and beta >= 0, or None (no smoothing)."""
    if smoothing is None:
        return None
    try:
        smoothing = Smoothing(*map(float, smoothing))
    except (TypeError, ValueError):
        raise ValueError(f"smoothing must be Smoothing(min_cutoff, beta, derivative_cutoff) "
                         f"or None, got {smoothing!r}") from None
    if not (0 < smoothing.min_cutoff < np.inf and 0 <= smoothing.beta < np.inf
            and 0 < smoothing.derivative_cutoff < np.inf):
        raise ValueError(f"smoothing: cutoffs must be finite and > 0 Hz and beta finite and "
                         f">= 0, got {smoothing}")
    return smoothing


def smooth_joints(joints, previous, velocity, smoothing=Smoothing()):
    """One filter step.

    Args:
        joints: (J, 3) float32 this frame's source joints, metres.
        previous: (J, 3) float32 the filter's output at the last frame, metres.
        velocity: (J, 3) float32 its speed estimate at the last frame, metres per second.
        smoothing: Smoothing, or None to pass the joints through (the speed is still
            tracked, so smoothing can be switched on mid-stream).
    Returns:
        the smoothed joints (J, 3) and the new velocity (J, 3), float32.
    """
    joints = as_float32_array(joints, "joints", (NUM_JOINTS, 3))
    previous = as_float32_array(previous, "previous", (NUM_JOINTS, 3))
    velocity = as_float32_array(velocity, "velocity", (NUM_JOINTS, 3))
    smoothing = check_smoothing(smoothing)
    return _smooth_kernel(joints, previous, velocity, *_parameters(smoothing))


def _parameters(smoothing):
    """(min_cutoff, beta, derivative_cutoff) for the kernel: an infinite cutoff passes
    every frame through unchanged."""
    return (np.inf, 0.0, Smoothing().derivative_cutoff) if smoothing is None else smoothing


@kernel
def _smoothing_factor(cutoff):
    """a(f) = 1 - 1 / (1 + 2 pi f / fps): 1 (no smoothing) for an infinite cutoff."""
    return np.float32(1.0) - np.float32(1.0) / (np.float32(1.0)
                                                + np.float32(2 * np.pi / FPS) * cutoff)


@kernel
def _smooth_kernel(joints, previous, velocity, min_cutoff, beta, derivative_cutoff):
    smoothed = np.empty_like(joints)
    new_velocity = np.empty_like(velocity)
    a_derivative = _smoothing_factor(np.float32(derivative_cutoff))
    for j in range(joints.shape[0]):
        speed = np.float32(0.0)
        for c in range(3):
            v = velocity[j, c] + a_derivative * (np.float32(FPS) * (joints[j, c] - previous[j, c])
                                                 - velocity[j, c])
            new_velocity[j, c] = v
            speed += v * v
        a = _smoothing_factor(np.float32(min_cutoff) + np.float32(beta) * np.sqrt(speed))
        for c in range(3):     # a = 1 passes the joint through exactly, not up to rounding
            smoothed[j, c] = joints[j, c] if a >= 1 else \
                previous[j, c] + a * (joints[j, c] - previous[j, c])
    return smoothed, new_velocity
