"""Reading what the command line retargets: SOURCE motions and TARGET bodies.

SOURCE, one of:
    - a folder of per-frame point files (``.ply``, ``.obj``, ``.xyz``, ``.npy``), in natural
      order of their names (``frame2`` before ``frame10``); hidden files and other suffixes
      are skipped. A frame with faces (a mesh) becomes points drawn evenly over its surface
      (``sampling.sample_point_clouds``), so that where its vertices crowd (hands, face)
      does not matter: SKR learned on such clouds;
    - an ``.npy`` array (T, P, 3) of frames (memory-mapped), or an ``.npz`` holding one such
      array (its only array, else the key ``points`` or ``source_points``);
    - a ``.bvh`` / ``.bvh.gz`` skeleton motion: its joints map onto the 22 canonical joints
      (``minretarget.skeletons``: any common naming scheme, or a skeleton map) and it is
      resampled to the model's 30 fps; it is retargeted from its joints directly, without
      the skeleton regressor (SKR).
TARGET: a ``.ply`` / ``.obj`` mesh or point cloud, an ``.xyz`` or ``.npy`` (V, 3) file, or an
``.npz`` (``read_target``), in T-pose.

Everything is converted on reading to canonical metres and axes (``minretarget.units``).
Frames are read lazily, one at a time, so memory does not grow with the number of frames
(a BVH file is read whole: it is small).
"""
import json
import re
from pathlib import Path
from typing import Iterable, NamedTuple

import numpy as np

from .bodies import shipped_body
from .bvh import read_bvh, resample
from .conventions import FPS
from .formats.mesh import POINT_SUFFIXES, checked_points, read_points
from .formats.npz import NpzFrames, load_npy, load_npz, npz_members
from .sampling import sample_point_clouds
from .skeletons import canonical_world
from .units import CANONICAL, Space, to_canonical
from .validation import as_float32_array

SAMPLE = Path(__file__).parent / "data" / "sample.npz"
MESH_POINTS = 2048     # points drawn on a source mesh's surface a frame (the sample's P)
_NPZ_KEYS = ("points", "source_points")
_TARGET_KEYS = (("target_points", "target_faces"), ("points", "faces"), ("vertices", "faces"))


class Source(NamedTuple):
    """A motion to retarget, opened for one pass over its frames."""
    path: str
    kind: str              # "points": (P, 3) clouds, or "skeleton": (J, 3) joints
    count: int             # T, the number of frames
    fps: float             # frames per second of ``frames``
    frames: Iterable       # frames start..T-1 (``open_source``), canonical metres, float32
    files: tuple = None    # a folder's T frame files, to name them in messages
    space: Space = CANONICAL   # the units and axes its file was read in

    def frame_name(self, index):
        """How messages name frame ``index``: its file (folders), else "walk.npy: frame 3"."""
        return str(self.files[index]) if self.files else f"{self.path}: frame {index}"


