"""Point and mesh files: ``.ply`` and ``.obj`` through trimesh (the ``cli`` extra), ``.xyz``
and ``.npy`` with NumPy. Lengths and axes are the file's own; ``minretarget.units`` converts.

Reading keeps the file's vertex order and count (no merging, no removal of unreferenced
vertices), so that faces and per-vertex outputs line up with the file.
"""
import warnings
from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..extras import require

POINT_SUFFIXES = (".ply", ".obj", ".xyz", ".npy")
MESH_SUFFIXES = (".ply", ".obj")


def read_points(path):
    """Read the points (and triangles, if any) of one file.

    Args:
        path: a ``.ply`` or ``.obj`` mesh or point cloud, an ``.xyz`` text file (x y z per line;
            further columns, e.g. normals, are ignored; ``#`` starts a comment) or an ``.npy``
            (N, 3) array.
    Returns:
        points: (N, 3) float32, the file's units and axes.
        faces: (F, 3) int64 triangles (polygons split by trimesh), or None for a point cloud.
    Raises:
        ValueError naming the file: unknown suffix, unreadable content, not (N, 3).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    faces = None
    try:
        if suffix in MESH_SUFFIXES:
            points, faces = _read_trimesh(path, suffix)
        elif suffix == ".xyz":
            points = np.loadtxt(path, usecols=(0, 1, 2), ndmin=2, comments="#")
        elif suffix == ".npy":
            points = np.load(path, allow_pickle=False)
        else:
            raise ValueError(f"unknown point file type {suffix!r}; expected one of "
                             f"{', '.join(POINT_SUFFIXES)}")
    except (ValueError, OSError, EOFError, IndexError, KeyError) as error:
        raise ValueError(f"{path}: cannot read points: {error}") from None
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind not in "fiu":
        raise ValueError(f"{path}: expected (N, 3) numeric points, got {points.dtype} "
                         f"{points.shape}")
    return np.ascontiguousarray(points, dtype=np.float32), faces


def _read_trimesh(path, suffix):
    trimesh = require("trimesh", f"reading {suffix} files")
    with warnings.catch_warnings():
        # maintain_order makes trimesh's OBJ texture code warn about absent UVs; harmless.
        warnings.simplefilter("ignore", RuntimeWarning)
        loaded = trimesh.load(path, file_type=suffix[1:], process=False, maintain_order=True)
    if isinstance(loaded, trimesh.Scene):
        geometries = list(loaded.geometry.values())
        if len(geometries) != 1:
            raise ValueError(f"holds {len(geometries)} objects; expected one mesh or point cloud")
        loaded = geometries[0]
    faces = getattr(loaded, "faces", None)
    if faces is not None and len(faces) == 0:
        faces = None
    return np.asarray(loaded.vertices), None if faces is None else np.asarray(faces, np.int64)


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

