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
def _unit3(v):
    return v / max(np.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2), 1e-12)


@kernel
def _analytic_frame(source, tpose, out, world):
    """One frame: source (J, 3), tpose (J, 3) -> out (J, 4) local quaternions; ``world``
    (J, 3, 3) float64 is scratch space for the world rotations."""
    turn, quaternion = np.empty((3, 3)), np.empty(4)
    for j in range(source.shape[0]):
        parent = np.eye(3) if j == 0 else world[_PARENTS[j]]
        count = 0
        cross_covariance = np.zeros((3, 3))     # sum over children of rest posed^T
        for k in range(_CHILD_TABLE.shape[1]):
            c = _CHILD_TABLE[j, k]
            if c < 0:
                break
            count += 1
            bone = (tpose[c] - tpose[j]).astype(np.float64)
            rest = _unit3(parent @ bone)
            posed = _unit3((source[c] - source[j]).astype(np.float64))
            for a in range(3):
                for b in range(3):
                    cross_covariance[a, b] += rest[a] * posed[b]
        if count == 0:                          # a leaf keeps its parent's rotation
            world[j] = parent
        elif count == 1:                        # the smallest turn rest -> posed
            cross = np.cross(rest, posed)
            dot = rest @ posed
            w = 1.0 + dot
            if dot < -1 + 1e-6:                 # opposite: a half turn about a perpendicular
                helper = np.array([1.0, 0, 0]) if abs(rest[0]) < 0.9 else np.array([0, 1.0, 0])
                cross, w = _unit3(np.cross(rest, helper)), 0.0
            quaternion[0], quaternion[1:] = w, cross
        else:                                   # Kabsch: the best-aligning rotation
            _horn_quaternion(cross_covariance, count, quaternion)
        if count:
            _quaternion_to_matrix_one(quaternion, turn)
            world[j] = turn @ parent
        local = world[j] if j == 0 else world[_PARENTS[j]].T @ world[j]
        _matrix_to_quaternion_one(np.ascontiguousarray(local), quaternion)
        out[j] = quaternion


@kernel
def _horn_quaternion(s, count, q):
    """The rotation (quaternion q (4,)) maximising sum_k posed_k . R rest_k, from
    s = sum_k rest_k posed_k^T (3, 3) over ``count`` unit pairs (Horn 1987): the top
    eigenvector of Horn's symmetric 4 x 4 matrix N. N's eigenvalues lie in [-count, count], so
    N + count I is positive semi-definite and its repeated square tends to l1 q q^T."""
    n = np.array([
        [s[0, 0] + s[1, 1] + s[2, 2], s[1, 2] - s[2, 1], s[2, 0] - s[0, 2], s[0, 1] - s[1, 0]],
        [s[1, 2] - s[2, 1], s[0, 0] - s[1, 1] - s[2, 2], s[0, 1] + s[1, 0], s[2, 0] + s[0, 2]],
        [s[2, 0] - s[0, 2], s[0, 1] + s[1, 0], s[1, 1] - s[0, 0] - s[2, 2], s[1, 2] + s[2, 1]],
        [s[0, 1] - s[1, 0], s[2, 0] + s[0, 2], s[1, 2] + s[2, 1], s[2, 2] - s[0, 0] - s[1, 1]]])
    power = n + count * np.eye(4)
    for _ in range(SQUARINGS):
        power = power @ power
        power /= np.trace(power)
    best = np.argmax(np.diag(power))            # the best-conditioned column of l1 q q^T
    q[:] = power[:, best] / np.sqrt(np.sum(power[:, best] ** 2))
