"""Resuming an interrupted ``minretarget retarget``: the run's state, kept beside its outputs.

Files in the output folder while a run goes on (removed when it completes):
    checkpoint.npz    replaced atomically at the start, every ``CHECKPOINT_EVERY`` frames
                      and at Ctrl-C: ``frames_done``; the stream's state after those frames
                      as ``state.*`` arrays (``stages.stream_arrays``: each stage's own,
                      with its version, e.g. ``state.smrm.encoder_hidden``); ``run``,
                      JSON of the inputs and options a resumed run must repeat (``run_record``).
                      Plain arrays: it loads without pickle.
    checkpoint.track  the small per-frame arrays, one float32 record a frame, appended as
                      frames are written: joints (J, 3), rotations (J, 4), root (3,) and
                      source_joints (J, 3), canonical metres. Only the first ``frames_done``
                      records count; the writers of ``result.npz``, ``.glb`` and ``.bvh`` read
                      the motion back from here, so memory stays flat in the stream's length.
    .previous_run/    with ``overwrite``: the files of the run that was in the folder before,
                      kept until the run replacing them completes (``finish_run``), and put
                      back if it fails before its first frame (``abandon_run``).
Order of writes: a frame's files, then its record; records reach the disk (fsync) before a
checkpoint counts them. After any interruption, Ctrl-C, kill or power loss, every frame that
the checkpoint counts is complete on disk; a resumed run starts after it with the saved
state and recomputes the rest exactly (the frames a kill caught after the last checkpoint
are written again, with the same bytes).
"""
import contextlib
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .contacts import FootLock
from .fit import FitSettings
from .conventions import NUM_JOINTS
from .formats.npz import ARCHIVE_ERRORS, load_npz
from .outputs import previous_outputs, remove_outputs
from .smoothing import Smoothing
from .pipeline import PipelineConfig
from .stages import stream_arrays, stream_from_arrays
from .units import CANONICAL
from .weights import flatten_weights

CHECKPOINT, TRACK = "checkpoint.npz", "checkpoint.track"
PREVIOUS_RUN = ".previous_run"
CHECKPOINT_EVERY = 30        # frames (1 s at 30 fps): at most this much work redone after a kill
VERSION = 9          # 2: the state holds the smoothed joints, their speed, the longest leg;
#                      3: and the foot contacts; 4: the mean leg length, not the longest;
#                      5: and the denoiser's (the smoothed and the denoised joints apart);
#                      6: the denoiser's two GRU states (the skeleton's, its mirror image's);
#                      7: the mean source bone lengths (for the rest poses), not the leg's;
#                      8: and the facing check's reference heading and count;
#                      9: each stage's state apart, with its own version (stages.py)
# The fields of a track record, in order, with their shapes.
FIELDS = (("joints", (NUM_JOINTS, 3)), ("rotations", (NUM_JOINTS, 4)), ("root", (3,)),
          ("source_joints", (NUM_JOINTS, 3)))
_SIZES = [int(np.prod(shape)) for _, shape in FIELDS]
RECORD = sum(_SIZES)         # float32 values per frame


