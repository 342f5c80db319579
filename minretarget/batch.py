"""``minretarget batch``: many motions onto many bodies, on every core or on a Ray cluster.

    minretarget batch JOB --out DIR [--workers N] [--ray auto|ADDRESS] [--resume]

JOB is TOML (Python >= 3.11) or JSON; its relative paths are relative to its own folder:

    sources = ["mocap/*.bvh", "captures/take_01", "walk.npz"]  # files, folders of frames, globs
    targets = ["bodies/*.ply", "heavy_woman"]     # T-pose bodies, or shipped bodies' names
    pairs = [{source = "08_01", target = "anna", options = {source_units = "cm"}}]  # optional
    [options]                                                   # every pair's (OPTIONS)
    format = "ply,npz,glb,bvh"
    foot_leash = 0.1

A source or target is named by its file or folder name without the suffix (a shipped body by
its name); names must be unique. Without ``pairs`` every source goes onto every target.
``options`` are those of ``minretarget retarget`` but ``--out``, ``--resume`` and
``--overwrite`` (``OPTIONS``, read by retarget's own parser, ``cli.add_retarget_arguments``):
``--source-units cm`` is ``source_units = "cm"``, ``--force`` is ``force = true``,
``--no-smoothing`` is ``smoothing = false``; ``weights`` and ``skeleton_map`` are paths,
relative to the job file. A pair's own ``options`` override the job's. The whole job is
checked before any work and every problem is listed at once: files exist, options valid,
weights load, and every source's frame 0 and every target read as ``retarget`` reads them
(``cli.source_of``, ``cli.target_of``), in the units and up axis given or told from the body,
one that is then not a person's size or lies along its up axis refused unless ``force``.

Each pair runs as ``minretarget retarget SOURCE TARGET --out DIR/<target>/<source>`` with its
options would, writing the same bytes there (``cli.retarget_to_files``, its checkpoints
included), then a done-marker, ``done.json`` (its ``summary.json`` entry, with the lines
``retarget`` prints about each file's units and up axis and its warnings, options written as
a job's keys). Pairs run longest first on a pool of
worker processes (``--workers``, default one per core) or of Ray actors (``--ray``), each
with one BLAS and numba thread, each keeping the weights and every target's set-up (skeleton
and skinning weights, keyed by the target's content) between pairs; of the pairs equally
long, a worker takes one whose target it has set up, else one whose target no worker has.
The batch's process reads each pair's target as it hands the pair out (``with_target``), so
that a worker needs no mesh reader. A
failing pair (a bad
file, a NaN frame) is recorded with its reason and the others go on; a pair whose worker dies
is run again (``ATTEMPTS`` in all), from its checkpoint. ``--resume`` skips the pairs done and
resumes the others from their checkpoints; without it a DIR holding any pair's folder is
refused. ``DIR/summary.json`` lists every pair's status, frames, seconds and outputs; the
command exits with status 0 only if every pair is done.
"""
import argparse
import atexit
import concurrent.futures
import contextlib
import ctypes
import gc
import glob
import hashlib
import io
import itertools
import json
import multiprocessing
import os
import queue
import re
import signal
import sys
import time
import warnings
from collections import Counter
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np

from .atomic import atomic_write
from .bodies import body_names
from .checkpoint import CHECKPOINT
from .cli import (add_retarget_arguments, blas_threads, int_at_least, pipeline_config,
                  retarget_to_files, set_target, source_of, target_of)
from .extras import MissingExtra, require
from .outputs import frame_name, parse_formats, previous_outputs
from .retargeter import Retargeter
from .units import make_space
from .validation import InputWarning
from .weights import load_weights

DONE = "done.json"               # in a pair's folder once its outputs are complete
SUMMARY = "summary.json"
ATTEMPTS = 3                     # runs of a pair whose worker dies, before it counts as failed
REPORT_EVERY = 0.5               # seconds between a worker's progress reports


class _Parser(argparse.ArgumentParser):
    """``minretarget retarget``'s arguments whose errors raise ValueError (argparse's message),
    so that a job lists them all."""

    def error(self, message):
        raise ValueError(message)


PARSER = _Parser(prog="minretarget retarget", add_help=False)
add_retarget_arguments(PARSER)
SET_BY_BATCH = ("out", "resume", "overwrite")       # and SOURCE, TARGET
PATHS = ("weights", "skeleton_map")                 # relative to the job file


def _switch(action):
    """What a job's key is set to to give a flag: True (``--force``), False (``--no-X``), or
    None for an option that takes a value."""
    return None if action.nargs != 0 else not action.dest.startswith("no_")