def natural_key(name):
    """Sort key for natural order: digit runs compare as numbers (``f2`` < ``f10``)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def frame_files(folder):
    """The point files of a folder (``POINT_SUFFIXES``, not hidden) in natural order."""
    files = [p for p in Path(folder).iterdir()
             if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in POINT_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def _cloud(points, faces, count, rng):
    """One source frame's cloud: ``count`` (None: ``MESH_POINTS``) points drawn area-uniform
    over the surface if it has ``faces``, else a random subset of ``count`` of its points
    (all of them if there are fewer, or if ``count`` is None)."""
    if faces is not None:
        return sample_point_clouds(points, faces, count or MESH_POINTS, rng)
    if count is None or len(points) <= count:
        return points
    return points[rng.choice(len(points), count, replace=False)]


def open_source(path, space, fps=None, points=None, seed=0, start=0, skeleton_map=None):
    """Open a SOURCE (module docstring).

    Args:
        path: folder, ``.npy``, ``.npz``, ``.bvh`` or ``.bvh.gz``.
        space: the source's ``units.Space``.
        fps: the source's frame rate; None: 30 for point clouds, the header's for BVH.
        points: resample every cloud to this many points (a random subset seeded by
            ``seed`` and the frame's index, so frame t is the same whatever frame a pass
            starts from), or None to keep them all; a mesh frame gets this many (None:
            ``MESH_POINTS``) drawn over its surface, seeded alike; not for BVH sources.
        seed: seed of that resampling.
        start: the first frame to yield (a resumed run); ``count`` stays the total.
        skeleton_map: a BVH's {canonical joint: its joint} where its names do not tell
            (``read_skeleton_map``); BVH sources only.
    Returns:
        Source; clouds keep their frame rate, BVH motions come out at 30 fps.
    Raises:
        ValueError naming the file (and frame) for anything unreadable or mis-shaped.
    """
    path = Path(path)
    name = path.name.lower()
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    if name.endswith((".bvh", ".bvh.gz")):
        if points is not None:
            raise ValueError(f"{path}: --points applies to point-cloud sources, not to BVH")
        return _bvh_source(path, space, fps, start, skeleton_map)
    if skeleton_map is not None:
        raise ValueError(f"{path}: --skeleton-map applies to BVH sources")
    files = None
    if path.is_dir():
        files = tuple(frame_files(path))
        if not files:
            raise ValueError(f"{path}: no point files ({', '.join(POINT_SUFFIXES)}) in folder")
        raw = (read_points(f) for f in files[start:])                # (points, faces)
        count = len(files)
    elif name.endswith((".npy", ".npz")):
        if name.endswith(".npy"):
            array = load_npy(path, mmap_mode="r")       # frames are read as they are used
        else:
            array = NpzFrames(path, _npz_key(path))
        _check_frames(path, array.shape, array.dtype)
        raw = ((frame, None) for frame in (array[start:] if isinstance(array, np.ndarray)
                                           else array.frames(start)))
        count = len(array)
    else:
        raise ValueError(f"{path}: SOURCE must be a folder of frames, a .npy/.npz array of "
                         "frames or a .bvh file")

    def frames():
        for index, (cloud, faces) in enumerate(raw, start):
            cloud = _cloud(np.asarray(cloud), faces, points, np.random.default_rng([seed, index]))
            if files is None:       # an array's frames; a folder's files are checked on reading
                try:                # before the units' product spreads an inf over its row
                    as_float32_array(cloud, "source points", (None, 3))
                except ValueError as error:
                    raise ValueError(f"{path}: frame {index}: {error}") from None
            yield to_canonical(cloud, space)

    return Source(str(path), "points", count, float(fps or FPS), frames(), files, space)


def _npz_key(path):
    keys = npz_members(path)
    if len(keys) == 1:
        return keys[0]
    for key in _NPZ_KEYS:
        if key in keys:
            return key
    raise ValueError(f"{path}: cannot read an array of frames: it holds "
                     f"{', '.join(keys) or 'no array'}; expected one array, or one named "
                     f"{' or '.join(_NPZ_KEYS)}")


def _check_frames(path, shape, dtype):
    if len(shape) != 3 or shape[2] != 3 or dtype.kind not in "fiu":
        raise ValueError(f"{path}: expected an array of frames (T, P, 3) of numbers, got "
                         f"{dtype} {shape}")


def read_skeleton_map(path):
    """A ``--skeleton-map`` file: JSON {canonical joint: BVH joint name} -> dict; ValueError
    naming the file if it is not such an object (the names are checked against the BVH by
    ``skeletons.map_skeleton``)."""
    try:
        mapping = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: cannot read the skeleton map: {error}") from None
    if not isinstance(mapping, dict) or not all(isinstance(v, str) for v in mapping.values()):
        raise ValueError(f'{path}: a skeleton map is a JSON object {{"canonical joint": '
                         f'"BVH joint", ...}}, got {json.dumps(mapping)[:80]}')
    return mapping


def _bvh_source(path, space, fps, start, skeleton_map):
    motion = read_bvh(path)
    try:
        motion = resample(motion, fps=FPS, source_fps=fps)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    positions, _ = canonical_world(motion, source=str(path), given=skeleton_map)   # (T, J, 3)
    joints = to_canonical(positions, space)
    return Source(str(path), "skeleton", len(joints), float(FPS), iter(joints[start:]),
                  space=space)


def read_target(path, space):
    """Read a TARGET: (V, 3) float32 canonical T-pose points and (F, 3) int64 faces or None.
    Besides the point files (``formats.mesh.read_points``) and the name of a shipped body
    (``minretarget.bodies``), an ``.npz`` holding
    ``target_points`` (and ``target_faces``: a result or the sample), ``points`` or
    ``vertices`` (and ``faces``), or one (V, 3) array."""
    if not Path(path).exists():                     # the name of a shipped body, or a typo
        points, faces = shipped_body(str(path))
        return to_canonical(points, space), faces
    if Path(path).suffix.lower() != ".npz":
        points, faces = read_points(path)
        return to_canonical(points, space), faces
    keys = npz_members(path)
    points_key, faces_key = next(
        ((p, f) for p, f in _TARGET_KEYS if p in keys),
        (keys[0], None) if len(keys) == 1 else (None, None))
    if points_key is None:
        raise ValueError(f"{path}: holds {', '.join(keys) or 'no array'}; a target .npz holds "
                         "one (V, 3) array, or target_points, points or vertices (with "
                         "target_faces or faces)")
    arrays = load_npz(path, keys=[k for k in (points_key, faces_key) if k in keys])
    points, faces = checked_points(path, arrays[points_key], arrays.get(faces_key))
    return to_canonical(points, space), faces


def load_sample(path=SAMPLE, start=0):
    """The demo's sample: a source clip of point clouds and a target mesh in T-pose.

    Args:
        path: the sample file; start: the first source frame to yield.
    Returns:
        source: Source of (P, 3) clouds, canonical metres.
        target_points: (V, 3) float32; target_faces: (F, 3) int64.
        metadata: dict (what the clip and the bodies are, and their licences).
    """
    with np.load(path, allow_pickle=False) as data:
        target_points = data["target_points"].astype(np.float32)
        target_faces = data["target_faces"].astype(np.int64)
        fps = float(data["fps"])
        metadata = json.loads(str(data["metadata"]))
    clouds = NpzFrames(path, "source_points")
    frames = (np.asarray(cloud, dtype=np.float32) for cloud in clouds.frames(start))
    return (Source(str(path), "points", len(clouds), fps, frames), target_points, target_faces,
            metadata)
