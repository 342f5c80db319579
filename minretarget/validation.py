"""Input checks shared by every public function: clear ValueErrors before any kernel runs."""
import numpy as np


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
    array = np.ascontiguousarray(array, dtype=np.float32)
    if finite and array.size and not np.isfinite(array).all():
        bad = np.argwhere(~np.isfinite(array))[0]
        raise ValueError(f"{name} has a non-finite value {array[tuple(bad)]} at index "
                         f"{tuple(int(i) for i in bad)}")
    return array


def as_point_cloud(value, name, min_points):
    """(P, 3) points -> float32 C-contiguous array, refusing clouds under ``min_points``."""
    points = as_float32_array(value, name, (None, 3))
    if points.shape[0] < min_points:
        raise ValueError(f"{name} has {points.shape[0]} points; at least {min_points} are needed")
    return points