def _key(action):
    """A ``retarget`` option's key in a job: ``source_units``, ``force``, ``smoothing``."""
    return action.dest.removeprefix("no_") if _switch(action) is False else action.dest


# Key -> ``retarget``'s argparse action, for each of its options (argparse lists them nowhere
# public): ``--fps`` is ``fps``, ``--up-axis`` is ``up_axis``, ``--force`` is ``force = true``,
# ``--no-X`` is ``X = false``. A value of None (JSON's null) is the option's default.
OPTIONS = {_key(action): action for action in PARSER._actions
           if action.option_strings and action.dest not in SET_BY_BATCH}
_FLAGS = {flag: action for action in OPTIONS.values() for flag in action.option_strings}


def in_job_terms(message):
    """``message`` (``retarget``'s or its parser's) with its options written as a job's keys:
    ``--source-units cm`` as ``source_units = "cm"``, ``--force`` as ``force = true``,
    ``argument --fps: ...`` as ``fps: ...``; the batch's own (``--resume``) kept."""
    def as_key(match):
        action, value = _FLAGS.get(match[2]), match[3]
        if action is None:
            return match[0]
        if _switch(action) is None and value in (action.choices or ()):
            return f'{_key(action)} = "{value}"'
        written = _key(action) if _switch(action) is None else (
            f"{_key(action)} = {str(_switch(action)).lower()}")
        return written + (f" {value}" if value else "")

    return re.sub(r"(argument )?(?<![\w-])(--[a-z][a-z-]*)(?: (\w+))?", as_key, message)


def _argv(options):
    """``retarget``'s command-line arguments for a job's ``options`` {key: value}."""
    argv = []
    for key, value in options.items():
        action = OPTIONS[key]
        flag, switch = action.option_strings[0], _switch(action)
        if value is None:
            continue
        if switch is not None:
            if not isinstance(value, bool):
                raise ValueError(f"{key}: must be true or false, got {value!r}")
            argv += [flag] if value is switch else []
        elif key == "format" and isinstance(value, list) and all(
                isinstance(item, str) for item in value):
            argv.append(f"{flag}={','.join(value)}")
        elif isinstance(value, (str, int, float)) and not isinstance(value, bool):
            argv.append(f"{flag}={value}")
        else:
            raise ValueError(f"{key}: must be a string or a number, got {value!r}")
    return argv


def parse_options(source, target, out, options):
    """``retarget``'s parsed arguments (argparse.Namespace) for ``SOURCE TARGET --out OUT`` and
    a job's ``options``; ValueError naming the option, in a job's terms."""
    try:
        return PARSER.parse_args([*_argv(options), "--out", out, "--", source, target])
    except ValueError as error:
        raise ValueError(in_job_terms(str(error))) from None


def _as_options(args):
    """{key: value} of every option in ``args`` (``parse_options``'s), defaults included."""
    return {key: getattr(args, action.dest) if _switch(action) is not False else
            not getattr(args, action.dest) for key, action in OPTIONS.items()}


class Pair(NamedTuple):
    """One source onto one target: everything a worker needs to run it."""
    name: str          # "<target>/<source>", its folder under the job's output folder
    source: str        # absolute path of the source motion
    target: str        # absolute path of the target body, or a shipped body's name
    options: dict      # every key of OPTIONS (paths absolute), as ``parse_options`` takes
    frames: int        # T, the source's frame count (30 fps for BVH)
    folder: str        # absolute path of its output folder
    target_read: "TargetRead | None" = None     # its target, read as it is handed out


class TargetRead(NamedTuple):
    """A pair's target as ``cli.target_of`` read it in the batch's process (``with_target``),
    with what that read printed and warned, for the worker to use instead of reading it."""
    points: np.ndarray     # (V, 3) float32 canonical points
    faces: "np.ndarray | None"
    space: object          # its units.Space
    printed: str           # the lines it printed (its units and up axis)
    warned: list           # [(warning category, message)]


class JobError(ValueError):
    """A job that cannot run; ``problems`` lists every reason found."""

    def __init__(self, job, problems):
        self.problems = problems
        super().__init__(f"{job}: {len(problems)} problem(s):\n  " + "\n  ".join(problems))


