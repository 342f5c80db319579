"""Rotations and forward kinematics (FK) on the 22-joint skeleton.

Conventions (see ``minretarget.conventions``): quaternions are (w, x, y, z); a joint's rotation
is local to its parent in the T-pose's world-aligned frames; lengths are metres. Every public
function takes any number of leading batch dimensions ``...``.
"""
import numpy as np

from ._jit import kernel
from .conventions import NUM_JOINTS, PARENTS
from .validation import as_float32_array

_PARENTS = np.asarray(PARENTS, dtype=np.int64)


# ----------------------------------------------------------------------------- quaternions

def quaternion_to_matrix(quaternions):
    """(..., 4) quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices.

    The quaternions need not be unit: the result is the rotation of q / |q|, for norms in
    [1e-15, 1e15] (``check_quaternion_norms``).
    """
    q = as_float32_array(quaternions, "quaternions", (..., 4))
    check_quaternion_norms(q, "quaternions")
    flat = np.ascontiguousarray(q.reshape(-1, 4))                   # (..., 4) -> (N, 4)
    out = np.empty((flat.shape[0], 3, 3), dtype=np.float32)
    _quaternion_to_matrix_kernel(flat, out)
    return out.reshape(q.shape[:-1] + (3, 3))


@kernel
def _quaternion_to_matrix_kernel(q, out):
    for n in range(q.shape[0]):
        _quaternion_to_matrix_one(q[n], out[n])


@kernel
def _quaternion_to_matrix_one(q, r):
    w, x, y, z = q[0], q[1], q[2], q[3]
    s = np.float32(2.0) / (w * w + x * x + y * y + z * z)   # 2 / |q|^2 normalises on the fly
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    r[0, 0] = 1 - yy - zz
    r[0, 1] = xy - wz
    r[0, 2] = xz + wy
    r[1, 0] = xy + wz
    r[1, 1] = 1 - xx - zz
    r[1, 2] = yz - wx
    r[2, 0] = xz - wy
    r[2, 1] = yz + wx
    r[2, 2] = 1 - xx - yy


def check_quaternion_norms(q, name):
    """ValueError unless every (..., 4) quaternion's norm is in [1e-15, 1e15]: a zero one
    is no rotation, and beyond that range 2 / |q|^2 under- or overflows in float32."""
    norms = np.sqrt(np.sum(np.square(q, dtype=np.float64), axis=-1))          # (...,)
    bad = ~((norms >= 1e-15) & (norms <= 1e15))
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{name} has a quaternion of norm {norms[index]:g} at index {index}; "
                         "rotations need a norm in [1e-15, 1e15]")


