"""``minretarget batch``: many motions onto many bodies, on every core or on a Ray cluster.

    minretarget batch JOB --out DIR [--workers N] [--ray auto|ADDRESS] [--resume]

JOB is TOML (Python >= 3.11) or JSON; its relative paths are relative to its own folder:

    sources = ["mocap/*.bvh", "captures/take_01", "walk.npz"]  # files, folders of frames, globs
    targets = ["bodies/*.ply"]                                  # T-pose bodies
    pairs = [{source = "08_01", target = "anna", options = {units = "cm"}}]   # optional
    [options]                                                   # every pair's (OPTIONS)
    format = "ply,npz,glb,bvh"
    foot_leash = 0.1

A source or target is named by its file or folder name without the suffix; names must be
unique. Without ``pairs`` every source goes onto every target. ``options`` are those of
``minretarget retarget`` (``OPTIONS``: ``--no-smoothing`` is ``smoothing = false``), a pair's
own ``options`` override the job's. The whole job is checked before any work (files exist,
sources and targets read, weights load, options valid) and every problem is listed at once.

Each pair runs as ``minretarget retarget SOURCE TARGET --out DIR/<target>/<source>`` would,
writing the same bytes there (``cli.retarget_to_files``, its checkpoints included), then a
done-marker, ``done.json`` (its ``summary.json`` entry). Pairs run longest first on a pool of
worker processes (``--workers``, default one per core) or of Ray actors (``--ray``), each
with one BLAS and numba thread, each keeping the weights and every target's set-up (skeleton
and skinning weights, keyed by the target's content) between pairs. A failing pair (a bad
file, a NaN frame) is recorded with its reason and the others go on; a pair whose worker dies
is run again (``ATTEMPTS`` in all), from its checkpoint. ``--resume`` skips the pairs done and
resumes the others from their checkpoints; without it a DIR holding any pair's folder is
refused. ``DIR/summary.json`` lists every pair's status, frames, seconds and outputs; the
command exits with status 0 only if every pair is done.
"""
import argparse
import concurrent.futures
import ctypes
import glob
import hashlib
import json
import multiprocessing
import os
import queue
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
from .checkpoint import CHECKPOINT
from .cli import DEFAULT_FORMATS, int_at_least, positive_float, retarget_to_files
from .contacts import FootLock
from .conventions import MIN_POINTS
from .extras import MissingExtra, require
from .outputs import frame_name, parse_formats, previous_outputs
from .retargeter import Retargeter
from .smoothing import Smoothing
from .sources import open_source, read_target
from .units import UNITS, UP_AXES, make_space
from .validation import InputWarning, as_point_cloud, check_body
from .weights import load_weights

DONE = "done.json"               # in a pair's folder once its outputs are complete
SUMMARY = "summary.json"
ATTEMPTS = 3                     # runs of a pair whose worker dies, before it counts as failed
REPORT_EVERY = 0.5               # seconds between a worker's progress reports


def _boolean(value):
    if not isinstance(value, bool):
        raise ValueError(f"must be true or false, got {value!r}")
    return value


def _one_of(choices):
    def check(value):
        if value not in choices:
            raise ValueError(f"must be one of {', '.join(choices)}, got {value!r}")
        return value
    return check


def _optional(check):
    return lambda value: None if value is None else check(value)


def _text(value):
    if not isinstance(value, str):
        raise ValueError(f"must be a string, got {value!r}")
    return value


def _formats(value):
    return parse_formats(",".join(value) if isinstance(value, list) else _text(value))