def check_options(raw, where, folder, base=None):
    """``base`` (a job's options; None: none) updated with the options table ``raw``, its
    paths taken from ``folder``, each value checked by ``retarget``'s parser alone (a bad one
    left out), then those together: (options, [problems])."""
    options = dict(base or {})
    if not isinstance(raw, dict):
        return options, [f"{where}: must be a table of options, got {raw!r}"]
    problems = []
    for key, value in raw.items():
        if key not in OPTIONS:
            problems.append(f"{where}: unknown option {key!r} (options: {', '.join(OPTIONS)})")
            continue
        if key in PATHS and isinstance(value, str):
            value = str(folder / value)
        try:
            parse_options("source", "target", "out", {key: value})
        except ValueError as error:
            problems.append(f"{where}: {error}")
        else:
            options[key] = value
    clash = _clash(options)                     # e.g. foot_leash with foot_lock = false
    if raw and clash and not _clash(base or {}):    # said once, where it arises
        problems.append(f"{where}: {clash}")
    return options, problems


def _clash(options):
    """Why options each valid alone are refused together, or None."""
    try:
        parse_options("source", "target", "out", options)
    except ValueError as error:
        return str(error)
    return None


def _read_table(path):
    """The job file as a dict (TOML or JSON, by suffix)."""
    text = path.read_bytes()
    if path.suffix.lower() == ".json":
        return json.loads(text)
    if path.suffix.lower() != ".toml":
        raise ValueError("a job file must end in .toml or .json")
    try:
        import tomllib
    except ImportError:
        raise ValueError("TOML job files need Python >= 3.11: write it as JSON") from None
    return tomllib.loads(text.decode("utf-8"))


def _name(path):
    """A source's or target's name: its file or folder name without the suffix."""
    return path.name if path.is_dir() else Path(path.name.removesuffix(".gz")).stem


def _expand(entries, key, base, problems, bodies=()):
    """{name: absolute path, or a shipped body's name} of a job's ``sources`` or ``targets``
    (paths, globs, and for targets the names in ``bodies``)."""
    if not isinstance(entries, list) or not entries:
        problems.append(f"{key}: must be a non-empty list of paths or glob patterns")
        return {}
    found = {}
    for entry in entries:
        if not isinstance(entry, str):
            problems.append(f"{key}: {entry!r} is not a path")
            continue
        pattern, is_glob = base / entry, any(c in entry for c in "*?[")
        if is_glob:
            paths = [Path(p) for p in sorted(glob.glob(str(pattern), recursive=True))]
        else:
            paths = [pattern] if pattern.exists() else []
        places = [(_name(path), path.resolve()) for path in paths]
        if not paths and not is_glob and entry in bodies:
            places = [(entry, entry)]       # read by name, as retarget reads it
        elif not paths:
            problems.append(f"{key}: {entry}: " + (
                "matches nothing" if is_glob else "no such file or folder" + (
                    f", nor a shipped body ({', '.join(bodies)})" if bodies else "")))
        for name, place in places:
            if name in found and found[name] != place:
                problems.append(f"{key}: {found[name]} and {place} have the same name "
                                f"{name!r}: rename one")
            found[name] = place
    return found


def _pairs(raw, sources, targets, options, folder, problems):
    """[(source name, target name, options)] of the job's ``pairs``, or every combination;
    ``folder``: the job file's."""
    if raw is None:
        return [(s, t, options) for t in targets for s in sources]
    if not isinstance(raw, list):
        problems.append("pairs: must be a list of tables {source, target, options}")
        return []
    pairs = []
    for index, pair in enumerate(raw):
        where = f"pairs[{index}]"
        if not isinstance(pair, dict) or set(pair) - {"source", "target", "options"}:
            problems.append(f"{where}: must be a table of source, target and options, "
                            f"got {pair!r}")
            continue
        pair_options, found = check_options(pair.get("options", {}), f"{where}: options",
                                            folder, options)
        problems += found
        for key, names in (("source", sources), ("target", targets)):
            if pair.get(key) not in names:
                problems.append(f"{where}: {key} {pair.get(key)!r} is not a name in "
                                f"{key}s ({', '.join(sorted(names)) or 'none'})")
        pairs.append((pair.get("source"), pair.get("target"), pair_options))
    named = Counter((s, t) for s, t, _ in pairs)
    problems += [f"pairs: {s} onto {t} is listed {n} times" for (s, t), n in named.items()
                 if n > 1]
    return pairs


