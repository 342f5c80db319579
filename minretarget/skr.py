"""Stage 1, SKR: PointNet regression of the 22 joints from a point cloud.

    points (P, 3) -> centre on the centroid -> 3x3 input transform -> point layer 0 ->
    w0 x w0 feature transform -> point layers 1, 2 -> max-pool over points -> MLP head ->
    (J, 3) offsets + centroid
Batch norm is folded into the linear layers at export (training/export.py), so every layer
here is a plain linear map with ReLU.
"""
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import MIN_POINTS
from .nn import MLP, dense, mlp
from .validation import as_float32_array


class PointNetWeights(NamedTuple):
    point: tuple   # 3 Dense layers applied to every point, each with ReLU
    head: MLP      # on the max-pooled feature


class SKRWeights(NamedTuple):
    input_transform: PointNetWeights     # predicts the 3 x 3 transform of the points
    feature_transform: PointNetWeights   # predicts the w0 x w0 transform of the features
    regressor: PointNetWeights           # predicts the J*3 joint offsets


def regress_joints(points, weights, workers=1):
    """Joint positions of the body in each point cloud.

    Args:
        points: (P, 3) or (B, P, 3) float32, metres, any order; P >= MIN_POINTS.
        weights: SKRWeights.
        workers: threads running clouds side by side (the kernel releases the GIL). Give
            BLAS one thread then (``OPENBLAS_NUM_THREADS=1``): its own threads and these
            would share the cores. Clouds are not stacked into one product per layer: a
            cloud's (P, 256) activations stay in cache, a stack's do not, and that measured
            up to twice slower per cloud.
    Returns:
        (J, 3) or (B, J, 3) float32 joint positions, metres, in the points' frame.
    """
    points = as_float32_array(points, "points", (..., None, 3))
    if points.ndim not in (2, 3):
        raise ValueError(f"points must have shape (P, 3) or (B, P, 3), got {points.shape}")
    if points.shape[-2] < MIN_POINTS:
        raise ValueError(f"points has {points.shape[-2]} points per cloud; at least "
                         f"{MIN_POINTS} are needed")
    batch = points if points.ndim == 3 else points[None]                # (B, P, 3)
    if workers > 1 and len(batch) > 1:
        with ThreadPoolExecutor(workers) as pool:
            joints = list(pool.map(lambda cloud: _regress_joints_kernel(cloud, weights), batch))
    else:
        joints = [_regress_joints_kernel(cloud, weights) for cloud in batch]
    return np.stack(joints) if points.ndim == 3 else joints[0]


@kernel
def _max_over_points(features):
    """(P, C) -> (1, C) column maxima."""
    out = features[0:1].copy()
    for i in range(1, features.shape[0]):
        for c in range(features.shape[1]):
            out[0, c] = max(out[0, c], features[i, c])
    return out


@kernel
def _point_feature(x, net, first):
    """Point layers ``first``.. of ``net`` on x (P, C), then max-pool: -> (1, C_last)."""
    for i in range(first, len(net.point)):
        x = dense(x, net.point[i], True)
    return _max_over_points(x)


@kernel
def _transform(x, net):
    """STN: x (P, k) -> (k, k) = identity + the net's prediction."""
    k = x.shape[1]
    transform = mlp(_point_feature(x, net, 0), net.head).reshape(k, k)
    for i in range(k):
        transform[i, i] += np.float32(1.0)
    return transform


@kernel
def _regress_joints_kernel(points, weights):
    centroid = np.zeros((1, 3), dtype=np.float32)
    for i in range(points.shape[0]):
        centroid[0] += points[i]
    centroid /= np.float32(points.shape[0])
    x = points - centroid                                                # (P, 3)
    x = np.dot(x, _transform(x, weights.input_transform))                # (P, 3)
    x = dense(x, weights.regressor.point[0], True)                       # (P, w0)
    x = np.dot(x, _transform(x, weights.feature_transform))              # (P, w0)
    feature = _point_feature(x, weights.regressor, 1)                    # (1, w2)
    offsets = mlp(feature, weights.regressor.head)                       # (1, J*3)
    return offsets.reshape(-1, 3) + centroid                             # (J, 3)
