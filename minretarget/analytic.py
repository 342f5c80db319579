"""Analytic retargeting: rotate each target bone onto the matching source bone (no learning).

The baseline of the accuracy benchmark, and SMRM's prior when its weights have
``smrm_analytic_prior`` (SMRM then predicts corrections to these rotations). For each joint,
in parent-before-child order, its world rotation is its parent's world rotation followed by the
smallest rotation that turns the parent-rotated T-pose bone (joint -> child) onto the source
bone. Joints with several children (pelvis: hips and spine; spine3: neck and collars) take the
rotation that best aligns all child directions at once (Kabsch's, found as Horn's quaternion:
the top eigenvector of a 4 x 4 matrix, by repeated squaring, which is plain arithmetic the
torch reference can differentiate and export to ONNX). Leaf joints (feet, head, wrists) have
no bone to align and keep their parent's rotation. Twist about a bone is therefore inherited
from the parent, never invented.
"""
import numpy as np

from ._jit import kernel
from .conventions import NUM_JOINTS, PARENTS
from .kinematics import _matrix_to_quaternion_one, _quaternion_to_matrix_one
from .validation import as_float32_array

CHILDREN = tuple(tuple(c for c in range(NUM_JOINTS) if PARENTS[c] == j) for j in range(NUM_JOINTS))
MAX_CHILDREN = max(len(c) for c in CHILDREN)
# The same as arrays for the kernels: row j lists j's children, padded with -1.
_CHILD_TABLE = np.array([list(c) + [-1] * (MAX_CHILDREN - len(c)) for c in CHILDREN])
_PARENTS = np.asarray(PARENTS, dtype=np.int64)
# Squarings of Horn's shifted matrix: its top eigenvector dominates as (l2 / l1)^(2^16);
# 12 already match an SVD to 1e-7 on random near-coplanar bones with heavy noise.
SQUARINGS = 16


def analytic_rotations(source_joints, target_tpose):
    """Local joint rotations that pose the target skeleton like the source skeleton.

    Args:
        source_joints: (..., J, 3) float32 source joint positions, metres.
        target_tpose: (J, 3) float32 the target's T-pose joints, metres.
    Returns:
        (..., J, 4) float32 local quaternions (w, x, y, z) for forward kinematics on the target.
    """
    source = as_float32_array(source_joints, "source_joints", (..., NUM_JOINTS, 3))
    tpose = as_float32_array(target_tpose, "target_tpose", (NUM_JOINTS, 3))
    flat = np.ascontiguousarray(source.reshape(-1, NUM_JOINTS, 3))    # (..., J, 3) -> (N, J, 3)
    out = np.empty((flat.shape[0], NUM_JOINTS, 4), dtype=np.float32)
    world = np.empty((NUM_JOINTS, 3, 3))
    for n in range(flat.shape[0]):
        _analytic_frame(flat[n], tpose, out[n], world)
    return out.reshape(source.shape[:-1] + (4,))