def read_job(path, out_dir):
    """Check a job file whole and list its pairs, longest first.

    Args:
        path: the job's ``.toml`` or ``.json`` (module docstring).
        out_dir: the job's output folder; pair folders are ``out_dir/<target>/<source>``.
    Returns:
        [Pair], sorted by frame count, most first (ties in the job's order).
    Raises:
        JobError listing every problem found: the file, unknown keys and options, bad option
        values, missing paths, duplicate names, sources and targets that do not read or whose
        units check fails (without ``force``), weights that do not load.
    """
    path, out_dir = Path(path), Path(out_dir).resolve()
    try:
        job = _read_table(path)
    except (OSError, ValueError) as error:       # json and tomllib errors are ValueErrors
        raise JobError(path, [str(error)]) from None
    if not isinstance(job, dict):
        raise JobError(path, ["must be a table of sources, targets, pairs and options"])
    problems = [f"unknown key {key!r} (keys: sources, targets, pairs, options)"
                for key in job if key not in ("sources", "targets", "pairs", "options")]
    base = path.resolve().parent
    sources = _expand(job.get("sources"), "sources", base, problems)
    targets = _expand(job.get("targets"), "targets", base, problems, body_names())
    options, found = check_options(job.get("options", {}), "options", base)
    problems += found
    listed = _pairs(job.get("pairs"), sources, targets, options, base, problems)
    if problems:          # reading files under options that do not parse would only add noise
        raise JobError(path, problems)
    pairs = _read_files(listed, sources, targets, out_dir, problems)
    if problems:
        raise JobError(path, list(dict.fromkeys(problems)))
    return sorted(pairs, key=lambda pair: -pair.frames)


def _read_files(listed, sources, targets, out_dir, problems):
    """[Pair] of the (source name, target name, options) ``listed`` whose weights load and
    whose source and target read as ``retarget`` reads them (each once per options); the
    others' problems are added to ``problems``."""
    read, pairs = {}, []           # (what, its options) -> (result, error or None)
    for source, target, options in listed:
        name = f"{target}/{source}"
        args = parse_options(str(sources[source]), str(targets[target]), str(out_dir / name),
                             options)
        known = json.dumps(options, sort_keys=True)
        checks = {("weights", args.weights): lambda args: load_weights(args.weights),
                  (f"source {source}", known): lambda args: source_of(args)[1],     # T
                  (f"target {target}", known): target_of}
        for key, reader in checks.items():
            if key not in read:
                read[key] = _quietly(reader, args)
                if read[key][1] is not None:
                    problems.append(f"{key[0]}: {read[key][1]}")
        if all(read[key][1] is None for key in checks):
            pairs.append(Pair(name, str(sources[source]), str(targets[target]),
                              _as_options(args), read[f"source {source}", known][0],
                              str(out_dir / name)))
    return pairs


def _quietly(read, args):
    """``read(args)`` without the lines it prints or the warnings it gives: (its result,
    None), or (None, its error in a job's terms)."""
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        try:
            return read(args), None
        except (OSError, ValueError) as error:
            return None, in_job_terms(str(error))


# --- a worker: one process (or Ray actor), pairs one after another ---------------------------

_WEIGHTS = {}      # weights path (None: the shipped ones) -> Weights, loaded once per worker
_TARGETS = {}      # (weights path, refine, mirror_target, target content hash)
                   # -> (tpose_joints, skin_weights, leg_length)
_WARMED = set()    # (weights path, target hash, config, skeleton) of the warm-ups done
_REPORT = [None]   # report((pair name, frames done)) to the batch, or None


def start_worker(report=None):
    """Set up a worker process: one BLAS and one numba thread (the cores go to the workers),
    and where progress goes (``report((pair name, frames done))``). numba's first, as setting
    its threads loads its threading layer (OpenMP's libgomp here), which the limit then
    reaches too: every thread pool that threadpoolctl sees in a worker says 1 thread."""
    numba.set_num_threads(1)
    require("threadpoolctl", "minretarget batch").threadpool_limits(1)
    _REPORT[0] = report


def start_local_worker(report):
    """``start_worker`` in a process of the local pool, which on Linux the kernel kills when
    the batch process dies: a killed batch leaves no worker writing into a pair that a
    ``--resume`` runs again. At its exit the garbage collector skips the objects it holds:
    the interpreter's collections over numba's and the weights' objects slow a worker's
    exit, which the batch waits for, and free nothing that has to be (its files are closed
    by then; the time it took: docs/runtime_notes.md)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)       # PR_SET_PDEATHSIG
    atexit.register(gc.freeze)
    start_worker(report)


def _content_hash(*arrays):
    """Hex SHA-256 of arrays' bytes (and None's), to know a target by its content."""
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(b"none" if array is None else np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


class _WorkerRetargeter(Retargeter):
    """A worker's Retargeter, whose ``warm_up`` runs once per worker for each weights file,
    target, pipeline and kind of source. ``cli.retarget_to_files`` warms up every stream: it
    loads the kernels (``minretarget retarget`` pays that once, in its one stream), then
    retargets two frames of the target's own points, which change nothing after the stream's
    restart (``Retargeter.reset``); the later pairs skip those two frames (with the
    ``fitted`` preset, 0.07 - 0.10 s of each pair: docs/batch.md)."""

    warm_key = None          # (weights path, target content hash), set by ``_set_target``

    def warm_up(self, skeleton=False):
        if self.target is None or self.warm_key is None:
            return super().warm_up(skeleton)
        key = (*self.warm_key, self.config, bool(skeleton))
        if key in _WARMED:
            self.reset()                    # where warm_up leaves the stream: at its start
        else:
            super().warm_up(skeleton)
            _WARMED.add(key)
        return None


def _retargeter(args):
    """A Retargeter for a pair's parsed options, as ``minretarget retarget`` makes it, with
    the worker's copy of its weights (a ``_WorkerRetargeter``)."""
    if args.weights not in _WEIGHTS:
        _WEIGHTS[args.weights] = load_weights(args.weights)
    return _WorkerRetargeter(_WEIGHTS[args.weights], pipeline_config(args), warn=False)


