"""Point and mesh files: ``.ply`` and ``.obj`` through trimesh (the ``cli`` extra), ``.xyz``
and ``.npy`` with NumPy. Lengths and axes are the file's own; ``minretarget.units`` converts.

Reading keeps the file's vertex order and count (no merging, no removal of unreferenced
vertices), so that faces and per-vertex outputs line up with the file.
"""
from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..extras import require
from .npz import load_npy

POINT_SUFFIXES = (".ply", ".obj", ".xyz", ".npy")
MESH_SUFFIXES = (".ply", ".obj")


def read_points(path):
    """Read the points (and triangles, if any) of one file.

    Args:
        path: a ``.ply`` or ``.obj`` mesh or point cloud, an ``.xyz`` text file (x y z per line;
            further columns, e.g. normals, are ignored; ``#`` starts a comment) or an ``.npy``
            (N, 3) array.
    Returns:
        points: (N, 3) float32, finite, the file's units and axes.
        faces: (F, 3) int64 triangles (polygons split by trimesh) indexing ``points``, or
            None for a point cloud.
    Raises:
        ValueError naming the file: unknown suffix, no such file, unreadable or damaged
        content, not (N, 3) numbers, a non-finite value, a face index out of range.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_SUFFIXES:
        raise ValueError(f"{path}: unknown point file type {suffix!r}; expected one of "
                         f"{', '.join(POINT_SUFFIXES)}")
    if not path.is_file():
        raise ValueError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    faces = None
    if suffix in MESH_SUFFIXES:
        points, faces = _read_trimesh(path, suffix)
    elif suffix == ".npy":
        points = load_npy(path)
    else:
        try:
            # an empty file is no points; told apart first, since np.loadtxt would warn
            # (and silencing a warning changes every thread's filters)
            points = (np.loadtxt(path, usecols=(0, 1, 2), ndmin=2, comments="#")
                      if _has_data(path) else np.empty((0, 3)))
        except (ValueError, OSError, IndexError, UnicodeDecodeError) as error:
            raise ValueError(f"{path}: cannot read points: {error}") from None
    return checked_points(path, points, faces)


def _has_data(path):
    """Whether a text point file has a line that is neither blank nor a # comment."""
    with open(path, encoding="utf-8", errors="replace") as file:
        return any(line.strip() and not line.lstrip().startswith("#") for line in file)


def checked_points(path, points, faces=None):
    """``read_points``'s checks on arrays read from ``path``: (N, 3) numbers, finite in
    float32, faces (F, 3) indexing them (or None) -> (float32 points, int64 faces or None);
    ValueError naming the file."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind not in "fiu":
        raise ValueError(f"{path}: expected (N, 3) numeric points, got {points.dtype} "
                         f"{points.shape}")
    with np.errstate(over="ignore"):        # beyond float32's range: inf, refused just below
        points = np.ascontiguousarray(points, dtype=np.float32)
    if not np.isfinite(points).all():
        row = int(np.argwhere(~np.isfinite(points))[0, 0])
        raise ValueError(f"{path}: point {row} is not finite (or too large for float32): "
                         f"{points[row].tolist()}")
    if faces is not None:
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
            raise ValueError(f"{path}: faces must be (F, 3) integers, got {faces.dtype} "
                             f"{faces.shape}")
        faces = faces.astype(np.int64) if len(faces) else None
    if faces is not None:
        outside = faces[(faces < 0) | (faces >= len(points))]
        if outside.size:
            raise ValueError(f"{path}: a face refers to vertex {int(outside[0])}; the file "
                             f"has {len(points)} vertices")
    return points, faces


def _read_trimesh(path, suffix):
    trimesh = require("trimesh", f"reading {suffix} files")
    try:
        # No warnings filter here, not even a scoped one: the filters are the process's (and
        # every thread's, catch_warnings included), and a reader must not change what its
        # caller sees. (An older trimesh warned about absent UVs here; 5.2 does not.)
        loaded = trimesh.load(path, file_type=suffix[1:], process=False, maintain_order=True)
        geometries = (list(loaded.geometry.values()) if isinstance(loaded, trimesh.Scene)
                      else [loaded])
        read = [(np.asarray(g.vertices), getattr(g, "faces", None)) for g in geometries]
    except Exception as error:  # noqa: BLE001
        # trimesh's readers fail on damaged files with many exception types (found by
        # fuzzing: UnboundLocalError, TypeError, OverflowError, ...): one clear error instead.
        raise ValueError(f"{path}: cannot read points; the file looks damaged or truncated "
                         f"({type(error).__name__}: {error})") from None
    if len(read) != 1:
        raise ValueError(f"{path}: holds {len(read)} objects; expected one mesh or point cloud")
    vertices, faces = read[0]
    faces = None if faces is None or len(faces) == 0 else np.asarray(faces, np.int64)
    return vertices, faces


def mesh_bytes(vertices, faces, file_type):
    """Encode a mesh or point cloud as a ``ply`` (binary, float32) or ``obj`` (text, 8 decimals).

    Args:
        vertices: (V, 3) float points.
        faces: (F, 3) int triangles, or None for a point cloud.
        file_type: "ply" or "obj".
    """
    trimesh = require("trimesh", f"writing .{file_type} files")
    vertices = np.asarray(vertices, dtype=np.float64)
    if faces is None:
        geometry = trimesh.PointCloud(vertices)
    else:
        geometry = trimesh.Trimesh(vertices, np.asarray(faces), process=False)
    data = geometry.export(file_type=file_type)
    return data.encode("ascii") if isinstance(data, str) else data


def write_mesh(path, vertices, faces=None):
    """Write a mesh or point cloud atomically; the type is the suffix of ``path``."""
    path = Path(path)
    data = mesh_bytes(vertices, faces, path.suffix.lower()[1:])
    with atomic_write(path) as file:
        file.write(data)