class Track:
    """The per-frame arrays of a run in ``checkpoint.track``: appended, then read back.

    Opening keeps the first ``count`` records of an existing file and drops the rest.
    """

    def __init__(self, path, count=0):
        self.path = Path(path)
        size = self.path.stat().st_size if count and self.path.is_file() else 0
        if size < count * RECORD * 4:
            raise ValueError(f"{self.path}: holds fewer than the {count} frames its "
                             "checkpoint counts; the output cannot be resumed (--overwrite "
                             "starts again)")
        self.file = open(self.path, "r+b" if count else "w+b")
        self.file.truncate(count * RECORD * 4)
        self.file.seek(0, os.SEEK_END)
        self.count = count

    def append(self, frame):
        """Add a RetargetedFrame's joints, rotations, root and source joints."""
        record = np.concatenate([np.asarray(getattr(frame, name), np.float32).ravel()
                                 for name, _ in FIELDS])
        self.file.write(record.tobytes())
        self.count += 1

    def sync(self):
        """Put every appended record on the disk."""
        self.file.flush()
        os.fsync(self.file.fileno())

    def records(self):
        """(T, RECORD) float32, every record so far (a read-only map of the file)."""
        self.file.flush()
        if self.count == 0:
            return np.empty((0, RECORD), np.float32)
        return np.memmap(self.path, np.float32, "r", shape=(self.count, RECORD))

    def stacked(self, name):
        """(T, ...) float32 array of one field over every record so far."""
        index = [n for n, _ in FIELDS].index(name)
        start = sum(_SIZES[:index])
        columns = self.records()[:, start:start + _SIZES[index]]
        return np.array(columns).reshape((-1,) + FIELDS[index][1])

    def frames(self):
        """{field: array} of each record so far, read one at a time."""
        return (_split(record) for record in self.records())

    def close(self):
        self.file.close()


def _split(record):
    fields, start = {}, 0
    for (name, shape), size in zip(FIELDS, _SIZES):
        fields[name] = np.array(record[start:start + size]).reshape(shape)
        start += size
    return fields