def _set_target(retargeter, args, points, faces, space):
    """``cli.set_target`` (``cli.target_of``'s target) with its skeleton, skinning weights and
    legs' length computed once per worker for each content, weights, and the pipeline's
    ``refine`` and ``mirror_target`` (all they depend on; a pair's ``preset`` sets both)."""
    content = _content_hash(points, faces)
    config = retargeter.config
    key = (args.weights, config.refine, config.mirror_target, content)
    set_target(retargeter, points, faces, args.target, space,
               *_TARGETS.get(key, (None, None, None)))
    target = retargeter.target
    _TARGETS[key] = target.tpose_joints, target.skin_weights, target.leg_length
    retargeter.warm_key = args.weights, content


def _reporting(open_at, name):
    """``open_at`` whose Sources report the pair's progress (``_reported``)."""
    def reporting(first):
        source = open_at(first)
        return source._replace(frames=_reported(source.frames, first, name))
    return reporting


def _reported(frames, first, name):
    """``frames`` (a Source's, from frame ``first``), reporting progress now and then."""
    report, last = _REPORT[0], time.monotonic()
    for done, frame in enumerate(frames, first + 1):
        yield frame
        if report is not None and time.monotonic() - last > REPORT_EVERY:
            report((name, done))
            last = time.monotonic()


def output_names(formats, count):
    """The files a run of ``count`` frames writes: ``["frame_000000.ply .. ...", ...]``."""
    names = [f"{frame_name(0, f)} .. {frame_name(count - 1, f)}" for f in formats
             if f in ("ply", "obj")]
    return names + [f"result.{f}" for f in formats if f not in ("ply", "obj")]


def spec(pair):
    """What a pair's done-marker must match for ``--resume`` to skip it."""
    return {"source": pair.source, "target": pair.target,
            "options": json.loads(json.dumps(pair.options))}


def _entry(pair, status, **fields):
    """A pair's summary entry (``run_pair``)."""
    return {"pair": pair.name, **spec(pair), "frames": pair.frames, "status": status, **fields}


def with_target(pair):
    """``pair`` with its target read here as ``cli.target_of`` reads it, and what that printed
    and warned (``TargetRead``): the batch's process has read every target in the job's
    check (and so imported the mesh reader, trimesh), and a worker given its pairs' targets
    does not import it (0.4 s of each worker's start, for a few milliseconds here a pair).
    Read as the pair is handed out, so that only the pairs in flight hold their points.
    A target that does not read now is left to the worker, which fails the pair with the
    reason."""
    said = io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(said):
        warnings.simplefilter("always", InputWarning)
        try:
            read = target_of(parse_options(pair.source, pair.target, pair.folder,
                                           pair.options))
        except Exception:       # noqa: BLE001  (the worker's read fails it with the reason)
            return pair
    return pair._replace(target_read=TargetRead(
        *read, said.getvalue(), [(w.category, str(w.message)) for w in caught]))


def _target(args, read):
    """``cli.target_of(args)``, or the same from ``read`` (a ``TargetRead``, or None): its
    lines printed and its warnings given again, as that read gave them."""
    if read is None:
        return target_of(args)
    sys.stdout.write(read.printed)
    for category, message in read.warned:
        warnings.warn(message, category, stacklevel=2)
    return read.points, read.faces, read.space