# Option -> (default, check). The options of ``minretarget retarget``: ``--fps`` is ``fps``,
# ``--up-axis`` is ``up_axis``, ``--no-X`` is ``X = false``, ``--mirror-source`` is
# ``mirror_source = true``. ``weights`` is a path, relative to the job file.
OPTIONS = {
    "format": (parse_formats(DEFAULT_FORMATS), _formats),
    "fps": (None, _optional(lambda value: positive_float(str(value)))),
    "units": ("m", _one_of(tuple(UNITS))),
    "up_axis": ("y", _one_of(tuple(UP_AXES))),
    "points": (None, _optional(lambda value: int_at_least(1)(str(value)))),
    "seed": (0, lambda value: int_at_least(0)(str(value))),
    "weights": (None, _optional(_text)),
    "smoothing": (True, _boolean),
    "foot_lock": (True, _boolean),
    "foot_leash": (None, _optional(lambda value: positive_float(str(value)))),
    "mirror_source": (False, _boolean),
    "refine": (True, _boolean),
    "denoise": (True, _boolean),
    "rest_pose": (True, _boolean),
    "facing_check": (True, _boolean),
}
DEFAULTS = {name: default for name, (default, _) in OPTIONS.items()}


class Pair(NamedTuple):
    """One source onto one target: everything a worker needs to run it."""
    name: str          # "<target>/<source>", its folder under the job's output folder
    source: str        # absolute path of the source motion
    target: str        # absolute path of the target body
    options: dict      # every name of OPTIONS (``weights`` an absolute path or None)
    frames: int        # T, the source's frame count (30 fps for BVH)
    folder: str        # absolute path of its output folder


class JobError(ValueError):
    """A job that cannot run; ``problems`` lists every reason found."""

    def __init__(self, job, problems):
        self.problems = problems
        super().__init__(f"{job}: {len(problems)} problem(s):\n  " + "\n  ".join(problems))


def check_options(raw, where, base=DEFAULTS):
    """``base`` updated with the options table ``raw``: (options, [problems])."""
    if not isinstance(raw, dict):
        return dict(base), [f"{where}: must be a table of options, got {raw!r}"]
    options, problems = dict(base), []
    for name, value in raw.items():
        if name not in OPTIONS:
            problems.append(f"{where}: unknown option {name!r} (options: {', '.join(OPTIONS)})")
            continue
        try:
            options[name] = OPTIONS[name][1](value)
        except (ValueError, argparse.ArgumentTypeError) as error:
            problems.append(f"{where}: {name}: {error}")
    if options["foot_leash"] is not None and not options["foot_lock"] and (
            "foot_leash" in raw or "foot_lock" in raw):
        problems.append(f"{where}: foot_leash needs foot_lock (it is false)")
    return options, problems


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


def _expand(entries, key, base, problems):
    """{name: absolute Path} of a job's ``sources`` or ``targets`` (paths and globs)."""
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
        if not paths:
            problems.append(f"{key}: {entry}: " + ("matches nothing" if is_glob else
                                                   "no such file or folder"))
        for path in paths:
            name = _name(path)
            if name in found and found[name] != path.resolve():
                problems.append(f"{key}: {found[name]} and {path} have the same name "
                                f"{name!r}: rename one")
            found[name] = path.resolve()
    return found


def _pairs(raw, sources, targets, options, problems):
    """[(source name, target name, options)] of the job's ``pairs``, or every combination."""
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
                                            options)
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
        values, missing paths, duplicate names, sources and targets that do not read,
        weights that do not load.
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
    targets = _expand(job.get("targets"), "targets", base, problems)
    options, found = check_options(job.get("options", {}), "options")
    problems += found
    listed = _pairs(job.get("pairs"), sources, targets, options, problems)
    if problems:          # reading files under options that do not parse would only add noise
        raise JobError(path, problems)
    listed = [(s, t, o if o["weights"] is None else {**o, "weights": str(base / o["weights"])})
              for s, t, o in listed]
    pairs = _read_files(listed, sources, targets, out_dir, problems)
    if problems:
        raise JobError(path, list(dict.fromkeys(problems)))
    return sorted(pairs, key=lambda pair: -pair.frames)


