"""Stage 1b': the facing check. A skeleton read backwards is read again, half turned.

A point cloud does not say which way its body faces, and SKR now and then reads a body
backwards: its skeleton turns half round about the vertical from one frame to the next, the
legs and arms come out crossed and the feet jump by tens of centimetres (``benchmarks/
heading_flips.py`` counts these frames). In a stream, the way the body faced a frame ago is
known, and a body does not turn far in a frame. So the stream keeps a reference heading h0
(``FacingState.reference``: at first the first frame's) and, per frame:
    1. SKR's skeleton of the cloud (the reading) faces h1 (``heading.heading_angles``); if
       it is within ``TRIGGER`` of h0 it stands and h0 becomes h1 (nearly every frame: no
       cost);
    2. else SKR reads the cloud again turned half round about the vertical through its
       centroid, and its skeleton is turned back: a second reading, with SKR's error in
       another place, since SKR sees another picture. If it faces within ``TRIGGER`` of h0,
       it is taken and h0 becomes its heading;
    3. else both face away: the one facing nearer h0 is taken, but h0 stays, so that one
       frame read backwards twice does not turn the reference round and have the next,
       right, reading refused. Only after ``CONFIRM`` such frames in a row does h0 become the
       first reading's heading (the body did turn, or h0 was wrong from the start).

``TRIGGER``, ``CONFIRM`` and the wait of step 3 were chosen on the training split's dance and
seated trials (validation has no flips to tune on), by how many frames still face more than
90 degrees from the truth's: the check about halves them, for a second reading on a small
fraction of the frames, and waiting before moving h0 beats moving it at once or never. The
counts of each variant: docs/runtime_notes.md, "Facing check".
"""
from typing import NamedTuple

import numpy as np

from .conventions import MIN_POINTS, NUM_JOINTS
from .heading import heading_angles, wrapped
from .validation import as_count, as_float32_array, as_point_cloud

TRIGGER = np.radians(45.0)   # a reading facing further than this from the reference is read
#                              again
CONFIRM = 5                  # frames in a row of both readings facing away that move the
#                              reference to the first reading's heading


class FacingState(NamedTuple):
    reference: float      # the heading the body is taken to face, radians (nan: none yet)
    away_frames: int      # frames in a row whose readings both faced away from it


def check_facing_state(state):
    """A FacingState of a finite (or nan) reference and a count; ValueError names the field."""
    if not isinstance(state, FacingState):
        raise ValueError(f"the facing check's state must be a FacingState, got "
                         f"{type(state).__name__}")
    try:
        reference = float(state.reference)
    except (TypeError, ValueError):
        raise ValueError(f"facing_check.reference must be a number (radians) or nan, got "
                         f"{state.reference!r}") from None
    if np.isinf(reference):
        raise ValueError(f"facing_check.reference must be finite or nan, got {reference}")
    return FacingState(reference, as_count(state.away_frames, "facing_check.away_frames"))


def half_turned(points, centre):
    """(..., N, 3) points turned half round about the vertical (+Y) through ``centre``
    (..., 3): x and z mirrored about it, which is a proper rotation (by pi)."""
    turned = np.array(points, dtype=np.float32)
    turned[..., 0] = 2 * centre[..., None, 0] - turned[..., 0]
    turned[..., 2] = 2 * centre[..., None, 2] - turned[..., 2]
    return turned


def check_facing(reading, points, reference, away_frames, skeleton, trigger=TRIGGER,
                 confirm=CONFIRM):
    """The facing check on one frame.

    Args:
        reading: (J, 3) float32 the skeleton found in ``points`` (e.g. SKR's), metres.
        points: (P, 3) float32 the frame's cloud, metres.
        reference: the heading the body is taken to face, radians (nan: none; the reading
            then stands).
        away_frames: the frames in a row before this one whose readings both faced away.
        skeleton: the skeleton finder, clouds (1, P, 3) -> joints (1, J, 3); called only when
            the reading faces further than ``trigger`` from ``reference``.
        trigger: radians; confirm: frames.
    Returns:
        the (J, 3) float32 skeleton to use (``reading`` or the second reading), and the
        reference and away_frames for the next frame.
    """
    reading = as_float32_array(reading, "reading", (NUM_JOINTS, 3))
    points = as_point_cloud(points, "points", MIN_POINTS)
    if np.isinf(reference) or away_frames < 0:
        raise ValueError(f"reference must be finite or nan and away_frames >= 0, got "
                         f"{reference!r} and {away_frames!r}")
    return _check_facing(reading, points, reference, away_frames, skeleton, trigger, confirm)


def _check_facing(reading, points, reference, away_frames, skeleton, trigger, confirm):
    """``check_facing`` on inputs already checked (the Retargeter's, every frame)."""
    first = float(heading_angles(reading))
    away = abs(wrapped(first - reference))
    if not away > trigger:                      # also nan: no reference yet
        return reading, first, 0
    centre = points.mean(axis=0, dtype=np.float64).astype(np.float32)
    second = half_turned(skeleton(half_turned(points, centre)[None])[0], centre)
    heading = float(heading_angles(second))
    second_away = abs(wrapped(heading - reference))
    if second_away <= trigger:
        return second, heading, 0
    nearer = second if second_away < away else reading
    if away_frames + 1 >= confirm:
        return nearer, first, 0
    return nearer, reference, away_frames + 1
