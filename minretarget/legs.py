"""Stage 1b'': the leg check. Legs read swapped are swapped back.

Where a dancer crosses one foot over the other, SKR puts each foot back on its own side: its
right foot lies on the cloud's left foot and its left on the right (``benchmarks/
heading_flips.py`` counts these frames), and the target's planted foot jumps across and back.
Motion alone cannot tell which labelling is right (a rule that keeps the legs' motion smooth
locks onto the wrong one as often as it mends the right one), and neither can the cloud's
shape near the bones. A second SKR trained with crossed legs in its frames (the weights'
``legs``; ``python -m training.export add-legs``) reads most crossings right, but plain
motion a little worse. So each frame the shipped reading stands unless both agree that its
legs are swapped:
    1. the reading's feet (ankles and toes), or its lower legs (knees too), exchanged, move at
       least ``JUMP`` less (summed over the six joints) from the last frame's checked
       skeleton than the reading does (it jumped);
    2. and the exchange lies nearer the second SKR's reading of the same cloud (run only
       then: nearly every frame skips it).
The feet are tried first, then the lower legs, which must move ``JUMP`` less again.

Scored on the readings alone (no smoothing; ``docs/training_notes.md``, "SKR on online
crossed legs"): legs swapped on validation 0 -> 0, on the training dances on held-out bodies
30 -> 25; condition 1 alone takes the dances to 80, condition 2 alone adds 5 swaps on
validation.
"""
import numpy as np

from .conventions import JOINT_INDEX, NUM_JOINTS
from .validation import as_float32_array

JUMP = 0.1   # metres, summed over the six joints, that an exchange must save to be considered
# Per leg (left, right): knee, ankle, toe.
LOWER_LEGS = np.array([[JOINT_INDEX[f"{side}_{name}"] for name in ("knee", "ankle", "foot")]
                       for side in ("left", "right")])
# What may be exchanged: the feet (ankle and toe), or the lower legs (knee too).
EXCHANGES = (LOWER_LEGS[:, 1:], LOWER_LEGS)


def exchanged(joints, pair):
    """(..., J, 3) joints with the left and right joints of ``pair`` (2, n) exchanged."""
    out = np.array(joints, dtype=np.float32)
    out[..., pair[0], :], out[..., pair[1], :] = joints[..., pair[1], :], joints[..., pair[0], :]
    return out


def leg_distance(a, b):
    """Summed distance of the six lower-leg joints of (..., J, 3) ``a`` and ``b``, metres."""
    return np.linalg.norm(a[..., LOWER_LEGS, :] - b[..., LOWER_LEGS, :], axis=-1).sum((-2, -1))


def check_legs(reading, previous, second_reading, jump=JUMP):
    """The leg check on one frame.

    Args:
        reading: (J, 3) float32 the frame's skeleton (SKR's, after the facing check), metres.
        previous: (J, 3) float32 the last frame's checked skeleton, metres.
        second_reading: () -> (J, 3) the second SKR's reading of the frame's cloud; called
            only when an exchange passes condition 1.
        jump: metres, condition 1's margin.
    Returns:
        (J, 3) float32: ``reading``, or it with its feet or lower legs exchanged.
    """
    reading = as_float32_array(reading, "reading", (NUM_JOINTS, 3))
    previous = as_float32_array(previous, "previous", (NUM_JOINTS, 3))
    if not jump >= 0:
        raise ValueError(f"jump must be >= 0 metres, got {jump!r}")
    return _check_legs(reading, previous, second_reading, jump)


def _check_legs(reading, previous, second_reading, jump):
    """``check_legs`` on inputs already checked (the Retargeter's, every frame)."""
    best, moved, second = reading, leg_distance(reading, previous), None
    for pair in EXCHANGES:               # the lower legs must beat the feet by ``jump`` too
        candidate = exchanged(reading, pair)
        candidate_moved = leg_distance(candidate, previous)
        if not candidate_moved < moved - jump:            # nearly every frame
            continue
        if second is None:
            second = second_reading()
        if leg_distance(candidate, second) < leg_distance(reading, second):
            best, moved = candidate, candidate_moved
    return best
