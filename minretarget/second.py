"""Stage 1b'': the second reading. Two skeleton readers, averaged where they agree on the legs.

The first SKR reads plain gait well and crossed legs badly: where a dancer crosses one foot
over the other it puts each foot back on its own side (``benchmarks/heading_flips.py``). A
second SKR trained with crossed legs in its frames, with a joint refiner of its own (the
weights' ``second``; ``python -m training.export add-second``), reads crossings better but
plain running worse, now and then with the legs swapped. So every cloud is read by both:
    1. where no exchange of the first reading's feet (ankles and toes) or lower legs (knees
       too) lies ``AGREE`` nearer the second reading than the first reading itself does
       (summed over the six joints), the two agree on the legs: the skeleton is their mean;
    2. elsewhere the first reading stands.
Two readers with errors of their own also average some of each one's error away (about 6 %
of the source skeleton's, on every split). Measured through the runtime against the first
reader alone (``docs/training_notes.md``, "SKR on online crossed legs"): validation PA-MPJPE
-0.42 mm [-0.95, +0.13], Acc -0.27 mm/frame^2 [-0.32, -0.22]; training dances PA-MPJPE -0.88
[-1.52, -0.30], Acc -0.51 [-0.63, -0.44], toes 0.139 m/s against 0.147. SKR and the refiner
run twice per frame.
"""
from typing import NamedTuple

import numpy as np

from .conventions import JOINT_INDEX, NUM_JOINTS
from .refine import RefinerWeights
from .skr import SKRWeights
from .validation import as_float32_array

AGREE = 0.1   # metres, summed over the six joints, an exchange must gain to show disagreement
# Per leg (left, right): knee, ankle, toe.
LOWER_LEGS = np.array([[JOINT_INDEX[f"{side}_{name}"] for name in ("knee", "ankle", "foot")]
                       for side in ("left", "right")])
# What a reader may swap: the feet (ankle and toe), or the lower legs (knee too).
EXCHANGES = (LOWER_LEGS[:, 1:], LOWER_LEGS)


class SecondReader(NamedTuple):
    skr: SKRWeights           # the same sizes as the first SKR
    refine: RefinerWeights    # the same sizes as the first refiner


def exchanged(joints, pair):
    """(..., J, 3) joints with the left and right joints of ``pair`` (2, n) exchanged."""
    out = np.array(joints, dtype=np.float32)
    out[..., pair[0], :], out[..., pair[1], :] = joints[..., pair[1], :], joints[..., pair[0], :]
    return out


def leg_distance(a, b):
    """(...,) summed distance of the six lower-leg joints of (..., J, 3) ``a`` and ``b``,
    metres."""
    return np.linalg.norm(a[..., LOWER_LEGS, :] - b[..., LOWER_LEGS, :], axis=-1).sum((-2, -1))


def legs_agree(first, second, margin=AGREE):
    """(...,) bool: no exchange of ``first``'s legs lies ``margin`` metres nearer ``second``
    than ``first`` does. ``first``, ``second``: (..., J, 3) readings of the same clouds."""
    as_read = leg_distance(first, second)
    return np.all([~(leg_distance(exchanged(first, pair), second) < as_read - margin)
                   for pair in EXCHANGES], axis=0)


def combined_readings(first, second, margin=AGREE):
    """The skeletons of clouds read by two readers.

    Args:
        first: (J, 3) or (T, J, 3) float32 the first reader's skeletons, metres.
        second: the second reader's of the same clouds, like ``first``.
        margin: metres, ``AGREE``.
    Returns:
        like ``first``: the mean of the two where ``legs_agree``, else ``first``.
    """
    first = as_float32_array(first, "first", (..., NUM_JOINTS, 3))
    if first.ndim not in (2, 3):
        raise ValueError(f"first must have shape (J, 3) or (T, J, 3), got {first.shape}")
    second = as_float32_array(second, "second", first.shape)
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0 metres, got {margin!r}")
    return _combined_readings(first, second, margin)


def _combined_readings(first, second, margin):
    """``combined_readings`` on inputs already checked (the Retargeter's)."""
    agree = legs_agree(first, second, margin)[..., None, None]
    return np.where(agree, (first + second) / np.float32(2), first).astype(np.float32)