def _read_files(listed, sources, targets, out_dir, problems):
    """[Pair] of the (source name, target name, options) ``listed`` whose weights load, whose
    source opens and whose target reads (each read once per units and axes); the others'
    problems are added to ``problems``."""
    for weights in dict.fromkeys(o["weights"] for _, _, o in listed):
        try:
            load_weights(weights)
        except (OSError, ValueError) as error:
            problems.append(f"weights: {error}")
    counts, bodies, pairs = {}, {}, []
    for source, target, options in listed:
        space = make_space(options["units"], options["up_axis"])
        key = (source, space, options["fps"], options["points"])
        if key not in counts:
            try:
                counts[key] = open_source(sources[source], space, fps=options["fps"],
                                          points=options["points"]).count
            except (OSError, ValueError) as error:
                counts[key] = None
                problems.append(f"source {source}: {error}")
        if (target, space) not in bodies:
            try:
                as_point_cloud(read_target(targets[target], space)[0], "its points", MIN_POINTS)
                bodies[target, space] = True
            except (OSError, ValueError) as error:
                bodies[target, space] = False
                problems.append(f"target {target}: {error}")
        if counts[key] is not None and bodies[target, space]:
            name = f"{target}/{source}"
            pairs.append(Pair(name, str(sources[source]), str(targets[target]), options,
                              counts[key], str(out_dir / name)))
    return pairs


# --- a worker: one process (or Ray actor), pairs one after another ---------------------------

_WEIGHTS = {}      # weights path (None: the shipped ones) -> Weights, loaded once per worker
_TARGETS = {}      # (weights path, refine, target content hash) -> (tpose_joints, skin_weights)
_REPORT = [None]   # report((pair name, frames done)) to the batch, or None


def start_worker(report=None):
    """Set up a worker process: one BLAS and one numba thread (the cores go to the workers),
    and where progress goes (``report((pair name, frames done))``)."""
    require("threadpoolctl", "minretarget batch").threadpool_limits(1)
    numba.set_num_threads(1)
    _REPORT[0] = report


def start_local_worker(report):
    """``start_worker`` in a process of the local pool, which on Linux the kernel kills when
    the batch process dies: a killed batch leaves no worker writing into a pair that a
    ``--resume`` runs again."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)       # PR_SET_PDEATHSIG
    start_worker(report)


def _content_hash(*arrays):
    """Hex SHA-256 of arrays' bytes (and None's), to know a target by its content."""
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(b"none" if array is None else np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def _retargeter(options):
    """A Retargeter with a pair's options, as ``minretarget retarget`` makes it."""
    weights = options["weights"]
    if weights not in _WEIGHTS:
        _WEIGHTS[weights] = load_weights(weights)
    foot_lock = FootLock() if options["foot_lock"] else None
    if options["foot_leash"] is not None:
        foot_lock = foot_lock._replace(max_offset=options["foot_leash"])
    return Retargeter(_WEIGHTS[weights], warn=False,
                      smoothing=Smoothing() if options["smoothing"] else None,
                      foot_lock=foot_lock, mirror_source=options["mirror_source"],
                      refine=options["refine"], denoise=options["denoise"],
                      rest_pose=options["rest_pose"], facing_check=options["facing_check"])


def _set_target(retargeter, path, options, space):
    """``cli.set_target`` with the target's skeleton and skinning weights computed once per
    worker for each content, weights and ``refine`` (the only options they depend on)."""
    points, faces = read_target(path, space)
    key = (options["weights"], options["refine"], _content_hash(points, faces))
    try:
        retargeter.set_target(points, faces, *_TARGETS.get(key, (None, None)))
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    check_body(points, path, space, tpose=True)
    _TARGETS[key] = retargeter.target.tpose_joints, retargeter.target.skin_weights


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