def run_pair(pair):
    """Run one pair into its folder as ``minretarget retarget`` would (``cli.target_of``,
    ``cli.source_of``, ``cli.retarget_to_files``) and mark it done (module docstring); never
    raises for the pair's own faults (a stop, Ctrl-C, raises KeyboardInterrupt after a
    checkpoint).

    Returns:
        its summary entry: {"pair", "source", "target", "options", "frames", "status":
        "done" or "failed", "outputs" (file names in its folder), "seconds", "read_as" (the
        lines retarget prints about each file's units and up axis), "warnings"; "error" when
        failed}.
    """
    start = time.perf_counter()
    formats = parse_formats(pair.options["format"])
    entry = _entry(pair, "done", outputs=output_names(formats, pair.frames))
    folder, said = Path(pair.folder), io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(said):
        warnings.simplefilter("always", InputWarning)
        try:
            args = parse_options(pair.source, pair.target, pair.folder, pair.options)
            with blas_threads(args.threads):
                retargeter = _retargeter(args)
                _set_target(retargeter, args, *_target(args, pair.target_read))
                open_at, _, settings = source_of(args)
                # A checkpoint: the pair was cut short (a killed worker or batch), go on from
                # it; else any files there are a killed run's from before its first checkpoint.
                resume = CHECKPOINT in previous_outputs(folder)
                for stale in folder.glob(f".{DONE}.*.tmp"):     # a kill while marking it done
                    stale.unlink(missing_ok=True)
                retarget_to_files(retargeter, _reporting(open_at, pair.name), folder, formats,
                                  make_space(args.out_units, args.out_up), settings,
                                  resume=resume, overwrite=not resume, progress=False)
        except Exception as error:      # noqa: BLE001  (a pair's fault must not stop the batch)
            expected = isinstance(error, (ValueError, OSError, MemoryError))
            entry.update(status="failed", outputs=[], error=in_job_terms(str(error)) if expected
                         else f"internal error: {type(error).__name__}: {error}")
    entry.update(seconds=round(time.perf_counter() - start, 3),
                 read_as=said.getvalue().splitlines(),
                 warnings=[in_job_terms(str(w.message)) for w in caught
                           if issubclass(w.category, InputWarning)])
    if entry["status"] == "done":
        with atomic_write(folder / DONE) as file:
            file.write(json.dumps(entry, indent=1).encode())
    return entry


# --- the pools: local processes or Ray actors, pairs handed out as workers free up ----------

def schedule(pairs, slots, submit, lost, drain):
    """Run ``pairs`` in order, one at a time on each of ``slots``; yield their summary
    entries (with ``attempts``) as they end.

    Args:
        pairs: [Pair], longest first: a slot that frees starts one of the longest waiting,
            one whose target its worker has set up where it can (``_pick``).
        slots: the workers, each given one pair at a time.
        submit: ``submit(slot, pair)`` -> a concurrent.futures.Future of ``run_pair(pair)``.
        lost: the exception type(s) of a Future whose worker died: its pair runs again,
            from its checkpoint, first in line, ``ATTEMPTS`` times in all.
        drain: called every ``REPORT_EVERY`` seconds (to show progress).
    """
    waiting, free, running, tries = list(pairs), list(range(len(slots))), {}, Counter()
    held = [set() for _ in slots]           # per slot: the targets its worker has set up
    while waiting or running:
        while waiting and free:
            index = free.pop()
            pair = waiting.pop(_pick(waiting, held, index))
            held[index].add(_target_key(pair))
            tries[pair.name] += 1
            running[submit(slots[index], pair)] = index, pair
        done, _ = concurrent.futures.wait(running, timeout=REPORT_EVERY,
                                          return_when=concurrent.futures.FIRST_COMPLETED)
        drain()
        for future in done:
            index, pair = running.pop(future)
            free.append(index)
            try:
                entry = future.result()
            except lost as error:
                for targets in held:        # a new worker (a local pool: new workers)
                    targets.clear()
                if tries[pair.name] < ATTEMPTS:
                    waiting.insert(0, pair)
                    continue
                entry = _entry(pair, "failed", outputs=[],
                               error=f"its worker died {ATTEMPTS} times ({error})")
            except Exception as error:  # noqa: BLE001  (e.g. a result that did not pickle)
                entry = _entry(pair, "failed", outputs=[],
                               error=f"internal error: {type(error).__name__}: {error}")
            yield {**entry, "attempts": tries[pair.name]}


def _target_key(pair):
    """What a worker's set-up of a pair's target depends on (``_set_target``'s key, the
    target named instead of hashed, the pipeline's ``refine`` and ``mirror_target`` told by
    its options)."""
    return (pair.target, pair.options["weights"], pair.options["refine"],
            pair.options.get("preset"))


def _pick(waiting, held, index):
    """Which of ``waiting`` (longest first) slot ``index`` starts: among the pairs as long as
    the first, the first whose target that slot's worker has set up, else the first whose
    target no worker has, else the first. Equal pairs (one source onto every target, or the
    benchmark's) then share out the targets instead of each worker setting up every one; a
    longer pair never waits for a shorter. (A local pool's pair goes to whichever process is
    idle: the one that has just ended this slot's pair, unless two ended at once.)"""
    ties = [(i, _target_key(pair)) for i, pair in enumerate(
        itertools.takewhile(lambda pair: pair.frames == waiting[0].frames, waiting))]
    anyone = set().union(*held)
    mine = [i for i, key in ties if key in held[index]]
    fresh = [i for i, key in ties if key not in anyone]
    return (mine or fresh or [0])[0]


