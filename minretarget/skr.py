"""Stage 1, SKR: PointNet regression of the 22 joints from a point cloud.

    points (P, 3) -> centre on the centroid -> 3x3 input transform -> point layer 0 ->
    w0 x w0 feature transform -> point layers 1, 2 -> max-pool over points -> MLP head ->
    (J, 3) offsets + centroid
Batch norm is folded into the linear layers at export (training/export.py), so every layer
here is a plain linear map with ReLU.
"""
import functools
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import FORWARD_AXIS, LEFT_AXIS, MIN_POINTS, MIRROR, UP_AXIS
from .nn import MLP, dense, mlp
from .validation import as_float32_array, as_workers


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
        workers: threads (the kernels release the GIL): a batch's clouds go side by side, a
            single cloud's points are shared (the threads meet at its three max-pools).
            Give BLAS one thread then (``OPENBLAS_NUM_THREADS=1`` or threadpoolctl), or its
            threads and these share the cores. Clouds are never stacked into one product
            per layer: a cloud's (P, 256) activations stay in cache, a stack's do not, which
            measured slower.
    Returns:
        (J, 3) or (B, J, 3) float32 joint positions, metres, in the points' frame.
    """
    points = as_float32_array(points, "points", (..., None, 3))
    if points.ndim not in (2, 3):
        raise ValueError(f"points must have shape (P, 3) or (B, P, 3), got {points.shape}")
    if points.shape[-2] < MIN_POINTS:
        raise ValueError(f"points has {points.shape[-2]} points per cloud; at least "
                         f"{MIN_POINTS} are needed")
    return regress_checked(points, weights, as_workers(workers))


def regress_checked(points, weights, workers):
    """``regress_joints`` on checked inputs (C-contiguous float32 clouds, a worker count)."""
    batch = points if points.ndim == 3 else points[None]                # (B, P, 3)
    if workers > 1 and len(batch) > 1:   # whole clouds side by side: no meeting points
        joints = list(_thread_pool(workers).map(
            lambda cloud: _regress_joints_one(cloud, weights), batch))
    elif workers > 1:                     # one cloud: its points shared
        joints = [_regress_joints_shared(batch[0], weights, _thread_pool(workers), workers)]
    else:
        joints = [_regress_joints_one(cloud, weights) for cloud in batch]
    return np.stack(joints) if points.ndim == 3 else joints[0]


def view_turn(points, viewpoint):
    """The turn about the up axis that puts one camera in front of its cloud: the horizontal
    direction from the cloud's centroid to the camera goes onto +Z (the T-pose's forward).
    The one-view SKR (``Weights.skr_view``) reads clouds turned so (``read_from_view``): it
    learns where the body faces from where the camera stands, whatever the world's axes.

    Args:
        points: (P, 3) float32 the cloud, metres.
        viewpoint: (3,) the camera's position, metres, in the cloud's frame.
    Returns:
        (3, 3) float32 rotation R: a point p turned is R p (``points @ R.T``); the identity
        when the camera stands straight above or below the centroid.
    """
    offset = np.asarray(viewpoint, np.float64) - np.asarray(points, np.float64).mean(axis=0)
    offset[UP_AXIS] = 0.0
    length = np.linalg.norm(offset)
    turn = np.eye(3)
    if length > 1e-6:
        # Rows: the camera's horizontal direction, up, and up x that direction, placed so that
        # R takes them onto forward (+Z), up (+Y) and left (+X): up x forward = left.
        toward = offset / length
        up = np.zeros(3)
        up[UP_AXIS] = 1.0
        turn[FORWARD_AXIS], turn[UP_AXIS], turn[LEFT_AXIS] = toward, up, np.cross(up, toward)
    return turn.astype(np.float32)


def read_from_view(skeleton, points, viewpoint):
    """A skeleton finder (clouds (B, P, 3) -> joints (B, J, 3), e.g. the one-view SKR) run on
    each cloud turned by ``view_turn``, its joints turned back.

    Args:
        skeleton: the finder, called once on all the turned clouds.
        points: (P, 3) or (B, P, 3) C-contiguous float32 clouds (checked), metres.
        viewpoint: (3,) the one camera that saw them all, metres.
    Returns:
        (J, 3) or (B, J, 3) float32 joints, metres.
    """
    batch = points if points.ndim == 3 else points[None]
    turns = np.stack([view_turn(cloud, viewpoint) for cloud in batch])          # (B, 3, 3)
    # One call on every turned cloud: a finder with threads reads them side by side.
    joints = skeleton(np.ascontiguousarray(np.einsum("bpa,bca->bpc", batch, turns)))
    joints = np.ascontiguousarray(np.einsum("bja,bac->bjc", joints, turns), dtype=np.float32)
    return joints if points.ndim == 3 else joints[0]


def mirror_averaged(skeleton, points):
    """A skeleton finder run on each cloud and on its mirror image (x -> -x: another plausible
    body and pose), the second skeleton mirrored back with left and right joints swapped and
    averaged with the first: what the finder gets wrong on one side more than the other
    cancels: it lowers the runtime skeleton's mean joint error on held-out bodies, in T-poses
    and in motion (docs/runtime_notes.md). Twice the finder's time.

    Args:
        skeleton: clouds (B, P, 3) -> joints (B, J, 3), e.g. SKR; called once, on 2B clouds.
        points: (P, 3) or (B, P, 3) float32 clouds, metres.
    Returns:
        (J, 3) or (B, J, 3) float32 joints, metres.
    """
    points = as_float32_array(points, "points", (..., None, 3))
    if points.ndim not in (2, 3):
        raise ValueError(f"points must have shape (P, 3) or (B, P, 3), got {points.shape}")
    return mirror_averaged_checked(skeleton, points)


def mirror_averaged_checked(skeleton, points):
    """``mirror_averaged`` on checked clouds (C-contiguous float32)."""
    mirror = np.ones(3, np.float32)
    mirror[LEFT_AXIS] = -1                                      # flip the body's left axis
    batch = points if points.ndim == 3 else points[None]                # (B, P, 3)
    both = skeleton(np.concatenate([batch, batch * mirror]))
    plain, mirrored = both[:len(batch)], both[len(batch):]              # (B, J, 3) each
    joints = ((plain + mirrored[:, list(MIRROR)] * mirror) / 2).astype(np.float32)
    return joints if points.ndim == 3 else joints[0]


@functools.lru_cache(maxsize=None)
def _thread_pool(workers):
    """One lasting pool per size: a stream calls SKR every frame, and starting threads each
    time would cost more than a small cloud's work. Idle threads wait without spinning."""
    return ThreadPoolExecutor(workers, thread_name_prefix="minretarget-skr")


