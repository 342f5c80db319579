"""Area-uniform point sampling on triangle meshes.

Source clouds: a fresh sample every frame (``sample_point_clouds``). Each point picks a triangle
with probability proportional to its area, then a uniform point in it (barycentric coordinates
by the square-root trick). The draws are independent, so a cloud comes in a random order that
is fresh every frame: nothing ties a point's index to a place on the body.

Targets: a fixed set of (triangle, barycentric coordinates) drawn once (``sample_surface``) and
re-evaluated on any posing of the same mesh (``points_from_barycentric``), so that the same
surface points can be followed through a motion (ground truth for evaluation).

Every function takes a seeded ``numpy.random.Generator``; lengths are metres.
"""
import numpy as np

from .validation import as_float32_array


def triangle_areas(vertices, faces):
    """(..., V, 3) vertices and (F, 3) faces -> (..., F) float32 triangle areas, metres^2."""
    vertices = np.asarray(vertices, dtype=np.float32)
    first = vertices[..., faces[:, 0], :]                              # (..., F, 3)
    cross = np.cross(vertices[..., faces[:, 1], :] - first, vertices[..., faces[:, 2], :] - first)
    return 0.5 * np.sqrt(np.einsum("...i,...i->...", cross, cross))


def _check_mesh(vertices, faces):
    vertices = as_float32_array(vertices, "vertices", (..., None, 3))
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {faces.dtype} "
                         f"{faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[-2]):
        raise ValueError(f"faces index vertices outside 0..{vertices.shape[-2] - 1}")
    return vertices, faces


def _uniform_barycentric(rng, shape):
    """(..., 3) float64 barycentric coordinates, uniform over the triangle (square-root trick)."""
    r1 = np.sqrt(rng.random(shape))
    r2 = rng.random(shape)
    return np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=-1)


def _area_weighted_faces(areas, count, rng):
    """(T, F) areas -> (T, count) int64 triangle indices, each row drawn i.i.d. by area."""
    frames, num_faces = areas.shape
    cumulative = np.cumsum(areas, axis=1, dtype=np.float64)
    cumulative /= cumulative[:, -1:]
    # Row t's CDF lives in (t, t + 1]: one searchsorted serves every frame.
    offsets = np.arange(frames)[:, None]
    draws = rng.random((frames, count)) + offsets                     # (T, count)
    flat = np.searchsorted((cumulative + offsets).ravel(), draws.ravel(), side="right")
    return np.minimum(flat.reshape(frames, count) - offsets * num_faces, num_faces - 1)


def sample_surface(vertices, faces, count, rng):
    """Draw fixed surface points on one mesh, area-uniform.

    Args:
        vertices: (V, 3) float32 mesh vertices, metres.
        faces: (F, 3) int triangles.
        count: Q, the number of points.
        rng: numpy Generator.
    Returns:
        face_index: (Q,) int64 triangle of each point.
        barycentric: (Q, 3) float32 barycentric coordinates (>= 0, summing to 1).
    """
    vertices, faces = _check_mesh(vertices, faces)
    if vertices.ndim != 2:
        raise ValueError(f"vertices must have shape (V, 3), got {vertices.shape}")
    face_index = _area_weighted_faces(triangle_areas(vertices, faces)[None], count, rng)[0]
    return face_index, _uniform_barycentric(rng, (count,)).astype(np.float32)


def points_from_barycentric(vertices, faces, face_index, barycentric):
    """Evaluate fixed surface points on (posed) meshes.

    Args:
        vertices: (..., V, 3) float32 mesh vertices, metres.
        faces: (F, 3) int triangles.
        face_index: (Q,) int triangle of each point.
        barycentric: (Q, 3) float32 barycentric coordinates.
    Returns:
        (..., Q, 3) float32 points, metres.
    """
    vertices, faces = _check_mesh(vertices, faces)
    corners = vertices[..., faces[face_index], :]                     # (..., Q, 3 corners, 3)
    return np.einsum("...qca,qc->...qa", corners, np.asarray(barycentric, np.float32))


def sample_point_clouds(vertices, faces, count, rng):
    """Fresh area-uniform point clouds, one per frame, each in its own random order.

    Args:
        vertices: (T, V, 3) or (V, 3) float32 posed mesh vertices, metres.
        faces: (F, 3) int triangles.
        count: P, points per frame.
        rng: numpy Generator.
    Returns:
        (T, P, 3) or (P, 3) float32 points, metres.
    """
    vertices, faces = _check_mesh(vertices, faces)
    single = vertices.ndim == 2
    frames = vertices[None] if single else vertices.reshape((-1,) + vertices.shape[-2:])
    face_index = _area_weighted_faces(triangle_areas(frames, faces), count, rng)  # (T, P)
    barycentric = _uniform_barycentric(rng, face_index.shape)                     # (T, P, 3)
    corners = frames[np.arange(len(frames))[:, None, None], faces[face_index]]    # (T, P, 3, 3)
    points = np.einsum("tpca,tpc->tpa", corners, barycentric).astype(np.float32)
    return points[0] if single else points.reshape(vertices.shape[:-2] + (count, 3))


def seeded_subset(points, count, seed):
    """``count`` of the (P, 3) ``points`` (all of them if P <= count), drawn without
    replacement by a generator seeded with ``seed`` (a stream's frame index, or a tuple of
    such integers): the same points of the same cloud whoever asks."""
    if len(points) <= count:
        return points
    return points[np.random.default_rng(seed).choice(len(points), count, replace=False)]
