"""Stage 1, SKR: PointNet regression of the 22 joints from a point cloud.

    points (P, 3) -> centre on the centroid -> 3x3 input transform -> point layer 0 ->
    w0 x w0 feature transform -> point layers 1, 2 -> max-pool over points -> MLP head ->
    (J, 3) offsets + centroid
Batch norm is folded into the linear layers at export (training/export.py), so every layer
here is a plain linear map with ReLU.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import MIN_POINTS, NUM_JOINTS
from .nn import MLP, dense, mlp
from .validation import as_float32_array


class PointNetWeights(NamedTuple):
    point: tuple   # 3 Dense layers applied to every point, each with ReLU
    head: MLP      # on the max-pooled feature


class SKRWeights(NamedTuple):
    input_transform: PointNetWeights     # predicts the 3 x 3 transform of the points
    feature_transform: PointNetWeights   # predicts the w0 x w0 transform of the features
    regressor: PointNetWeights           # predicts the J*3 joint offsets


def regress_joints(points, weights, chunk_points=65536):
    """Joint positions of the body in each point cloud.

    Args:
        points: (P, 3) or (B, P, 3) float32, metres, any order; P >= MIN_POINTS.
        weights: SKRWeights.
        chunk_points: clouds go through the network together, about this many points at a
            time: one matrix product per layer for all of them, activations bounded to
            ``chunk_points x widest layer`` floats.
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
    clouds = max(1, chunk_points // batch.shape[1])
    joints = np.empty((batch.shape[0], NUM_JOINTS, 3), dtype=np.float32)
    for start in range(0, batch.shape[0], clouds):
        joints[start:start + clouds] = _regress_joints_kernel(batch[start:start + clouds],
                                                              weights)
    return joints if points.ndim == 3 else joints[0]


@kernel
def _max_per_cloud(features, clouds):
    """(B*P, C) rows of B clouds of P points -> (B, C) column maxima of each cloud."""
    count = features.shape[0] // clouds
    out = np.empty((clouds, features.shape[1]), dtype=np.float32)
    for b in range(clouds):
        out[b] = features[b * count]
        for i in range(b * count + 1, (b + 1) * count):
            for c in range(features.shape[1]):
                out[b, c] = max(out[b, c], features[i, c])
    return out


@kernel
def _transform_per_cloud(x, net, clouds):
    """STN: x (B*P, k) -> each cloud's points times its (k, k) = identity + prediction."""
    k = x.shape[1]
    features = x
    for layer in net.point:
        features = dense(features, layer, True)
    transforms = mlp(_max_per_cloud(features, clouds), net.head).reshape(clouds, k, k)
    count = x.shape[0] // clouds
    out = np.empty_like(x)
    for b in range(clouds):
        transform = transforms[b] + np.eye(k, dtype=np.float32)
        out[b * count:(b + 1) * count] = np.dot(x[b * count:(b + 1) * count], transform)
    return out


@kernel
def _regress_joints_kernel(points, weights):
    """(B, P, 3) -> (B, J, 3); every layer is one matrix product over all B*P points."""
    clouds, count = points.shape[0], points.shape[1]
    centroids = np.zeros((clouds, 3), dtype=np.float32)
    x = np.empty((clouds * count, 3), dtype=np.float32)
    for b in range(clouds):
        for i in range(count):
            centroids[b] += points[b, i]
        centroids[b] /= np.float32(count)
        for i in range(count):
            x[b * count + i] = points[b, i] - centroids[b]
    x = _transform_per_cloud(x, weights.input_transform, clouds)            # (B*P, 3)
    x = dense(x, weights.regressor.point[0], True)                          # (B*P, w0)
    x = _transform_per_cloud(x, weights.feature_transform, clouds)          # (B*P, w0)
    for i in range(1, len(weights.regressor.point)):
        x = dense(x, weights.regressor.point[i], True)                      # (B*P, w2)
    offsets = mlp(_max_per_cloud(x, clouds), weights.regressor.head)        # (B, J*3)
    return offsets.reshape(clouds, -1, 3) + centroids.reshape(clouds, 1, 3)
