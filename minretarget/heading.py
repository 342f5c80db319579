"""The body-aligned frame SMRM and the skeleton denoiser see a skeleton in.

The heading is the turn about +Y from +Z to the way the body faces; turned by minus the
heading, a skeleton faces +Z whichever way it walks, so the networks need not learn every
direction.
"""
import numpy as np

from ._jit import kernel
from .conventions import JOINT_INDEX

# The joints whose left-right axis says which way the body faces.
_LEFT_HIP, _RIGHT_HIP, _LEFT_SHOULDER, _RIGHT_SHOULDER = (
    JOINT_INDEX[name] for name in ("left_hip", "right_hip", "left_shoulder", "right_shoulder"))


@kernel
def turn_about_up(x, y, z, sin, cos):
    """Rotate the vector (x, y, z) about +Y by the angle with this sine and cosine."""
    return cos * x + sin * z, y, cos * z - sin * x


@kernel
def heading_features(joints, previous_root):
    """The body-aligned view SMRM and the denoiser take of a (J, 3) skeleton.

    Heading: the turn about +Y from +Z to the way the body faces (facing = across x up,
    across = left hip - right hip + left shoulder - right shoulder). Returns its sine and
    cosine and the features (1, J*3 + 3): joints - root, then root - previous_root, both
    turned by minus the heading."""
    j = joints.shape[0]
    # scalars, not array expressions: numba compiles those slowly (issue 40)
    across_x = (joints[_LEFT_HIP, 0] - joints[_RIGHT_HIP, 0]
                + joints[_LEFT_SHOULDER, 0] - joints[_RIGHT_SHOULDER, 0])
    across_z = (joints[_LEFT_HIP, 2] - joints[_RIGHT_HIP, 2]
                + joints[_LEFT_SHOULDER, 2] - joints[_RIGHT_SHOULDER, 2])
    norm = max(np.sqrt(across_x ** 2 + across_z ** 2), np.float32(1e-8))
    sin, cos = -across_z / norm, across_x / norm
    features = np.empty((1, 3 * j + 3), dtype=np.float32)
    for k in range(j + 1):
        if k < j:
            x, y, z = (joints[k, 0] - joints[0, 0], joints[k, 1] - joints[0, 1],
                       joints[k, 2] - joints[0, 2])
        else:
            x, y, z = (joints[0, 0] - previous_root[0], joints[0, 1] - previous_root[1],
                       joints[0, 2] - previous_root[2])
        features[0, 3 * k], features[0, 3 * k + 1], features[0, 3 * k + 2] = turn_about_up(
            x, y, z, -sin, cos)
    return features, sin, cos


def heading_angles(joints):
    """The heading of ``heading_features`` as an angle: (..., J, 3) skeletons -> (...,)
    float64 radians in (-pi, pi], the turn about +Y from +Z to the way each body faces."""
    joints = np.asarray(joints, dtype=np.float64)
    across = (joints[..., _LEFT_HIP, :] - joints[..., _RIGHT_HIP, :]
              + joints[..., _LEFT_SHOULDER, :] - joints[..., _RIGHT_SHOULDER, :])
    return np.arctan2(-across[..., 2], across[..., 0])


def wrapped(angles):
    """Angles (radians) into [-pi, pi)."""
    return (np.asarray(angles) + np.pi) % (2 * np.pi) - np.pi
