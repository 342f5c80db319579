"""Stage 1b, joint refinement: each of SKR's joints moved by a small PointNet that looks at the
points around it.

SKR predicts all 22 joints from one global feature of the cloud, which pulls joints far from
the body's centre towards their average place (the wrists come out too close to the
elbows, the forearms turned off their direction: docs/runtime_notes.md). The refiner sees each
joint's own neighbourhood:

    for each joint j of SKR's skeleton (J, 3):
        its K nearest points of the cloud, less joint j, / scale   (K, 3)
        -> per-point layers (ReLU) -> max-pool                    (1, C)
        ++ every joint less joint j (J*3) ++ one-hot of j (J)       the skeleton as context
        -> MLP -> offset * scale; joint j + offset
Clouds of more than ``MAX_POINTS`` points are thinned to about that many by a stride in
their order first: the K nearest points then cover about the neighbourhood the refiner was
trained on (clouds of 1,024 to 2,048 points). So above MAX_POINTS the result depends a little
on the points' order (which points the stride keeps); at or below it, not at all.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import NUM_JOINTS
from .nn import MLP, dense, mlp
from .validation import as_float32_array

MAX_POINTS = 2048
SCALE = np.float32(0.1)     # metres: neighbourhoods and offsets in units of 10 cm


class RefinerWeights(NamedTuple):
    point: tuple   # Dense layers applied to every neighbour, each with ReLU
    head: MLP      # on [pooled feature, skeleton relative to the joint, one-hot of the joint]


def refine_joints(points, joints, weights, neighbours):
    """SKR's joints moved to where each one's neighbourhood in the cloud puts it.

    Args:
        points: (P, 3) or (B, P, 3) float32, metres, any order.
        joints: (J, 3) or (B, J, 3) float32 SKR's joints of those clouds, metres.
        weights: RefinerWeights.
        neighbours: K, the points each joint looks at (``ModelConfig.refine_neighbours``).
    Returns:
        joints like ``joints``, float32, metres.
    """
    points = as_float32_array(points, "points", (..., None, 3))
    if points.ndim not in (2, 3) or points.shape[-2] == 0:
        raise ValueError(f"points must have shape (P, 3) or (B, P, 3) with P >= 1, got "
                         f"{points.shape}")
    joints = as_float32_array(joints, "joints", points.shape[:-2] + (NUM_JOINTS, 3))
    if int(neighbours) < 1:
        raise ValueError(f"neighbours must be at least 1, got {neighbours}")
    return refine_checked(points, joints, weights, int(neighbours))


def refine_checked(points, joints, weights, neighbours):
    """``refine_joints`` on checked inputs (C-contiguous float32 arrays, an int >= 1)."""
    stride = -(-points.shape[-2] // MAX_POINTS)                 # ceil: at most MAX_POINTS
    clouds = points[..., ::stride, :] if points.ndim == 3 else points[None, ::stride]
    skeletons = joints if joints.ndim == 3 else joints[None]
    k = min(neighbours, clouds.shape[1])
    refined = np.empty_like(skeletons)
    for b in range(len(clouds)):
        refined[b] = _refine_kernel(np.ascontiguousarray(clouds[b]), skeletons[b], weights, k)
    return refined if points.ndim == 3 else refined[0]


@kernel
def _nearest(points, centre, k):
    """Indices of the k <= P points nearest ``centre`` (3,), in no particular order (the
    max-pool does not care). A max-heap of the k nearest so far: most points fail one comparison with
    its top, so this is about one pass over the points, where a full sort orders them all."""
    heap_distance, heap_index = np.empty(k, dtype=np.float32), np.empty(k, dtype=np.int64)
    heap_distance[:] = np.inf
    heap_index[:] = 0
    for i in range(points.shape[0]):
        dx, dy, dz = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
        distance = dx * dx + dy * dy + dz * dz            # scalars: no array per point
        if distance >= heap_distance[0]:
            continue
        parent = 0                                  # replace the farthest, sift it down
        while True:
            child = 2 * parent + 1
            if child >= k:
                break
            if child + 1 < k and heap_distance[child + 1] > heap_distance[child]:
                child += 1
            if heap_distance[child] <= distance:
                break
            heap_distance[parent] = heap_distance[child]
            heap_index[parent] = heap_index[child]
            parent = child
        heap_distance[parent] = distance
        heap_index[parent] = i
    return heap_index


@kernel
def _refine_kernel(points, joints, weights, k):
    num_joints = joints.shape[0]
    # Every joint's neighbourhood stacked into one (J*K, 3) matrix, so each point layer is
    # one matrix product for all joints.
    local = np.empty((num_joints * k, 3), dtype=np.float32)
    for j in range(num_joints):
        nearest = _nearest(points, joints[j], k)
        for i in range(k):
            for axis in range(3):
                local[j * k + i, axis] = (points[nearest[i], axis] - joints[j, axis]) / SCALE
    x = local
    for layer in weights.point:
        x = dense(x, layer, True)
    width = x.shape[1]
    head_input = np.empty((num_joints, width + 4 * num_joints), dtype=np.float32)
    head_input[:] = 0.0
    for j in range(num_joints):
        for c in range(width):                                   # max-pool the j-th block
            best = x[j * k, c]
            for i in range(1, k):
                best = max(best, x[j * k + i, c])
            head_input[j, c] = best
        for other in range(num_joints):
            for axis in range(3):
                head_input[j, width + 3 * other + axis] = joints[other, axis] - joints[j, axis]
        head_input[j, width + 3 * num_joints + j] = 1.0
    refined = mlp(head_input, weights.head)                     # (J, 3) offsets / SCALE
    for j in range(num_joints):
        for axis in range(3):
            refined[j, axis] = joints[j, axis] + SCALE * refined[j, axis]
    return refined