def _digest(arrays):
    """Hex SHA-256 of a sequence of arrays (their dtype, shape and bytes) and None's."""
    digest = hashlib.sha256()
    for array in arrays:
        if array is None:
            digest.update(b"none")
        else:
            array = np.ascontiguousarray(array)
            digest.update(f"{array.dtype.str}{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()


def source_stamp(source):
    """One short SHA-256 per file of ``source`` (a folder's frame files in order, or the one
    file) of its name, size and modification time: a file rewritten since a run began
    changes its own, as ``make`` would tell, without reading every frame again."""
    stamps = []
    for path in source.files or (source.path,):
        status = os.stat(path)
        line = f"{Path(path).name}\0{status.st_size}\0{status.st_mtime_ns}"
        stamps.append(hashlib.sha256(line.encode()).hexdigest()[:16])
    return stamps


def same_source(then, now, frames_done):
    """Whether a run's source stamps allow resuming after ``frames_done`` frames: a folder's
    frames not yet done may have changed (a bad frame fixed after it stopped the run), those
    done may not; one file (a clip, a BVH) must be as it was."""
    if not (isinstance(then, list) and isinstance(now, list)) or len(then) != len(now):
        return then == now
    return then[:frames_done] == now[:frames_done] if len(now) > 1 else then == now


def run_record(source, target, weights, formats, space, points, seed, config=PipelineConfig(),
               skeleton_map=None, viewpoint=None):
    """What a resumed run must repeat, as a JSON-able dict: the source (its resolved path,
    kind, frame count, rate, units and up axis, a BVH's skeleton map, and its files' sizes
    and times: ``source_stamp``), the target and weights (SHA-256 of their arrays), the
    formats, units, up axis, the resampling, a depth camera's viewpoint, and the pipeline
    (``pipeline.PipelineConfig``: the settings that change the result with these weights and
    this kind of source)."""
    fitted = config.fit_source is not None and source.kind == "points"
    return {"version": VERSION, "source": str(Path(source.path).resolve()),
            "source_kind": source.kind, "frames": source.count, "fps": source.fps,
            # Recorded only when not canonical, so runs from before it match their checkpoints.
            **({"source_space": list(source.space)} if source.space != CANONICAL else {}),
            **({"skeleton_map": skeleton_map} if skeleton_map else {}),
            **({"viewpoint": list(viewpoint)} if viewpoint is not None else {}),
            "source_stamp": source_stamp(source),
            "target_sha256": _digest(target),
            "weights_sha256": _digest(flatten_weights(weights).values()),
            "formats": list(formats), "units": space.units, "up_axis": space.up_axis,
            "points": points, "seed": seed,
            "smoothing": None if config.smoothing is None else list(config.smoothing),
            "foot_lock": None if config.foot_lock is None else list(config.foot_lock),
            "mirror_source": config.mirror_source,
            # Recorded only when it changes the result, so runs from before the refiner and
            # runs with weights that have none still match their checkpoints.
            **({"refine": True} if config.refine and weights.refine is not None else {}),
            **({"denoise": True} if config.denoise and weights.denoise is not None else {}),
            **({"rest_pose": True} if config.rest_pose and weights.rest_pose is not None
               else {}),
            **({"facing_check": True} if config.facing_check and source.kind == "points"
               else {}),
            **({"skr_view": True} if config.skr_view and weights.skr_view is not None
               and viewpoint is not None else {}),
            # Recorded only when on, as the others (skeleton sources are never fitted).
            **({"source_fit": list(config.fit_source)} if fitted else {})}


def save_checkpoint(out_dir, run, stages, state, frames_done, track):
    """Record that ``frames_done`` frames are complete, with the stream's ``state`` after
    them (``stages.StreamState`` of the retargeter's ``stages``; None before the first);
    their track records are synced to disk first."""
    track.sync()
    arrays = {"version": np.array(VERSION), "run": np.array(json.dumps(run, sort_keys=True)),
              "frames_done": np.array(frames_done, np.int64)}
    if state is not None:
        arrays.update({f"state.{key}": value
                       for key, value in stream_arrays(stages, state).items()})
    with atomic_write(Path(out_dir) / CHECKPOINT) as file:
        np.savez(file, **arrays)


# Run record entries that hold a NamedTuple's values, by its fields.
_FIELDS = {"smoothing": Smoothing._fields, "foot_lock": FootLock._fields,
           "source_fit": FitSettings._fields}


def difference(key, then, now):
    """One entry of two run records that differ, for people: "foot_lock max_offset 0.01
    then, 0.1 now", "the target differs (its SHA-256)", "refine off then, on now"."""
    if key == "source_stamp":
        return "the source's files of the frames done changed (their sizes or times)"
    if key.endswith("_sha256"):
        return f"the {key[:-len('_sha256')]} differs (its SHA-256)"
    if key in _FIELDS and isinstance(then, list) and isinstance(now, list):
        if len(then) != len(now):                  # a version with other fields made it
            return f"{key}: {len(then)} settings then, {len(now)} now (another version)"
        return "; ".join(f"{key} {field} {a:g} then, {b:g} now"
                         for field, a, b in zip(_FIELDS[key], then, now) if a != b)

    def shown(value):
        if value is None or isinstance(value, bool):
            return "on" if value else "off"
        return " ".join(map(str, value)) if isinstance(value, list) else str(value)
    return f"{key} {shown(then)} then, {shown(now)} now"


def load_checkpoint(out_dir, run, stages):
    """The checkpoint in ``out_dir``: (frames_done, ``stages.StreamState`` or None), the
    state read for the retargeter's ``stages``.

    Raises:
        ValueError naming the file: unreadable, or made by a run with other inputs or
        options (named, with both values), or a state that does not fit the stages.
    """
    path = Path(out_dir) / CHECKPOINT
    try:
        arrays = load_npz(path)
        saved = json.loads(str(arrays["run"]))
        frames_done = int(arrays["frames_done"])
        if not isinstance(saved, dict):
            raise ValueError(f"its run record is {type(saved).__name__}, not a dict")
    except ARCHIVE_ERRORS as error:
        raise ValueError(f"{path}: unreadable checkpoint ({error}); the output cannot be "
                         "resumed (--overwrite starts again)") from None
    # Over both records' keys: an option recorded only when on (refine, denoise, rest_pose,
    # facing_check) may be off.
    differences = [difference(key, saved.get(key), run.get(key))
                   for key in dict.fromkeys([*run, *saved]) if saved.get(key) != run.get(key)
                   and not (key == "source_stamp"
                            and same_source(saved.get(key), run.get(key), frames_done))]
    if differences:
        raise ValueError(f"{path}: this output was started with other inputs or options "
                         f"({'; '.join(differences)}); resume with the same ones, or use "
                         "--overwrite to start again")
    if not 0 <= frames_done <= run["frames"]:
        raise ValueError(f"{path}: frames_done {frames_done} is not in [0, {run['frames']}]")
    if frames_done == 0:
        return 0, None
    try:
        state = stream_from_arrays(stages, {key[len("state."):]: value
                                            for key, value in arrays.items()
                                            if key.startswith("state.")})
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: bad saved state: {error}") from None
    if state.frames_seen != frames_done:
        raise ValueError(f"{path}: its state has seen {state.frames_seen} frames, not "
                         f"{frames_done}")
    return frames_done, state


def prepare_out_dir(out_dir, run, stages, resume=False, overwrite=False):
    """Make ``out_dir`` ready for a run; returns (frames_done, state) to start from.

    A fresh run refuses a folder that holds a run's files (frames, results, a checkpoint),
    so that nothing is lost by a repeated command. ``overwrite`` moves them (only them;
    other files stay) into ``PREVIOUS_RUN`` there, until the new run completes; if that
    folder is there already, an earlier replacement failed midway, and its files are
    deleted instead, the run it was replacing kept. ``resume`` continues the run of the
    checkpoint there (``load_checkpoint``), or starts one if the folder holds none of a
    run's files. Either way the temporaries of writes that a kill interrupted are removed.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir}: is a file; --out names the folder the outputs go into")
    previous = previous_outputs(out_dir)
    if overwrite:
        _set_aside(out_dir, previous)
    elif previous and not (resume and CHECKPOINT in previous):
        listed = ", ".join(previous[:3]) + (", ..." if len(previous) > 3 else "")
        if CHECKPOINT in previous:
            raise ValueError(f"{out_dir}: holds an interrupted run ({listed}): add --resume "
                             "to continue it, or --overwrite to start again")
        raise ValueError(f"{out_dir}: already holds the files of a finished run ({listed}): "
                         "choose another --out, or add --overwrite to replace them"
                         + (" (there is no checkpoint to --resume)" if resume else ""))
    remove_outputs(out_dir, temporaries_only=True)
    return load_checkpoint(out_dir, run, stages) if resume and previous else (0, None)


def _set_aside(out_dir, names):
    kept = out_dir / PREVIOUS_RUN
    if kept.is_dir() and CHECKPOINT in names:
        remove_outputs(out_dir)             # an unfinished replacement: keep what it replaced
        return
    shutil.rmtree(kept, ignore_errors=True)  # left by a kill in finish_run: stale
    if names:
        kept.mkdir()
        for name in names:
            os.replace(out_dir / name, kept / name)


def finish_run(out_dir):
    """The run in ``out_dir`` is complete: delete the run it replaced, then its checkpoint
    (in this order, so that a kill between the two leaves a resumable run)."""
    shutil.rmtree(Path(out_dir) / PREVIOUS_RUN, ignore_errors=True)
    for name in (CHECKPOINT, TRACK):
        with contextlib.suppress(FileNotFoundError):
            (Path(out_dir) / name).unlink()


def abandon_run(out_dir, created=False):
    """The run in ``out_dir`` failed before its first frame was complete: delete its files
    (every run file there is its: its checkpoint, a frame file written before the failure)
    and put back the run it was replacing, if any; a folder the run ``created`` goes too."""
    remove_outputs(out_dir)
    kept = Path(out_dir) / PREVIOUS_RUN
    if kept.is_dir():
        for path in kept.iterdir():
            os.replace(path, Path(out_dir) / path.name)
        kept.rmdir()
    if created:
        Path(out_dir).rmdir()