def run_pair(pair):
    """Run one pair into its folder and mark it done (module docstring); never raises for
    the pair's own faults (a stop, Ctrl-C, raises KeyboardInterrupt after a checkpoint).

    Returns:
        its summary entry: {"pair", "source", "target", "options", "frames", "status":
        "done" or "failed", "outputs" (file names in its folder), "seconds", "warnings";
        "error" when failed}.
    """
    start = time.perf_counter()
    entry = _entry(pair, "done", outputs=output_names(pair.options["format"], pair.frames))
    options, folder = pair.options, Path(pair.folder)
    space = make_space(options["units"], options["up_axis"])

    def open_at(first):
        source = open_source(pair.source, space, fps=options["fps"], points=options["points"],
                             seed=options["seed"], start=first)
        return source._replace(frames=_reported(source.frames, first, pair.name))

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputWarning)
        try:
            retargeter = _retargeter(options)
            _set_target(retargeter, pair.target, options, space)
            # A checkpoint: the pair was cut short (a killed worker or batch), go on from it;
            # else any files there are a killed run's from before its first checkpoint.
            resume = CHECKPOINT in previous_outputs(folder)
            retarget_to_files(retargeter, open_at, folder, options["format"], space,
                              {"points": options["points"], "seed": options["seed"]},
                              resume=resume, overwrite=not resume, progress=False)
        except Exception as error:      # noqa: BLE001  (a pair's fault must not stop the batch)
            expected = isinstance(error, (ValueError, OSError, MemoryError))
            entry.update(status="failed", outputs=[], error=str(error) if expected else
                         f"internal error: {type(error).__name__}: {error}")
    entry.update(seconds=round(time.perf_counter() - start, 3),
                 warnings=[str(w.message) for w in caught if w.category is InputWarning])
    if entry["status"] == "done":
        with atomic_write(folder / DONE) as file:
            file.write(json.dumps(entry, indent=1).encode())
    return entry


# --- the pools: local processes or Ray actors, pairs handed out as workers free up ----------

def schedule(pairs, slots, submit, lost, drain):
    """Run ``pairs`` in order, one at a time on each of ``slots``; yield their summary
    entries (with ``attempts``) as they end.

    Args:
        pairs: [Pair], in the order to start them.
        slots: the workers, each given one pair at a time.
        submit: ``submit(slot, pair)`` -> a concurrent.futures.Future of ``run_pair(pair)``.
        lost: the exception type(s) of a Future whose worker died: its pair runs again,
            from its checkpoint, first in line, ``ATTEMPTS`` times in all.
        drain: called every ``REPORT_EVERY`` seconds (to show progress).
    """
    waiting, free, running, tries = list(pairs), list(slots), {}, Counter()
    while waiting or running:
        while waiting and free:
            pair, slot = waiting.pop(0), free.pop()
            tries[pair.name] += 1
            running[submit(slot, pair)] = slot, pair
        done, _ = concurrent.futures.wait(running, timeout=REPORT_EVERY,
                                          return_when=concurrent.futures.FIRST_COMPLETED)
        drain()
        for future in done:
            slot, pair = running.pop(future)
            free.append(slot)
            try:
                entry = future.result()
            except lost as error:
                if tries[pair.name] < ATTEMPTS:
                    waiting.insert(0, pair)
                    continue
                entry = _entry(pair, "failed", outputs=[],
                               error=f"its worker died {ATTEMPTS} times ({error})")
            except Exception as error:  # noqa: BLE001  (e.g. a result that did not pickle)
                entry = _entry(pair, "failed", outputs=[],
                               error=f"internal error: {type(error).__name__}: {error}")
            yield {**entry, "attempts": tries[pair.name]}


class LocalPool:
    """``count`` worker processes (``start_worker``); a pool that a dying worker broke is
    replaced at the next ``submit``."""

    lost = BrokenProcessPool

    def __init__(self, count):
        # spawn: a worker starts clean (no threads or BLAS state forked from this process)
        self.context = multiprocessing.get_context("spawn")
        self.progress = self.context.Queue()
        self.slots = [None] * count
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
        for entry in schedule(todo, pool.slots, pool.submit, pool.lost, drain):
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
