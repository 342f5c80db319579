"""Writing a retargeted stream to files, frame by frame, in the formats asked for.

    with open_writers(out_dir, ("ply", "glb"), target, count, fps, space, track) as write:
        for frame in frames:          # RetargetedFrame, canonical metres
            write(frame)

Formats (``FORMATS``), lengths in the user's units and axes (``space``) except glTF's:
    ply, obj   ``frame_000000.ply`` ...: the posed target, its faces and vertex order kept
               (a point cloud when the target has no faces).
    npz        ``result.npz``, every array (``npz_keys``); ``vertices`` is streamed into the
               archive as frames come, so it is never held in memory whole.
    glb        ``result.glb``: the rigged, animated target (``minretarget.formats.glb``);
               glTF fixes metres and +Y up, so it ignores ``space``.
    bvh        ``result.bvh``: the skeleton motion (``minretarget.skeletons.rig_to_bvh``).
Across frames only joints, rotations, root and source joints are kept (J * 13 floats a
frame), in a file (``checkpoint.Track``), for npz, glb and bvh. Every file is written
atomically: an interrupted run leaves no ``result.*`` and only complete frame files.
"""
import contextlib
import re
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .bvh import write_bvh
from .conventions import JOINT_NAMES, PARENTS
from .formats.glb import write_glb
from .formats.mesh import write_mesh
from .formats.npz import NpzWriter
from .skeletons import rig_to_bvh
from .units import from_canonical, rotations_from_canonical

FORMATS = ("ply", "obj", "npz", "glb", "bvh")


def parse_formats(text):
    """"ply,glb" -> ("ply", "glb"); ValueError for an empty list or an unknown name."""
    formats = tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ValueError(f"unknown output format(s) {', '.join(unknown) or '(none)'}; choose "
                         f"from {','.join(FORMATS)}")
    return formats


def frame_name(index, suffix):
    """``frame_000042.ply``: six digits or more, so names sort in frame order."""
    return f"frame_{index:06d}.{suffix}"


DEMO_MARK = ".minretarget_demo"    # in a folder whose run is a demo's, which a demo replaces

# The files a run writes (``checkpoint`` adds its own two; the demo its mark), and the
# temporary names that ``atomic_write`` gives them until they are complete.
OUTPUT_NAME = re.compile(r"frame_\d{6,}\.(ply|obj)|result\.(npz|glb|bvh)"
                         r"|checkpoint\.(npz|track)|" + re.escape(DEMO_MARK))
_TEMPORARY_NAME = re.compile(r"\.(?P<name>.+)\.[^.]+\.tmp")


def previous_outputs(out_dir):
    """Sorted names of the files in ``out_dir`` that a run writes (``OUTPUT_NAME``)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return []
    return sorted(p.name for p in out_dir.iterdir() if OUTPUT_NAME.fullmatch(p.name))


def remove_outputs(out_dir, temporaries_only=False):
    """Delete the files of ``previous_outputs`` (or only the temporaries of an interrupted
    run's writes); other files in ``out_dir`` are left alone."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return
    for path in out_dir.iterdir():
        temporary = _TEMPORARY_NAME.fullmatch(path.name)
        name = temporary.group("name") if temporary else None if temporaries_only else path.name
        if name is not None and OUTPUT_NAME.fullmatch(name) and path.is_file():
            path.unlink()


@contextlib.contextmanager
def _mesh_frames(out_dir, suffix, target, space, start):
    index = start

    def write(frame):
        nonlocal index
        write_mesh(out_dir / frame_name(index, suffix), from_canonical(frame.vertices, space),
                   target.faces)
        index += 1

    yield write


def npz_keys(target, fps, space, track):
    """The arrays of ``result.npz`` besides ``vertices`` (T, V, 3), user units and axes:
    joints (T, J, 3), rotations (T, J, 4) local quaternions (w, x, y, z) in the user's axes,
    root (T, 3), source_joints (T, J, 3); target_points (V, 3), target_faces (F, 3) int64
    (F = 0 for a point cloud), target_tpose_joints (J, 3), target_skin_weights (V, J);
    fps, joint_names (J,), parents (J,), units ("m", "cm" or "mm"), up_axis ("y" or "z")."""
    faces = np.empty((0, 3), np.int64) if target.faces is None else target.faces
    return {
        "joints": from_canonical(track.stacked("joints"), space),
        "rotations": rotations_from_canonical(track.stacked("rotations"), space),
        "root": from_canonical(track.stacked("root"), space),
        "source_joints": from_canonical(track.stacked("source_joints"), space),
        "target_points": from_canonical(target.points, space),
        "target_faces": faces.astype(np.int64),
        "target_tpose_joints": from_canonical(target.tpose_joints, space),
        "target_skin_weights": target.skin_weights,
        "fps": np.array(float(fps)), "joint_names": np.array(JOINT_NAMES),
        "parents": np.array(PARENTS, np.int64),
        "units": np.array(space.units), "up_axis": np.array(space.up_axis),
    }


@contextlib.contextmanager
def _npz(path, target, count, fps, space, track, past_vertices):
    with atomic_write(path) as file, NpzWriter(file) as archive:
        with archive.frames("vertices", (count, len(target.points), 3), np.float32) as vertices:
            for posed in past_vertices:
                vertices(from_canonical(posed, space))
            yield lambda frame: vertices(from_canonical(frame.vertices, space))
        for key, array in npz_keys(target, fps, space, track).items():
            archive.add(key, array)


@contextlib.contextmanager
def _glb(path, target, fps, track):
    yield lambda frame: None
    write_glb(path, target.points, target.faces, target.skin_weights, target.tpose_joints,
              track.stacked("rotations"), track.stacked("root"), fps)


@contextlib.contextmanager
def _bvh(path, target, fps, space, track):
    yield lambda frame: None
    motion = rig_to_bvh(from_canonical(target.tpose_joints, space),
                        rotations_from_canonical(track.stacked("rotations"), space),
                        from_canonical(track.stacked("root"), space), 1.0 / fps)
    write_bvh(path, motion)


@contextlib.contextmanager
def open_writers(out_dir, formats, target, count, fps, space, track, past_vertices=()):
    """Open a writer per format in ``out_dir`` (module docstring).

    Args:
        out_dir: output folder, created if needed.
        formats: names from ``FORMATS``.
        target: ``retargeter.Target`` (canonical metres).
        count: T, the number of frames of the whole motion (the npz header needs it).
        fps: frames per second, for glb and bvh timing and the npz.
        space: ``units.Space`` of the outputs.
        track: ``checkpoint.Track`` that keeps the motion's small arrays; it may already
            hold the first frames (a resumed run), whose frame files exist.
        past_vertices: the (V, 3) canonical vertices of those first frames, for the npz
            (iterated only when npz is written).
    Yields:
        ``write(frame)`` for each further RetargetedFrame in order: its files, then its
        track record; the files that need the whole motion are written when the block
        ends without error.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        writers = []
        for name in formats:
            if name in ("ply", "obj"):
                writer = _mesh_frames(out_dir, name, target, space, track.count)
            elif name == "npz":
                writer = _npz(out_dir / "result.npz", target, count, fps, space, track,
                              past_vertices)
            elif name == "glb":
                writer = _glb(out_dir / "result.glb", target, fps, track)
            elif name == "bvh":
                writer = _bvh(out_dir / "result.bvh", target, fps, space, track)
            else:
                raise ValueError(f"unknown output format {name!r}; choose from {FORMATS}")
            writers.append(stack.enter_context(writer))
        writers.append(track.append)

        def write(frame):
            for writer in writers:
                writer(frame)

        yield write
