"""Input checks shared by every public entry.

Errors: clear ValueErrors for bad shapes, dtypes and values, before any kernel runs.
Warnings (``InputWarning`` subclasses): valid input that is probably a mistake (units, up
axis, pose), each with the way out. The command line prints them as ``minretarget: warning:``.
"""
import warnings

import numpy as np

from .units import CANONICAL, UNITS, make_space


def as_float32_array(value, name, shape, finite=True):
    """Check ``value`` against a shape pattern and return it as a C-contiguous float32 array.

    Args:
        value: anything ``np.asarray`` accepts, of a real numeric dtype.
        name: the argument's name, for the error message.
        shape: a tuple of ints (exact size), None (any size) and at most one leading
            Ellipsis (any number of leading dimensions), e.g. ``(..., 22, 4)`` or ``(None, 3)``.
        finite: also refuse NaN and inf.
    Raises:
        ValueError naming the argument, the expected and the actual shape, dtype or bad value.
    """
    array = np.asarray(value)
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f"{name} must be a real numeric array, got dtype {array.dtype}")
    fixed = shape[1:] if shape and shape[0] is Ellipsis else shape
    leading_any = len(fixed) != len(shape)
    if (array.ndim < len(fixed) if leading_any else array.ndim != len(fixed)) or any(
            want is not None and got != want
            for want, got in zip(fixed, array.shape[array.ndim - len(fixed):])):
        pattern = ", ".join("..." if s is Ellipsis else "any" if s is None else str(s)
                            for s in shape)
        raise ValueError(f"{name} must have shape ({pattern}), got {array.shape}")
    given = array
    with np.errstate(over="ignore"):    # a value past float32's range is refused below, named
        array = np.ascontiguousarray(given, dtype=np.float32)
    if finite and array.size and not np.isfinite(array).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
        what = "non-finite value" if not np.isfinite(given[bad]) else "value past float32's range"
        raise ValueError(f"{name} has a {what} {given[bad]} at index {bad}")
    return array


# Metres from the origin past which float32 cannot place a body's points to about a
# millimetre (its spacing there is 1 mm; SKR's joints move 5 mm at 9 km).
MAX_COORDINATE = 1e4


def as_count(value, name):
    """``value`` as an int >= 0 (a count kept in a stream's state), or ValueError naming it."""
    try:
        count = int(value)
    except (TypeError, ValueError, OverflowError):                  # None, "x", inf
        count = -1
    if count < 0 or count != value:
        raise ValueError(f"{name} must be a count (an integer >= 0), got {value!r}")
    return count


def as_point_cloud(value, name, min_points):
    """(P, 3) points, metres -> float32 C-contiguous array, refusing clouds under
    ``min_points`` and coordinates beyond ``MAX_COORDINATE``."""
    points = as_float32_array(value, name, (None, 3))
    if points.shape[0] < min_points:
        raise ValueError(f"{name} has {points.shape[0]} points; at least {min_points} are needed")
    far = np.abs(points) > MAX_COORDINATE
    if far.any():
        bad = tuple(int(i) for i in np.argwhere(far)[0])
        raise ValueError(f"{name} has a coordinate {points[bad]:.6g} at index {bad}, over "
                         f"{MAX_COORDINATE:g} m from the origin, where float32 cannot hold a "
                         "body to a millimetre: move the cloud near the origin (or check its "
                         "units)")
    return points


def as_workers(value):
    """A thread count: a positive int (bools and floats refused); ValueError otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"workers must be a positive integer, got {value!r}")
    return int(value)


# ----------------------------------------------------------------------------- likely mistakes

class InputWarning(UserWarning):
    """Input that is valid but probably not what the user meant; the message says why and
    what to do. Subclasses say which mistake."""


class UnitsWarning(InputWarning):
    """The body's size is not a person's in metres: the file is probably in cm or mm."""


class UpAxisWarning(InputWarning):
    """The body lies along Z instead of standing along +Y: the file is probably Z-up."""


class FitWarning(InputWarning):
    """The source fit found no body in a cloud (it lost the body, or the cloud is not one)."""


class TPoseWarning(InputWarning):
    """The target's arms are far from horizontal: it is probably not in T-pose."""


