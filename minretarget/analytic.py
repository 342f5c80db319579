"""Analytic retargeting: rotate each target bone onto the matching source bone (no learning).

The baseline of the accuracy benchmark, and a fallback that needs no SMRM. For each joint, in
parent-before-child order, its world rotation is its parent's world rotation followed by the
smallest rotation that turns the parent-rotated T-pose bone (joint -> child) onto the source
bone. Joints with several children (pelvis: hips and spine; spine3: neck and collars) take the
rotation that best aligns all child directions at once (Kabsch). Leaf joints (feet, head,
wrists) have no bone to align and keep their parent's rotation. Twist about a bone is
therefore inherited from the parent, never invented.
"""
import numpy as np

from .conventions import NUM_JOINTS, PARENTS
from .kinematics import matrix_to_quaternion, quaternion_to_matrix
from .validation import as_float32_array

CHILDREN = tuple(tuple(c for c in range(NUM_JOINTS) if PARENTS[c] == j) for j in range(NUM_JOINTS))


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _rotation_between(a, b):
    """(N, 3) unit vectors a, b -> (N, 3, 3) the smallest rotations taking a to b."""
    cross = np.cross(a, b)
    dot = np.sum(a * b, axis=-1)
    # Opposite vectors: a half turn (w = 1 + dot = 0) about any axis perpendicular to a.
    opposite = dot < -1 + 1e-6
    if opposite.any():
        helper = np.where(np.abs(a[opposite, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        cross[opposite] = _unit(np.cross(a[opposite], helper))
    q = np.concatenate([(1 + dot)[:, None], cross], axis=-1)       # half-angle quaternion
    return quaternion_to_matrix(q).astype(np.float64)


def _best_rotation(a, b):
    """(N, K, 3) unit vectors a, b -> (N, 3, 3) proper rotations R minimising sum |R a - b|^2."""
    u, _, vt = np.linalg.svd(np.einsum("nki,nkj->nij", b, a))      # covariance b a^T
    d = np.sign(np.linalg.det(u @ vt))
    return u @ (np.eye(3) * np.stack([np.ones_like(d), np.ones_like(d), d], -1)[:, None, :]) @ vt


def analytic_rotations(source_joints, target_tpose):
    """Local joint rotations that pose the target skeleton like the source skeleton.

    Args:
        source_joints: (..., J, 3) float32 source joint positions, metres.
        target_tpose: (J, 3) float32 the target's T-pose joints, metres.
    Returns:
        (..., J, 4) float32 local quaternions (w, x, y, z) for forward kinematics on the target.
    """
    source = as_float32_array(source_joints, "source_joints", (..., NUM_JOINTS, 3))
    tpose = as_float32_array(target_tpose, "target_tpose", (NUM_JOINTS, 3)).astype(np.float64)
    batch = source.shape[:-2]
    source = source.reshape(-1, NUM_JOINTS, 3).astype(np.float64)   # (..., J, 3) -> (N, J, 3)
    n = source.shape[0]
    world = np.empty((n, NUM_JOINTS, 3, 3))
    for j in range(NUM_JOINTS):
        parent = world[:, PARENTS[j]] if j else np.broadcast_to(np.eye(3), (n, 3, 3))
        children = CHILDREN[j]
        if not children:
            world[:, j] = parent
            continue
        rest = _unit(np.einsum("nab,kb->nka", parent, tpose[list(children)] - tpose[j]))
        posed = _unit(source[:, list(children)] - source[:, j:j + 1])   # (N, K, 3)
        turn = (_rotation_between(rest[:, 0], posed[:, 0]) if len(children) == 1
                else _best_rotation(rest, posed))
        world[:, j] = turn @ parent
    parents = [0] + list(PARENTS[1:])
    local = np.einsum("njba,njbc->njac", world[:, parents], world)      # G_parent^T G_j
    local[:, 0] = world[:, 0]
    return matrix_to_quaternion(local).reshape(batch + (NUM_JOINTS, 4))
