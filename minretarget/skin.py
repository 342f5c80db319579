"""Stage 3, SKIN: the skinning-weight field and linear blend skinning (LBS).

Skinning weights are computed once per target: per point, the MLP reads its offsets to the J
T-pose joints (J*3, metres) and a softmax turns J logits into weights that are >= 0 and sum
to one. Each frame, LBS blends the joints' affine maps (``kinematics.skinning_transforms``)
with those weights and applies the blend to the T-pose point.
"""
import numpy as np

from ._jit import kernel
from .conventions import NUM_JOINTS
from .nn import mlp
from .validation import as_float32_array


def skinning_weights(points, tpose_joints, weights, chunk=4096):
    """Skinning weights of target points.

    Args:
        points: (V, 3) float32 target points in T-pose, metres.
        tpose_joints: (J, 3) float32 the target's T-pose joints, metres.
        weights: MLP weights of the skinning field.
        chunk: points per kernel call, bounding the (chunk, width) activations in memory.
    Returns:
        (V, J) float32 weights, each row >= 0 and summing to 1.
    """
    points = as_float32_array(points, "points", (None, 3))
    tpose_joints = as_float32_array(tpose_joints, "tpose_joints", (NUM_JOINTS, 3))
    out = np.empty((points.shape[0], NUM_JOINTS), dtype=np.float32)
    for start in range(0, points.shape[0], chunk):
        out[start:start + chunk] = _skinning_weights_kernel(
            points[start:start + chunk], tpose_joints, weights)
    return out


@kernel
def _skinning_weights_kernel(points, tpose_joints, weights):
    v, j = points.shape[0], tpose_joints.shape[0]
    offsets = np.empty((v, j * 3), dtype=np.float32)
    for i in range(v):
        for k in range(j):
            for a in range(3):
                offsets[i, 3 * k + a] = points[i, a] - tpose_joints[k, a]
    logits = mlp(offsets, weights)                                       # (V, J)
    for i in range(v):   # softmax, shifted by the row maximum so exp cannot overflow
        shift = logits[i, 0]
        for k in range(1, j):
            shift = max(shift, logits[i, k])
        total = np.float32(0.0)
        for k in range(j):
            logits[i, k] = np.exp(logits[i, k] - shift)
            total += logits[i, k]
        for k in range(j):      # scalars: a slice assignment costs numba seconds to compile
            logits[i, k] /= total
    return logits


def linear_blend_skinning(points, skin_weights, transforms, chunk=32):
    """Pose T-pose points with per-joint affine maps, for one frame or many.

    Args:
        points: (V, 3) float32 T-pose points, metres.
        skin_weights: (V, J) float32 skinning weights.
        transforms: (J, 3, 4) or (T, J, 3, 4) float32 T-pose -> posed maps
            (``kinematics.skinning_transforms``).
        chunk: frames per kernel call, bounding its (V, chunk * 12) blend in memory.
    Returns:
        (V, 3) or (T, V, 3) float32 posed points, metres; row i stays point i.
    """
    points = as_float32_array(points, "points", (None, 3))
    skin_weights = as_float32_array(skin_weights, "skin_weights", (points.shape[0], None))
    transforms = as_float32_array(transforms, "transforms", (..., skin_weights.shape[1], 3, 4))
    if transforms.ndim not in (3, 4):
        raise ValueError(f"transforms must have shape (J, 3, 4) or (T, J, 3, 4), got "
                         f"{transforms.shape}")
    frames = transforms.reshape(-1, skin_weights.shape[1], 12)          # (T, J, 12)
    out = np.empty((len(frames),) + points.shape, dtype=np.float32)
    for start in range(0, len(frames), chunk):
        # (J, t * 12): every frame's maps side by side, so one matrix product blends them all
        maps = np.ascontiguousarray(frames[start:start + chunk].transpose(1, 0, 2))
        _linear_blend_skinning_kernel(points, skin_weights, maps.reshape(len(maps), -1),
                                      out[start:start + chunk])
    return out if transforms.ndim == 4 else out[0]


@kernel
def _linear_blend_skinning_kernel(points, skin_weights, maps, out):
    """maps (J, T*12) -> out (T, V, 3). The blend of the maps is a matrix product (BLAS);
    then each point goes through its own blended 3 x 4 map."""
    blended = np.dot(skin_weights, maps)                                 # (V, T*12)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for t in range(out.shape[0]):
            m = blended[i, 12 * t:12 * t + 12]                           # row-major 3 x 4
            out[t, i, 0] = m[0] * x + m[1] * y + m[2] * z + m[3]
            out[t, i, 1] = m[4] * x + m[5] * y + m[6] * z + m[7]
            out[t, i, 2] = m[8] * x + m[9] * y + m[10] * z + m[11]