def matrix_to_quaternion(matrices):
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    Uses the largest of the four squared components to pick a numerically stable branch;
    computed in float64.
    """
    m = np.asarray(matrices, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"matrices must have shape (..., 3, 3), got {m.shape}")
    flat = np.ascontiguousarray(m.reshape(-1, 3, 3))                # (..., 3, 3) -> (N, 3, 3)
    out = np.empty((flat.shape[0], 4))
    _matrix_to_quaternion_kernel(flat, out)
    return out.reshape(m.shape[:-2] + (4,)).astype(np.float32)


@kernel
def _matrix_to_quaternion_kernel(m, out):
    for n in range(m.shape[0]):
        _matrix_to_quaternion_one(m[n], out[n])


@kernel
def _matrix_to_quaternion_one(m, q):
    """One (3, 3) rotation -> q (4,), unit with w >= 0: the branch of the largest of 4 w^2,
    4 x^2, 4 y^2, 4 z^2 (each from the diagonal), the rest from the off-diagonal terms."""
    squares = (1 + m[0, 0] + m[1, 1] + m[2, 2], 1 + m[0, 0] - m[1, 1] - m[2, 2],
               1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2])
    best = 0
    for k in range(1, 4):
        if squares[k] > squares[best]:
            best = k
    if best == 0:
        q[0], q[1], q[2], q[3] = (squares[0], m[2, 1] - m[1, 2], m[0, 2] - m[2, 0],
                                  m[1, 0] - m[0, 1])
    elif best == 1:
        q[0], q[1], q[2], q[3] = (m[2, 1] - m[1, 2], squares[1], m[1, 0] + m[0, 1],
                                  m[0, 2] + m[2, 0])
    elif best == 2:
        q[0], q[1], q[2], q[3] = (m[0, 2] - m[2, 0], m[1, 0] + m[0, 1], squares[2],
                                  m[2, 1] + m[1, 2])
    else:
        q[0], q[1], q[2], q[3] = (m[1, 0] - m[0, 1], m[0, 2] + m[2, 0], m[2, 1] + m[1, 2],
                                  squares[3])
    norm = np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    sign = -1.0 if q[0] < 0 else 1.0
    for k in range(4):
        q[k] = sign * q[k] / norm


@kernel
def _quaternion_multiply_one(a, b, out):
    """``quaternion_multiply`` of two (4,) quaternions into out (4,), in a kernel."""
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]


def quaternion_multiply(a, b):
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z): rotate by b, then by a."""
    a = np.asarray(a, dtype=np.float32)
    b = np.asarray(b, dtype=np.float32)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quaternion_slerp(q0, q1, weight):
    """(..., 4) quaternions, (...) weights in [0, 1] -> (..., 4) float64 shortest-path slerp."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    weight = np.asarray(weight, dtype=np.float64)
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)             # q and -q are the same rotation
    angle = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    sin = np.sin(angle)
    small = sin < 1e-6                                     # nearly equal: lerp is exact enough
    safe = np.where(small, 1.0, sin)
    w0 = np.where(small, 1 - weight, np.sin((1 - weight) * angle) / safe)
    w1 = np.where(small, weight, np.sin(weight * angle) / safe)
    q = w0[..., None] * q0 + w1[..., None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- forward kinematics

def forward_kinematics(rotations, root, tpose_joints):
    """Pose a skeleton.

    Args:
        rotations: (..., J, 4) float32 local joint quaternions (w, x, y, z).
        root: (..., 3) float32 world position of the pelvis, metres.
        tpose_joints: (J, 3) or (..., J, 3) float32 T-pose joint positions, metres.
    Returns:
        joints: (..., J, 3) float32 posed joint positions, metres.
        global_rotations: (..., J, 3, 3) float32 joint rotations in world coordinates.
    """
    rotations = as_float32_array(rotations, "rotations", (..., NUM_JOINTS, 4))
    check_quaternion_norms(rotations, "rotations")
    batch = rotations.shape[:-2]
    root = as_float32_array(root, "root", batch + (3,))
    tpose_joints = as_float32_array(tpose_joints, "tpose_joints", (..., NUM_JOINTS, 3))
    try:
        tpose = np.broadcast_to(tpose_joints, batch + (NUM_JOINTS, 3))
    except ValueError:
        raise ValueError(f"tpose_joints of shape {tpose_joints.shape} does not broadcast to "
                         f"the rotations' batch shape {batch}") from None
    # Writable, as every other caller's: numba compiles a kernel again for a read-only array.
    tpose = np.require(tpose, requirements="W")
    n = int(np.prod(batch, dtype=np.int64))
    joints = np.empty((n, NUM_JOINTS, 3), dtype=np.float32)
    global_rotations = np.empty((n, NUM_JOINTS, 3, 3), dtype=np.float32)
    _forward_kinematics_kernel(
        np.ascontiguousarray(rotations.reshape(n, NUM_JOINTS, 4)),     # (..., J, 4) -> (N, J, 4)
        np.ascontiguousarray(root.reshape(n, 3)),
        np.ascontiguousarray(tpose.reshape(n, NUM_JOINTS, 3)),
        _PARENTS, joints, global_rotations)
    return (joints.reshape(batch + (NUM_JOINTS, 3)),
            global_rotations.reshape(batch + (NUM_JOINTS, 3, 3)))


@kernel
def _forward_kinematics_kernel(rotations, root, tpose, parents, joints, global_rotations):
    local = np.empty((3, 3), dtype=np.float32)
    for n in range(rotations.shape[0]):
        _quaternion_to_matrix_one(rotations[n, 0], global_rotations[n, 0])
        for a in range(3):
            joints[n, 0, a] = root[n, a]
        for j in range(1, rotations.shape[1]):
            _place_joint(rotations[n], tpose[n], parents, joints[n], global_rotations[n], j,
                         local)


@kernel
def _place_joint(rotations, tpose, parents, joints, global_rotations, j, local):
    """One pose's joint j > 0 from its parent's, in place: its position in ``joints`` (J, 3)
    and its world rotation in ``global_rotations`` (J, 3, 3); ``local`` (3, 3) is scratch.
    A stage that changes a chain's rotations (the foot lock) places that chain again."""
    p = parents[j]
    _quaternion_to_matrix_one(rotations[j], local)
    parent_rotation = global_rotations[p]
    for a in range(3):
        # Bone offset from the T-pose, rotated by the parent's global rotation.
        offset = np.float32(0.0)
        for b in range(3):
            offset += parent_rotation[a, b] * (tpose[j, b] - tpose[p, b])
            acc = np.float32(0.0)
            for c in range(3):
                acc += parent_rotation[a, c] * local[c, b]
            global_rotations[j, a, b] = acc
        joints[j, a] = joints[p, a] + offset


def skinning_transforms(joints, global_rotations, tpose_joints):
    """Per-joint affine maps from T-pose space to posed space, as used by linear blend skinning.

    Args:
        joints: (..., J, 3) posed joint positions, metres.
        global_rotations: (..., J, 3, 3) world rotations of the joints.
        tpose_joints: (..., J, 3) T-pose joint positions, metres.
    Returns:
        (..., J, 3, 4) float32: ``[G | p - G t]``, so a T-pose point x maps to ``G x + p - G t``.
    """
    translation = joints - np.einsum("...ab,...b->...a", global_rotations, tpose_joints)
    return np.concatenate([global_rotations, translation[..., None]], axis=-1).astype(np.float32)


def leg_length(joints):
    """(..., J, 3) joints -> (...,) mean length of the two hip-knee-ankle chains, metres.

    Bone lengths do not change with pose, so this measures a body's scale from any frame.
    """
    joints = np.asarray(joints, dtype=np.float32)
    total = 0.0
    for hip, knee, ankle in ((1, 4, 7), (2, 5, 8)):
        total = total + np.linalg.norm(joints[..., knee, :] - joints[..., hip, :], axis=-1)
        total = total + np.linalg.norm(joints[..., ankle, :] - joints[..., knee, :], axis=-1)
    return (total / 2).astype(np.float32)