class LocalPool:
    """``count`` worker processes (``start_worker``); a pool that a dying worker broke is
    replaced at the next ``submit``."""

    lost = BrokenProcessPool

    def __init__(self, count):
        # spawn: a worker starts clean (no threads or BLAS state forked from this process)
        self.context = multiprocessing.get_context("spawn")
        self.progress = self.context.Queue()
        self.slots = list(range(count))        # a pair goes to any idle process
        self.executor = self._executor()

    def _executor(self):
        return concurrent.futures.ProcessPoolExecutor(
            len(self.slots), mp_context=self.context, initializer=start_local_worker,
            initargs=(self.progress.put,))

    def submit(self, slot, pair):
        try:
            return self.executor.submit(run_pair, pair)
        except self.lost:
            self.executor.shutdown(wait=True)
            self.executor = self._executor()
            return self.executor.submit(run_pair, pair)

    def drain(self):
        """The (pair name, frames done) reports since the last call."""
        reports = []
        while True:
            try:
                reports.append(self.progress.get_nowait())
            except queue.Empty:
                return reports

    def close(self):
        self.executor.shutdown(wait=True, cancel_futures=True)


class RayWorker:
    """A Ray actor (``ray.remote(RayWorker)``): a worker that keeps its weights and targets.
    Progress goes with each call, not to the constructor: Ray keeps a restarted actor's
    constructor arguments in its object store, where they may be lost."""

    def __init__(self):
        start_worker()

    def run(self, pair, report):
        _REPORT[0] = report
        return run_pair(pair)


class RayPool:
    """``count`` Ray actors (at most, and by default, one per CPU of the cluster) on the
    cluster at ``address`` ("auto": the one running here or at RAY_ADDRESS), or on the
    instance this process has started already (``ray.init``). Paths must read and write the
    same files on every node."""

    def __init__(self, address, count=None):
        try:
            import ray
            from ray.util.queue import Queue
        except ImportError as error:
            raise MissingExtra(f"--ray needs the package 'ray' ({error}): pip install "
                               "\"minretarget[ray]\"") from None
        self.ray, self.started = ray, not ray.is_initialized()
        if self.started:
            ray.init(address=address, log_to_driver=False)
        self.lost = ray.exceptions.RayActorError
        self.progress = Queue()
        # No more actors than CPUs: one that waits for a CPU would hold its pair forever.
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        count = min(count or cpus, cpus)
        actor = ray.remote(num_cpus=1, max_restarts=-1)(RayWorker)
        self.slots = [actor.remote() for _ in range(count)]

    def submit(self, actor, pair):
        return actor.run.remote(pair, self.progress.put).future()

    def drain(self):
        return self.progress.get_nowait_batch(self.progress.qsize())

    def close(self):
        for actor in self.slots:
            self.ray.kill(actor)
        self.progress.shutdown()
        if self.started:
            self.ray.shutdown()


def _done_before(pairs, problems):
    """{pair name: its done-marker's entry} of the pairs done by an earlier run of the job;
    a marker of another source, target or options is a problem."""
    done = {}
    for pair in pairs:
        marker = Path(pair.folder) / DONE
        if marker.is_file():
            entry = json.loads(marker.read_text())
            if {key: entry.get(key) for key in spec(pair)} != spec(pair):
                problems.append(f"{marker}: was done with another source, target or options "
                                "than the job's now: choose another --out, or delete it")
            done[pair.name] = {**entry, "skipped": True}
    return done