@kernel
def _analytic_frame(source, tpose, out, world):
    """One frame: source (J, 3), tpose (J, 3) -> out (J, 4) local quaternions; ``world``
    (J, 3, 3) float64 is scratch space for the world rotations. Scalar loops throughout: no
    BLAS products, array temporaries or slice assignments, which cost numba seconds to compile
    (issue 40) and a 3 x 3 product nothing at run time."""
    parent, turn, local = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    covariance, quaternion = np.empty((3, 3)), np.empty(4)
    rest, posed = np.empty(3), np.empty(3)
    for j in range(source.shape[0]):
        for a in range(3):
            for b in range(3):
                parent[a, b] = (1.0 if a == b else 0.0) if j == 0 else world[_PARENTS[j], a, b]
                covariance[a, b] = 0.0          # sum over children of rest posed^T
        count = 0
        for k in range(_CHILD_TABLE.shape[1]):
            c = _CHILD_TABLE[j, k]
            if c < 0:
                break
            count += 1
            for a in range(3):
                rest[a] = 0.0
                posed[a] = np.float64(source[c, a] - source[j, a])
            for b in range(3):
                bone = np.float64(tpose[c, b] - tpose[j, b])
                for a in range(3):
                    rest[a] += parent[a, b] * bone
            _normalise3(rest)
            _normalise3(posed)
            for a in range(3):
                for b in range(3):
                    covariance[a, b] += rest[a] * posed[b]
        if count == 1:                          # the smallest turn rest -> posed
            dot = rest[0] * posed[0] + rest[1] * posed[1] + rest[2] * posed[2]
            if dot < -1 + 1e-6:                 # opposite: a half turn about a perpendicular
                h0, h1 = (1.0, 0.0) if abs(rest[0]) < 0.9 else (0.0, 1.0)
                posed[0] = -rest[2] * h1        # rest x (h0, h1, 0), made unit
                posed[1] = rest[2] * h0
                posed[2] = rest[0] * h1 - rest[1] * h0
                _normalise3(posed)
                quaternion[0] = 0.0
                for a in range(3):
                    quaternion[1 + a] = posed[a]
            else:
                quaternion[0] = 1.0 + dot
                quaternion[1] = rest[1] * posed[2] - rest[2] * posed[1]
                quaternion[2] = rest[2] * posed[0] - rest[0] * posed[2]
                quaternion[3] = rest[0] * posed[1] - rest[1] * posed[0]
        elif count > 1:                         # Kabsch: the best-aligning rotation
            _horn_quaternion(covariance, float(count), quaternion)
        if count:
            _quaternion_to_matrix_one(quaternion, turn)
        for a in range(3):                      # world = turn parent; a leaf keeps its parent's
            for b in range(3):
                if count:
                    total = 0.0
                    for c in range(3):
                        total += turn[a, c] * parent[c, b]
                    world[j, a, b] = total
                else:
                    world[j, a, b] = parent[a, b]
        for a in range(3):                      # local = parent's world^T world
            for b in range(3):
                if j == 0:
                    local[a, b] = world[0, a, b]
                else:
                    total = 0.0
                    for c in range(3):
                        total += world[_PARENTS[j], c, a] * world[j, c, b]
                    local[a, b] = total
        _matrix_to_quaternion_one(local, quaternion)
        for a in range(4):
            out[j, a] = quaternion[a]


@kernel
def _normalise3(v):
    """A 3-vector to unit length in place (a zero one stays zero)."""
    norm = max(np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), 1e-12)
    for a in range(3):
        v[a] = v[a] / norm


@kernel
def _horn_quaternion(s, count, q):
    """The rotation (quaternion q (4,)) maximising sum_k posed_k . R rest_k, from
    s = sum_k rest_k posed_k^T (3, 3) over ``count`` unit pairs (Horn 1987): the top
    eigenvector of Horn's symmetric 4 x 4 matrix N. N's eigenvalues lie in [-count, count], so
    N + count I is positive semi-definite and its repeated square tends to l1 q q^T."""
    power, square = np.empty((4, 4)), np.empty((4, 4))
    power[0, 0] = s[0, 0] + s[1, 1] + s[2, 2]
    power[1, 1] = s[0, 0] - s[1, 1] - s[2, 2]
    power[2, 2] = s[1, 1] - s[0, 0] - s[2, 2]
    power[3, 3] = s[2, 2] - s[0, 0] - s[1, 1]
    power[0, 1] = power[1, 0] = s[1, 2] - s[2, 1]
    power[0, 2] = power[2, 0] = s[2, 0] - s[0, 2]
    power[0, 3] = power[3, 0] = s[0, 1] - s[1, 0]
    power[1, 2] = power[2, 1] = s[0, 1] + s[1, 0]
    power[1, 3] = power[3, 1] = s[2, 0] + s[0, 2]
    power[2, 3] = power[3, 2] = s[1, 2] + s[2, 1]
    for a in range(4):
        power[a, a] += count
    for _ in range(SQUARINGS):
        trace = 0.0
        for a in range(4):
            for b in range(4):
                total = 0.0
                for c in range(4):
                    total += power[a, c] * power[c, b]
                square[a, b] = total
            trace += square[a, a]
        for a in range(4):
            for b in range(4):
                power[a, b] = square[a, b] / trace
    best = 0                                    # the best-conditioned column of l1 q q^T
    for a in range(1, 4):
        if power[a, a] > power[best, best]:
            best = a
    norm = np.sqrt(power[0, best] ** 2 + power[1, best] ** 2 + power[2, best] ** 2
                   + power[3, best] ** 2)
    for a in range(4):
        q[a] = power[a, best] / norm