def _regress_joints_shared(points, weights, pool, parts):
    """``_regress_joints_one`` with the per-point layers on ``parts`` slices of the
    points in ``pool``'s threads; the max-pools combine the slices' maxima."""
    def pooled(function, slices):
        return np.max(np.concatenate(list(pool.map(function, slices))), axis=0, keepdims=True)

    x, centroid = _centred(points)
    slices = np.array_split(x, parts)
    net = weights.input_transform
    input_transform = _transform_matrix(pooled(lambda s: _point_feature(s, net, 0), slices),
                                        net.head)
    first = weights.regressor.point[0]
    slices = list(pool.map(lambda s: _first_layer(s, input_transform, first), slices))
    net = weights.feature_transform
    feature_transform = _transform_matrix(pooled(lambda s: _point_feature(s, net, 0), slices),
                                          net.head)
    net = weights.regressor
    feature = pooled(lambda s: _point_feature(np.dot(s, feature_transform), net, 1), slices)
    return _joints(feature, net.head, centroid)


@kernel
def _centred(points):
    """(P, 3) -> the points less their centroid (P, 3), and the centroid (1, 3). Scalar
    loops: numba compiles array expressions and slice assignments slowly (issue 40)."""
    centroid = np.empty((1, 3), dtype=np.float32)
    centroid[:] = 0.0
    for i in range(points.shape[0]):
        for a in range(3):
            centroid[0, a] += points[i, a]
    for a in range(3):
        centroid[0, a] /= np.float32(points.shape[0])
    centred = np.empty_like(points)
    for i in range(points.shape[0]):
        for a in range(3):
            centred[i, a] = points[i, a] - centroid[0, a]
    return centred, centroid


@kernel
def _point_feature(x, net, first):
    """Point layers ``first``.. of ``net`` on x (P, C), then max-pool: -> (1, C_last)."""
    for i in range(first, len(net.point)):
        x = dense(x, net.point[i], True)
    out = np.empty((1, x.shape[1]), dtype=x.dtype)           # column maxima
    for c in range(x.shape[1]):
        out[0, c] = x[0, c]
    for i in range(1, x.shape[0]):
        for c in range(x.shape[1]):
            out[0, c] = max(out[0, c], x[i, c])
    return out


@kernel
def _transform_matrix(feature, head):
    """STN head: the pooled feature (1, C) -> (k, k) = identity + the head's prediction."""
    flat = mlp(feature, head)
    k = int(np.sqrt(flat.shape[1]))
    transform = flat.reshape(k, k)
    for i in range(k):
        transform[i, i] += np.float32(1.0)
    return transform


@kernel
def _first_layer(x, input_transform, layer):
    """(P, 3) centred points -> (P, w0): the input transform, then point layer 0."""
    return dense(np.dot(x, input_transform), layer, True)


@kernel
def _joints(feature, head, centroid):
    """The pooled feature (1, C) -> (J, 3) joints: the head's offsets plus the centroid."""
    joints = mlp(feature, head).reshape(-1, 3)
    for j in range(joints.shape[0]):
        for a in range(3):
            joints[j, a] += centroid[0, a]
    return joints


def _regress_joints_one(points, weights):
    """SKR on one cloud (P, 3) -> joints (J, 3), stage by stage. Plain Python over the stage
    kernels (which the shared path calls too), not one kernel around them: numba compiled
    such a kernel with all of them inlined again, most of a second's cold start (issue 40),
    for a few microseconds of calls a cloud."""
    x, centroid = _centred(points)                                       # (P, 3), (1, 3)
    net = weights.input_transform
    x = _first_layer(x, _transform_matrix(_point_feature(x, net, 0), net.head),
                     weights.regressor.point[0])                          # (P, w0)
    net = weights.feature_transform
    feature = _transformed_feature(x, _transform_matrix(_point_feature(x, net, 0), net.head),
                                   weights.regressor)                     # (1, w2)
    return _joints(feature, weights.regressor.head, centroid)            # (J, 3)


@kernel
def _transformed_feature(x, transform, net):
    """(P, w0) features -> through the feature transform (w0, w0), then point layers 1..
    of ``net`` and the max-pool: (1, w2). The layer offset is an np.int64, not a literal 1:
    numba compiles a kernel once per literal value it is called with."""
    return _point_feature(np.dot(x, transform), net, np.int64(1))