def run_batch(job, out_dir, workers=None, ray=None, resume=False, progress=True):
    """Run a job (module docstring); returns the summary it writes to ``out_dir/summary.json``.

    Args:
        job: path of the job file; out_dir: the output folder.
        workers: local processes or Ray actors (None: one per core, or per Ray CPU).
        ray: a Ray address ("auto", "ray://host:10001") to run on Ray, or None.
        resume: skip the pairs done in ``out_dir`` and go on with the others.
        progress: show a progress bar on stderr.
    Raises:
        JobError before any work for a bad job, or an ``out_dir`` that holds pair folders
        without ``resume``; KeyboardInterrupt at Ctrl-C (the summary written first).
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    pairs, problems = read_job(job, out_dir), []
    done = _done_before(pairs, problems) if resume else {}
    started = [pair.name for pair in pairs if Path(pair.folder).exists()]
    if started and not resume:
        problems.append(f"{out_dir}: holds the folders of {len(started)} pair(s) of this job "
                        f"({', '.join(started[:3])}{', ...' if len(started) > 3 else ''}): add "
                        "--resume to go on with them, or choose another --out")
    if problems:
        raise JobError(job, problems)
    todo = [pair for pair in pairs if pair.name not in done]
    tqdm = require("tqdm", "the progress bar").tqdm
    local = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    pool = (RayPool(ray, workers) if ray else LocalPool(max(1, min(workers or local,
                                                                   len(todo)))))
    bar = tqdm(total=sum(pair.frames for pair in todo), unit="frame", desc="batch",
               disable=not progress, file=sys.stderr)
    shown, entries = Counter(), dict(done)

    def show(name, frames):
        bar.update(max(0, frames - shown[name]))
        shown[name] = max(shown[name], frames)

    def drain():
        for name, frames in pool.drain():
            show(name, frames)

    try:
        def submit(slot, pair):
            return pool.submit(slot, with_target(pair))

        for entry in schedule(todo, pool.slots, submit, pool.lost, drain):
            entries[entry["pair"]] = entry
            show(entry["pair"], entry["frames"])
            failed = sum(e["status"] == "failed" for e in entries.values())
            bar.set_postfix_str(f"{len(entries)}/{len(pairs)} pairs, {failed} failed")
    finally:
        bar.close()
        pool.close()
        summary = _summary(pairs, entries, pool, time.perf_counter() - start)
        out_dir.mkdir(parents=True, exist_ok=True)
        with atomic_write(out_dir / SUMMARY) as file:
            file.write(json.dumps(summary, indent=1).encode())
    return summary


def _summary(pairs, entries, pool, seconds):
    """The batch's summary: totals over the pairs run now, and every pair's entry."""
    ran = [e for e in entries.values() if e["status"] == "done" and not e.get("skipped")]
    frames = sum(e["frames"] for e in ran)
    listed = [entries.get(p.name) or _entry(p, "not run") for p in pairs]
    statuses = Counter(e["status"] for e in listed)
    return {"engine": "ray" if isinstance(pool, RayPool) else "local",
            "workers": len(pool.slots), "seconds": round(seconds, 3), "frames": frames,
            "frames_per_second": round(frames / seconds, 3), "done": statuses["done"],
            "skipped": sum(bool(e.get("skipped")) for e in listed),
            "failed": statuses["failed"], "not_run": statuses["not run"], "pairs": listed}


def _command(args):
    summary = run_batch(args.job, args.out, args.workers, args.ray, args.resume)
    print(f"batch: {summary['done']} of {len(summary['pairs'])} pairs done "
          f"({summary['skipped']} by an earlier run), {summary['failed']} failed; "
          f"{summary['frames']} frames in {summary['seconds']:.1f} s "
          f"({summary['frames_per_second']:.1f} frames/s) on {summary['workers']} "
          f"{summary['engine']} workers; {Path(args.out) / SUMMARY}")
    failed = [e for e in summary["pairs"] if e["status"] == "failed"]
    for entry in failed:
        print(f"minretarget: failed: {entry['pair']}: {entry['error']}", file=sys.stderr)
    if failed:
        raise ValueError(f"{len(failed)} of {len(summary['pairs'])} pairs failed (listed "
                         f"above and in {Path(args.out) / SUMMARY}); the others are done")


def add_command(commands):
    """Add ``minretarget batch`` to the command line's subparsers."""
    batch = commands.add_parser(
        "batch", help="retarget many sources onto many targets (a job file)",
        description="Run every pair of a JOB file (.toml or .json: sources, targets, pairs "
        "and the options of retarget; see docs/batch.md) into DIR/<target>/<source>, on a "
        "pool of processes or on Ray. Exit status 0 when every pair is done, 1 otherwise.")
    batch.add_argument("job", help="JOB file (.toml or .json)")
    batch.add_argument("--out", required=True, help="output folder DIR")
    batch.add_argument("--workers", type=int_at_least(1), default=None,
                       help="worker processes, or Ray actors (default: one per core, or per "
                       "CPU of the Ray cluster)")
    batch.add_argument("--ray", metavar="auto|ADDRESS", default=None,
                       help="run on the Ray cluster at ADDRESS (auto: the one started here "
                       "with `ray start`, or at RAY_ADDRESS); needs the ray extra")
    batch.add_argument("--resume", action="store_true",
                       help="skip the pairs done in DIR, resume the others from their "
                       "checkpoints")
    batch.set_defaults(run=_command)