HUMAN_HEIGHT = (0.3, 3.0)    # metres: a toddler to a giant; outside it, suspect the units
# (the ranges of metres, centimetres and millimetres do not overlap, so the units of a file
# can be told from its body's size: ``guess_space``)
LYING_RATIO = 2.0            # Z extent over Y extent above which the body lies along Z
# Arm span over height: about 1 in a T-pose, 0.77 with the arms 45 degrees down, 0.35 along
# the body (shoulders 0.2 and arms 0.4 of the height).
TPOSE_MIN_SPAN = 0.8
UNIT_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}


def guess_space(points, units=None, up_axis=None):
    """The units and up axis a file's body is most likely in.

    Args:
        points: (N, 3) points or joints of one body as in the file (its units and axes).
        units, up_axis: the file's, if known (kept as given), else None to guess: the up
            axis is Z if the body is longer along Z than along Y, else Y; the units are those
            in which its largest extent is a person's (``HUMAN_HEIGHT``), or metres if none
            is (``body_problems`` then says so).
    Returns:
        ``units.Space``.
    """
    extent = np.ptp(np.asarray(points, dtype=np.float64), axis=0)           # (3,) x, y, z
    up_axis = up_axis or ("z" if extent[2] > extent[1] else "y")
    if units is None:
        low, high = HUMAN_HEIGHT
        units = next((u for u, scale in UNITS.items() if low <= extent.max() * scale <= high),
                     "m")
    return make_space(units, up_axis)


def body_problems(points, name, space=CANONICAL, tpose=False, role=None):
    """What about a body suggests wrong units, up axis or pose (``check_body``).

    Args:
        points: (N, 3) canonical points or joints of one body (metres, +Y up), finite.
        name: what they are, for the message, e.g. "target.ply" or "scans/: frame 0".
        space: the ``units.Space`` the file was read with, so the advice names the option
            to change (the Python API passes canonical data: the default).
        tpose: also check that the arms are roughly horizontal (targets only).
        role: "source" or "target": the advice names ``--source-units`` ... rather than
            ``--units`` and ``--up-axis``.
    Returns:
        [(category, message)]: UnitsWarning, UpAxisWarning, TPoseWarning, each at most once.
    """
    units_option, up_option = (f"--{role}-units", f"--{role}-up") if role else (
        "--units", "--up-axis")
    extent = np.ptp(np.asarray(points, dtype=np.float64), axis=0)          # (3,) x, y, z
    height = float(extent.max())
    low, high = HUMAN_HEIGHT
    problems = []
    if not low <= height <= high:
        in_file = height / space.scale
        guesses = [u for u, scale in UNITS.items() if u != space.units
                   and low <= in_file * scale <= high]
        advice = (f"looks like {UNIT_NAMES[guesses[0]]} (use {units_option} {guesses[0]}, or "
                  "scale the points to metres)" if guesses else "check its units")
        size = f"{height:.4g} m" + (f" ({in_file:.4g} {space.units})" if space.units != "m"
                                    else "")
        problems.append((UnitsWarning, f"{name}: the body is {size} tall (its largest "
                         f"extent), not a person's {low:g} to {high:g} m: {advice}"))
    if extent[2] > LYING_RATIO * extent[1]:
        other = "z" if space.up_axis == "y" else "y"
        problems.append((UpAxisWarning, f"{name}: the body lies along Z ({extent[2]:.4g} m "
                         f"along Z, {extent[1]:.4g} m along Y, up axis "
                         f"{space.up_axis.upper()}): its up axis looks like {other.upper()} "
                         f"(use {up_option} {other})"))
    elif tpose and extent[0] < TPOSE_MIN_SPAN * extent[1]:
        problems.append((TPoseWarning, f"{name}: the arms look far from horizontal: the body "
                         f"is {extent[0]:.4g} m wide (X) for {extent[1]:.4g} m tall (Y), a "
                         f"ratio of {extent[0] / extent[1]:.2f} where a T-pose has about 1: "
                         "the target should be in T-pose (arms horizontal, facing +Z, left "
                         "hand toward +X)"))
    return problems


def check_body(points, name, space=CANONICAL, tpose=False, role=None):
    """Warn about a body whose size or orientation suggests wrong units, up axis or pose:
    each of ``body_problems(points, name, space, tpose, role)``."""
    for category, message in body_problems(points, name, space, tpose, role):
        warnings.warn(message, category, stacklevel=3)
