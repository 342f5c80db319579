"""Units and axes of user files, and the conversions to and from the canonical ones.

Canonical (``minretarget.conventions``): metres, +Y up, the T-pose body faces +Z with its left
hand at +X. A user's files may instead be in centimetres or millimetres, and Z-up:

    up axis "y": the canonical axes.
    up axis "z": +Z up, the body facing -Y, its left hand at +X (Blender, 3ds Max and most
        Z-up tools). Canonical = (x, z, -y) of the file, a rotation, so handedness is kept.

Inputs are converted to canonical on reading; outputs are converted back to the user's units
and axes on writing, except glTF, which the specification fixes to metres and +Y up.
"""
from typing import NamedTuple

import numpy as np

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}            # metres per file unit
# Rotation A taking file coordinates to canonical ones: canonical = A @ file.
UP_AXES = {"y": np.eye(3),
           "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])}


class Space(NamedTuple):
    """How a user's files measure lengths (``units``) and which way is up (``up_axis``)."""
    units: str = "m"
    up_axis: str = "y"

    @property
    def scale(self):
        """Metres per file unit."""
        return UNITS[self.units]

    @property
    def axes(self):
        """(3, 3) float64 rotation A with canonical = A @ file."""
        return UP_AXES[self.up_axis]


CANONICAL = Space()


def make_space(units="m", up_axis="y"):
    """A checked Space; ValueError names the bad value and the accepted ones."""
    if units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    if up_axis not in UP_AXES:
        raise ValueError(f"up axis must be one of {', '.join(UP_AXES)}, got {up_axis!r}")
    return Space(units, up_axis)


def to_canonical(points, space):
    """(..., 3) points in the file's units and axes -> (..., 3) float32 canonical metres."""
    points = np.asarray(points, dtype=np.float64)
    return ((points * space.scale) @ space.axes.T).astype(np.float32)


def from_canonical(points, space):
    """(..., 3) canonical points, metres -> (..., 3) float32 in the file's units and axes."""
    points = np.asarray(points, dtype=np.float64)
    return ((points @ space.axes) / space.scale).astype(np.float32)


def rotations_from_canonical(quaternions, space):
    """(..., 4) local quaternions (w, x, y, z) in canonical axes -> the same rotations in the
    file's axes: the matrix becomes ``A^T R A``, whose quaternion is (w, A^T v)."""
    q = np.asarray(quaternions, dtype=np.float64)
    return np.concatenate([q[..., :1], q[..., 1:] @ space.axes], axis=-1).astype(np.float32)


def rotations_to_canonical(quaternions, space):
    """The inverse of ``rotations_from_canonical``: (w, v) -> (w, A v)."""
    q = np.asarray(quaternions, dtype=np.float64)
    return np.concatenate([q[..., :1], q[..., 1:] @ space.axes.T], axis=-1).astype(np.float32)
