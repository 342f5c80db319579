"""The ``minretarget`` command: retarget files, draw previews, run the demo.

    minretarget demo [--out DIR] [--weights FILE] [--threads N]
    minretarget retarget SOURCE TARGET --out DIR [--format ply,obj,npz,glb,bvh] [--fps F]
                         [--source-units m|cm|mm] [--source-up y|z] [--target-units ...]
                         [--target-up ...] [--units ...] [--up-axis ...] [--force]
                         [--out-units m|cm|mm] [--out-up y|z] [--skeleton-map FILE.json]
                         [--points N] [--seed S]
                         [--weights FILE] [--threads N] [--no-smoothing] [--no-foot-lock]
                         [--mirror-source] [--no-refine] [--no-denoise] [--no-rest-pose]
                         [--no-facing-check] [--source-fit]
                         [--resume | --overwrite]
    minretarget render RESULT --out FILE.png|FILE.gif
    minretarget batch JOB --out DIR [--workers N] [--ray auto|ADDRESS] [--resume]
    minretarget inspect FILE.bvh [--skeleton-map FILE.json]
    minretarget bodies
    minretarget warmup [--weights FILE]

SOURCE and TARGET kinds: ``minretarget.sources``; outputs: ``minretarget.outputs``; units and
axes: ``minretarget.units``. Each input's units and up axis, unless given, are told from its
body's size and shape (``validation.guess_space``) and reported in one line; a body that is
still not a person's size, or lies along its up axis, is refused before anything is written
unless ``--force``. Outputs are in metres, +Y up, unless ``--out-units`` / ``--out-up``.
Needs the ``cli`` extra (``pip install "minretarget[cli]"``): without it the command says so
instead of failing with a traceback. Bad input (a missing or malformed file, a wrong shape or
value) is reported in one line naming the file (and frame), exit status 1; likely mistakes
(not a T-pose; units or up axis with ``--force``) in ``minretarget: warning:`` lines. An
interrupted ``retarget`` keeps its complete frames and a checkpoint: ``--resume`` finishes
it with the same result as an uninterrupted run (``minretarget.checkpoint``); a run that
fails before its first frame leaves the folder as it was. The numba kernels compile on a
machine's first run (about 15-25 s, said in a line before the progress bar starts), or at
``minretarget warmup``, then load from their on-disk cache. A fresh run refuses an output
folder that holds another run's files unless ``--overwrite``, which keeps them aside until
the new run completes; the demo replaces only an earlier demo's.
"""
import argparse
import contextlib
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from . import __version__
from ._jit import on_first_compile
from .bvh import read_bvh
from .bodies import body_lines
from .checkpoint import (CHECKPOINT, CHECKPOINT_EVERY, PREVIOUS_RUN, TRACK, Track,
                         abandon_run, finish_run, prepare_out_dir, run_record,
                         save_checkpoint)
from .contacts import FootLock
from .conventions import MIN_POINTS
from .extras import MissingExtra, require
from .fit import FitSettings
from .outputs import (DEMO_MARK, FORMATS, frame_name, open_writers, parse_formats,
                      previous_outputs)
from .render import render
from .pipeline import DEFAULT_PRESET, PRESETS, preset
from .retargeter import Retargeter
from .skeletons import canonical_world, mapping_lines, skeleton_of
from .sources import MESH_POINTS, load_sample, open_source, read_skeleton_map, read_target
from .units import CANONICAL, UNITS, UP_AXES, make_space, to_canonical
from .validation import (UNIT_NAMES, InputWarning, TPoseWarning, body_problems, check_body,
                         guess_space)
from .weights import DEFAULT_WEIGHTS

DEFAULT_FORMATS = "ply,npz,glb,bvh"


def load_retargeter(weights=None, config="default"):
    """A Retargeter with ``weights`` (None: the shipped default) and the pipeline ``config``
    (``pipeline.PipelineConfig`` or a preset's name), or FileNotFoundError saying what to do
    when the default weights are not installed."""
    if weights is None and not DEFAULT_WEIGHTS.is_file():
        raise FileNotFoundError(
            f"the default weights are not installed ({DEFAULT_WEIGHTS} is missing): they ship "
            "with minretarget once the model is trained. Pass --weights FILE to use a weights "
            "file of your own (python -m training.train ... exports one).")
    # warn=False: the command line checks the inputs itself, naming files and options.
    return Retargeter.from_weights(weights, config, warn=False)


def set_target(retargeter, points, faces, name, space=CANONICAL, tpose_joints=None,
               skin_weights=None, leg_length=None):
    """``retargeter.set_target(points, faces, tpose_joints, skin_weights, leg_length)``, its
    errors prefixed with the target's name; warns (``validation.InputWarning``) if it does not look
    like a T-pose person in ``space``."""
    try:
        retargeter.set_target(points, faces, tpose_joints, skin_weights, leg_length)
    except ValueError as error:
        raise ValueError(f"{name}: {error}") from None
    check_body(points, name, space, tpose=True, role="target")


def blas_threads(count):
    """A context within which every BLAS library of the process (NumPy's, and SciPy's, which
    numba's kernels call) runs ``count`` threads: more than one busy-wait between SKR's small
    products, and on a shared CPU made a run 3 to 4 times slower (issue 41)."""
    threadpoolctl = require("threadpoolctl", "--threads")
    import scipy.linalg.cython_blas  # noqa: F401  (loads SciPy's BLAS: the limit reaches it)
    return threadpoolctl.threadpool_limits(count, user_api="blas")


@contextlib.contextmanager
def stop_between_steps():
    """Within: Ctrl-C (SIGINT) ends a loop after the step in progress (a frame; a training
    step), not inside it, so that no library can swallow the KeyboardInterrupt (trimesh
    catches BaseException in places, and a run once went on to the end) and the state saved
    is a whole step's. Yields a list that is non-empty once a stop is asked; a second
    Ctrl-C interrupts at once."""
    asked = []
    if threading.current_thread() is not threading.main_thread():   # signals: main only
        yield asked
        return

    def ask(signum, frame):
        if asked:
            raise KeyboardInterrupt
        asked.append(signum)

    previous = signal.signal(signal.SIGINT, ask)
    try:
        yield asked
    finally:
        signal.signal(signal.SIGINT, previous)


def retarget_to_files(retargeter, open_at, out_dir, formats, space, settings, resume=False,
                      overwrite=False, progress=True, demo=False):
    """Retarget every frame of a source onto the retargeter's target; write ``formats``.

    Args:
        retargeter: Retargeter with weights and a target (``set_target``); for a skeleton
            source its config's ``smoothing`` and ``denoise`` are switched off (clean joints:
            smoothing would only lag, and the denoiser learned SKR's errors).
        open_at: ``open_at(start)`` -> ``sources.Source`` whose frames begin at ``start``.
        out_dir: output folder; formats: names from ``outputs.FORMATS``.
        space: ``units.Space`` of the outputs.
        settings: {"points": ..., "seed": ..., "skeleton_map": ..., "viewpoint": ...
            (optional)}: how the source was resampled, a BVH's skeleton map, and the depth
            camera that saw a cloud source ((3,) canonical metres, ``Retargeter.step``).
        resume: continue the interrupted run in ``out_dir``; overwrite: replace the files of
            an earlier run there (``checkpoint.prepare_out_dir``).
        progress: show a tqdm progress bar on stderr.
        demo: mark the folder's run as a demo's (``outputs.DEMO_MARK``), which a later demo
            may replace.
    Returns:
        the Source retargeted (its ``count`` frames are all written, resumed or not).
    """
    source = open_at(0)
    if source.count == 0:
        raise ValueError(f"{source.path}: holds no frames")
    tqdm = require("tqdm", "the progress bar").tqdm
    out_dir = Path(out_dir)
    if source.kind != "points":
        # A skeleton source is clean: smoothing would only lag, and the denoiser learned SKR's
        # errors, not its.
        retargeter.config = retargeter.config.replace(smoothing=None, denoise=False)
    run = run_record(source, retargeter.target, retargeter.weights, formats, space,
                     config=retargeter.config, **settings)
    # Before the folder is touched (a Ctrl-C in a cold cache's compile leaves it as it was)
    # and before the progress bar starts.
    retargeter.warm_up(skeleton=source.kind != "points")
    start, state = prepare_out_dir(out_dir, run, retargeter.stages, resume, overwrite)
    if start:
        source = open_at(start)
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    if demo:
        (out_dir / DEMO_MARK).write_text("minretarget demo: a later demo may replace this run\n")
    retargeter.state = state
    viewpoint = settings.get("viewpoint")
    if source.kind != "points":
        step = retargeter.step_skeleton
    elif viewpoint is None:
        step = retargeter.step
    else:
        def step(points):
            return retargeter.step(points, viewpoint)
    track = Track(out_dir / TRACK, start)
    # A resumed run's npz gets the first frames' vertices again from their saved rotations
    # and root, posed exactly as the interrupted run posed them.
    past = (retargeter.pose(fields["rotations"], fields["root"])[0]
            for fields in track.frames())
    done, stages = start, retargeter.stages
    try:
        save_checkpoint(out_dir, run, stages, state, start, track)
        with open_writers(out_dir, formats, retargeter.target, source.count, source.fps, space,
                          track, past) as write, stop_between_steps() as stop_asked:
            frames = tqdm(source.frames, total=source.count, initial=start, unit="frame",
                          desc="retargeting", disable=not progress, file=sys.stderr)
            for index, data in enumerate(frames, start):
                try:
                    frame = step(data)
                except ValueError as error:
                    raise ValueError(f"{source.frame_name(index)}: {error}") from None
                if index == 0:
                    check_body(data, source.frame_name(0), source.space, role="source")
                write(frame)
                done, state = index + 1, retargeter.state
                if stop_asked:
                    raise KeyboardInterrupt
                if done % CHECKPOINT_EVERY == 0:
                    save_checkpoint(out_dir, run, stages, state, done, track)
    except BaseException as error:
        # Ctrl-C or a bad frame: keep what is done, so that --resume goes on from here (and
        # say so); with nothing done, leave the folder as it was.
        if done > start:
            save_checkpoint(out_dir, run, stages, state, done, track)
        elif start == 0:
            track.close()
            abandon_run(out_dir, created)
        if done and isinstance(error, (ValueError, OSError)):
            raise ValueError(f"{error}; the {frames_text(done)} done are kept: fix it, then add "
                             "--resume to continue") from None
        raise
    finally:
        track.close()
    finish_run(out_dir)
    return source


def frames_text(count):
    """"1 frame", "2 frames"."""
    return f"{count} frame{'' if count == 1 else 's'}"


def _written(out_dir, formats, count):
    names = [f"{frame_name(0, f)} .. {frame_name(count - 1, f)}" for f in formats
             if f in ("ply", "obj")]
    names += [f"result.{f}" for f in formats if f not in ("ply", "obj")]
    return f"{out_dir}: " + ", ".join(names)


def file_space(points, name, role, units=None, up_axis=None, force=False, min_points=1):
    """The units and up axis of one input file, told from its body where not given
    (``validation.guess_space``), reported in one line on stdout.

    Args:
        points: (N, 3) the body's points or joints as in the file (a source: its frame 0).
        name: the file (and frame), for messages; role: "source" or "target".
        units, up_axis: given by the user, or None to guess.
        force: go on (with a warning, later) when the body read in that space is still not
            a person's size or lies along its up axis.
        min_points: fewer points are refused as such (``conventions.MIN_POINTS`` for a
            cloud).
    Returns:
        ``units.Space``.
    Raises:
        ValueError naming the file and the option to give, unless ``force``.
    """
    if len(points) < min_points:       # too few to tell: the count is what is wrong
        raise ValueError(f"{name}: the {role} has {len(points)} points; at least "
                         f"{min_points} are needed")
    space = guess_space(points, units, up_axis)
    canonical = to_canonical(points, space)
    problems = [message for category, message in body_problems(canonical, name, space,
                                                               role=role)
                if category is not TPoseWarning]
    if problems and not force:
        raise ValueError(f"{'; '.join(problems)}; nothing written (--force goes on anyway)")
    height = float(np.ptp(canonical[:, 1]))
    print(f"{role}: {UNIT_NAMES[space.units]} ({'given' if units else 'detected'}), "
          f"{space.up_axis.upper()} up ({'given' if up_axis else 'detected'}), "
          f"body {height:.2f} m tall ({name})")
    return space


def pipeline_config(args):
    """The pipeline (``pipeline.PipelineConfig``) that ``retarget``'s parsed options ``args``
    ask for: the preset, changed by the options."""
    config = preset(args.preset)
    foot_lock = None if args.no_foot_lock else config.foot_lock
    if args.foot_leash is not None:                   # never with --no-foot-lock (argparse)
        foot_lock = (foot_lock or FootLock())._replace(max_offset=args.foot_leash)
    fitted = args.source_fit      # the fit's skeleton is neither smoothed nor denoised
    return config.replace(
        smoothing=None if args.no_smoothing or fitted else config.smoothing,
        foot_lock=foot_lock, mirror_source=args.mirror_source or config.mirror_source,
        refine=config.refine and not args.no_refine,
        denoise=config.denoise and not (args.no_denoise or fitted),
        rest_pose=config.rest_pose and not args.no_rest_pose,
        facing_check=config.facing_check and not args.no_facing_check,
        fit_source=FitSettings() if fitted and config.fit_source is None else config.fit_source)


def target_of(args):
    """``retarget``'s TARGET read in its units and up axis, given or told from the body
    (``file_space``, which says them in a line): (V, 3) float32 canonical points, (F, 3)
    faces or None, and its ``units.Space``; ValueError naming the file."""
    # Read as it is (the canonical space changes nothing), then in its own space.
    as_in_file, faces = read_target(args.target, CANONICAL)
    space = file_space(as_in_file, args.target, "target", args.target_units or args.units,
                       args.target_up or args.up_axis, args.force, MIN_POINTS)
    return to_canonical(as_in_file, space), faces, space


def source_of(args):
    """``retarget``'s SOURCE opened in its units and up axis, given or told from its frame 0
    (``file_space``), as ``target_of``; warns when ``--points`` exceeds that frame's.

    Returns:
        open_at: ``open_at(start)`` -> ``sources.Source`` from frame ``start`` (canonical).
        count: T, its frame count; settings: ``retarget_to_files``'s ``settings``.
    """
    skeleton_map = args.skeleton_map and read_skeleton_map(args.skeleton_map)
    reading = {"fps": args.fps, "points": args.points, "seed": args.seed,
               "skeleton_map": skeleton_map}
    raw = open_source(args.source, CANONICAL, **reading)
    if raw.count == 0:
        raise ValueError(f"{raw.path}: holds no frames")
    frame_0 = next(iter(raw.frames))
    space = file_space(frame_0, raw.frame_name(0), "source", args.source_units or args.units,
                       args.source_up or args.up_axis, args.force,
                       MIN_POINTS if raw.kind == "points" else 1)
    if args.points and len(frame_0) < args.points:
        warnings.warn(f"{raw.frame_name(0)}: {len(frame_0)} points, fewer than --points "
                      f"{args.points}: clouds that small are used whole", InputWarning)
    viewpoint = None
    if args.viewpoint is not None:
        if raw.kind != "points":
            raise ValueError(f"{raw.path}: --viewpoint places the depth camera that saw a "
                             f"point cloud, and this source is a {raw.kind} motion")
        if pipeline_config(args).fit_source is None:
            raise ValueError(f"--viewpoint is read by the source fit, which --preset "
                             f"{args.preset} does not run: add --source-fit, or use the "
                             "fitted preset (the default)")
        # In the source's units and axes, as its points are.
        viewpoint = to_canonical([float(value) for value in args.viewpoint.split(",")],
                                 space).tolist()

    def open_at(first):
        return open_source(args.source, space, start=first, **reading)

    return open_at, raw.count, {"points": args.points, "seed": args.seed,
                                "skeleton_map": skeleton_map,
                                **({"viewpoint": viewpoint} if viewpoint else {})}


def _retarget(args):
    start = time.perf_counter()
    space = make_space(args.out_units, args.out_up)
    formats = parse_formats(args.format)
    retargeter = load_retargeter(args.weights, pipeline_config(args))
    points, faces, target_space = target_of(args)
    set_target(retargeter, points, faces, args.target, target_space)
    open_at, _, settings = source_of(args)
    source = retarget_to_files(retargeter, open_at, args.out, formats, space, settings,
                               resume=args.resume, overwrite=args.overwrite)
    print(f"retargeted {frames_text(source.count)} at {source.fps:g} fps in "
          f"{time.perf_counter() - start:.1f} s; wrote "
          f"{_written(args.out, formats, source.count)}")


def _inspect(args):
    motion = read_bvh(args.bvh)
    skeleton_map = args.skeleton_map and read_skeleton_map(args.skeleton_map)
    scheme, skeleton = skeleton_of(motion, skeleton_map, str(args.bvh))
    joints, _ = canonical_world(motion, skeleton, str(args.bvh))
    space = guess_space(joints[0])
    print(f"{args.bvh}: {len(motion.names)} joints, {frames_text(motion.num_frames)} at "
          f"{motion.fps:g} fps; skeleton {scheme}; {UNIT_NAMES[space.units]}, "
          f"{space.up_axis.upper()} up (detected)")
    print("\n".join(mapping_lines(skeleton, motion.names)))


def _bodies(args):
    print("\n".join(body_lines()))


def _render(args):
    count = render(args.result, args.out)
    print(f"drew {frames_text(count)} into {args.out}")


def _demo(args):
    start = time.perf_counter()
    retargeter = load_retargeter(args.weights)
    source, target_points, target_faces, metadata = load_sample()
    print(f"demo: {metadata['description']}")
    out = Path(args.out)
    # A demo replaces an earlier demo's run (the one in the folder, and the one a failed
    # replacement keeps aside), and refuses to touch another run's files.
    for folder in (out, out / PREVIOUS_RUN):
        previous = previous_outputs(folder)
        if previous and DEMO_MARK not in previous:
            raise ValueError(f"{folder}: holds the files of a run that is not a demo's "
                             f"({', '.join(previous[:3])}{', ...' if len(previous) > 3 else ''}"
                             "): choose another --out")
    set_target(retargeter, target_points, target_faces, "the sample's target")
    count = retarget_to_files(retargeter, lambda first: load_sample(start=first)[0], out,
                              FORMATS, CANONICAL, {"points": None, "seed": 0},
                              overwrite=True, demo=True).count
    clouds = load_sample()[0].frames                # a fresh pass over the source clouds
    render(out / "result.npz", out / "preview.png", source_points=clouds)
    print(f"retargeted {frames_text(count)} in {time.perf_counter() - start:.1f} s; wrote "
          f"{_written(out, FORMATS, count)}, preview.png")


def _warmup(args):
    start = time.perf_counter()
    retargeter = load_retargeter(args.weights)
    _, target_points, target_faces, _ = load_sample()
    retargeter.set_target(target_points, target_faces)
    for name, mirror_source, skeleton in (("regressed", False, False),
                                          ("regressed", True, False),
                                          ("regressed", False, True), ("fitted", False, False)):
        retargeter.config = preset(name).replace(mirror_source=mirror_source)
        retargeter.warm_up(skeleton)
    print(f"kernels ready in {time.perf_counter() - start:.1f} s; later runs load them from "
          "numba's cache")


def int_at_least(minimum):
    """argparse type: an integer >= ``minimum`` (also the data command line's)."""
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value
    parse.__name__ = f"integer >= {minimum}"
    return parse


def viewpoint_text(text):
    """``--viewpoint X,Y,Z``: three finite numbers, checked and kept as written (a batch job
    writes it so too)."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not np.isfinite(values).all():
        raise argparse.ArgumentTypeError(f"must be three numbers X,Y,Z, got {text!r}")
    return text


def positive_float(text):
    """argparse type: a positive finite number (also the training command line's)."""
    value = float(text)
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
    return value


class OneLineErrors(argparse.ArgumentParser):
    """An argument parser whose errors are one line (the usage of a command with twenty
    options buried the message), pointing at ``--help``; exit status 2 as argparse's."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


WEIGHTS_HELP = "weights .npz (default: the weights shipped with minretarget)"
THREADS_HELP = ("BLAS threads (default 1: more are faster only on an idle machine, and several "
                "times slower on a shared one)")


def add_retarget_arguments(retarget):
    """Add ``minretarget retarget``'s arguments to the parser ``retarget`` (also how
    ``minretarget batch`` reads a pair's options)."""
    retarget.add_argument("source", help="SOURCE motion")
    retarget.add_argument("target", help="TARGET body in T-pose, or a shipped body's name")
    retarget.add_argument("--out", required=True, help="output folder")
    retarget.add_argument("--format", default=DEFAULT_FORMATS,
                          help=f"comma-separated outputs among {','.join(FORMATS)} "
                          f"(default {DEFAULT_FORMATS})")
    retarget.add_argument("--fps", type=positive_float, default=None,
                          help="source frame rate (default 30 for clouds, the header's for "
                          "BVH, which is resampled to 30)")
    for role in ("source", "target"):
        retarget.add_argument(f"--{role}-units", choices=tuple(UNITS), default=None,
                              help=f"length unit of the {role.upper()} file (default: told "
                              "from the body's size)")
        retarget.add_argument(f"--{role}-up", choices=tuple(UP_AXES), default=None,
                              help=f"up axis of the {role.upper()} file (z: Z up, facing -Y; "
                              "default: told from the body's shape)")
    retarget.add_argument("--units", choices=tuple(UNITS), default=None,
                          help="length unit of both input files")
    retarget.add_argument("--up-axis", choices=tuple(UP_AXES), default=None,
                          help="up axis of both input files")
    retarget.add_argument("--force", action="store_true",
                          help="go on when an input body, in its units and up axis, is not a "
                          "person's size or lies along its up axis (default: refused)")
    retarget.add_argument("--skeleton-map", metavar="FILE.json", default=None,
                          help='a BVH source\'s {"canonical joint": "its joint", ...} where '
                          "its names do not tell (minretarget inspect shows the mapping)")
    retarget.add_argument("--out-units", choices=tuple(UNITS), default="m",
                          help="length unit of the outputs (default m); .glb is always m")
    retarget.add_argument("--out-up", choices=tuple(UP_AXES), default="y",
                          help="up axis of the outputs (default y); .glb is always Y up")
    retarget.add_argument("--points", type=int_at_least(MIN_POINTS), default=None,
                          help="resample every source cloud to N points (a random subset, "
                          "seeded; a mesh frame: N drawn evenly over its surface, default "
                          f"{MESH_POINTS})")
    retarget.add_argument("--seed", type=int_at_least(0), default=0,
                          help="seed of the --points subsets (default 0); each frame's subset "
                          "depends only on it and the frame's index")
    retarget.add_argument("--weights", default=None, help=WEIGHTS_HELP)
    retarget.add_argument("--threads", type=int_at_least(1), default=1, help=THREADS_HELP)
    retarget.add_argument("--preset", choices=["default", *PRESETS], default="default",
                          help="the pipeline to start from (docs/python_api.md): paper (SKR, "
                               "SMRM, FK, LBS only), regressed (SKR's reading smoothed and "
                               f"denoised), fitted (a body model tracked in each cloud); "
                               f"default: {DEFAULT_PRESET}. The options below change it")
    retarget.add_argument("--no-smoothing", action="store_true",
                          help="do not smooth the source skeleton of each point cloud over "
                               "time (default: smoothed against jitter; the denoiser still "
                               "runs unless --no-denoise; skeleton sources are never smoothed)")
    feet = retarget.add_mutually_exclusive_group()
    feet.add_argument("--no-foot-lock", action="store_true",
                      help="keep SMRM's leg rotations as they come (default: a foot that "
                           "stops on the ground is held there, the leg bent to reach it)")
    feet.add_argument("--foot-leash", type=positive_float, default=None, metavar="METRES",
                      help="how far a planted toe may be held from where SMRM puts it "
                           f"(default {FootLock().max_offset:g}): longer holds feet firmer "
                           "and bends the legs more; 0.1 slides about as little as the "
                           "ground truth on the test benchmark, for 4 mm of PA-MPJPE "
                           "(README, Results)")
    retarget.add_argument("--mirror-source", action="store_true",
                          help="average SKR's skeleton of each source cloud with the one it "
                               "finds on the cloud's mirror image: a few millimetres more "
                               "accurate, SKR twice as long")
    retarget.add_argument("--no-refine", action="store_true",
                          help="use SKR's joints as they are (default: each is moved by the "
                               "weights' joint refiner, which looks at the points around it)")
    retarget.add_argument("--no-denoise", action="store_true",
                          help="hand SMRM the smoothed source skeleton (default: the weights' "
                               "denoiser, trained on SKR's skeletons of moving bodies, takes "
                               "out most of its jitter first)")
    retarget.add_argument("--no-rest-pose", action="store_true",
                          help="align the target's T-pose bones with the source's as they "
                               "are (default: the weights' rest-pose model first turns them by "
                               "how the two bodies' proportions change their rest poses)")
    retarget.add_argument("--no-facing-check", action="store_true",
                          help="take every SKR skeleton as it comes (default: one that faces "
                               "far from the heading kept so far is read again from the cloud "
                               "turned half round, and the reading facing nearer kept)")
    retarget.add_argument("--viewpoint", type=viewpoint_text, default=None, metavar="X,Y,Z",
                          help="where the one depth camera that saw every source cloud stood, "
                               "in the source's units and axes (its points' frame): the source "
                               "fit then fits only the side of the body the camera sees "
                               "(default: clouds over the whole body; docs/single_view.md; "
                               "write --viewpoint=-1,2,3 when X is negative)")
    retarget.add_argument("--source-fit", action="store_true",
                          help="track a calibrated body model in every source cloud after SKR "
                               "and hand its joints on, neither smoothed nor denoised (the "
                               "fitted preset's stage, on any preset; docs/source_fit.md)")
    again = retarget.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue an interrupted run in --out from its last checkpoint "
                       "(same arguments); the result is the same as an uninterrupted run's")
    again.add_argument("--overwrite", action="store_true",
                       help="replace the files of an earlier run in --out (without it, a "
                       "folder holding them is refused)")


def build_parser():
    parser = OneLineErrors(
        prog="minretarget", description="Correspondence-free online human motion retargeting: "
        "make a T-pose target body perform a source motion.")
    parser.add_argument("--version", action="version", version=f"minretarget {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = commands.add_parser("demo", help="retarget the shipped sample, write every output "
                               "and a preview")
    demo.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    demo.add_argument("--weights", default=None, help=WEIGHTS_HELP)
    demo.add_argument("--threads", type=int_at_least(1), default=1, help=THREADS_HELP)
    demo.set_defaults(run=_demo)

    retarget = commands.add_parser(
        "retarget", help="retarget a motion onto a target body",
        description="Retarget SOURCE (a folder of per-frame .ply/.obj/.xyz/.npy point clouds, "
        "a .npy/.npz array (T, P, 3) of frames, or a .bvh skeleton motion) onto TARGET (a "
        ".ply/.obj mesh or point cloud, a .xyz/.npy (V, 3) file, a .npz holding "
        "target_points (a result's), points or vertices, with their faces, in T-pose; or the "
        "name of a shipped body: minretarget bodies).")
    add_retarget_arguments(retarget)
    retarget.set_defaults(run=_retarget)

    from .batch import add_command         # here: batch imports this module
    add_command(commands)

    preview = commands.add_parser("render", help="draw a result's source and target over time")
    preview.add_argument("result", help="a result.npz written by retarget or demo")
    preview.add_argument("--out", required=True, help="FILE.png (a strip) or FILE.gif")
    preview.set_defaults(run=_render)

    bodies = commands.add_parser("bodies", help="list the target bodies that ship with "
                                 "minretarget (a TARGET may name one)")
    bodies.set_defaults(run=_bodies)

    inspect = commands.add_parser("inspect", help="show how a BVH's joints map onto the 22 "
                                  "canonical joints")
    inspect.add_argument("bvh", help="a .bvh or .bvh.gz file")
    inspect.add_argument("--skeleton-map", metavar="FILE.json", default=None,
                         help="as for retarget")
    inspect.set_defaults(run=_inspect)

    warmup = commands.add_parser("warmup", help="compile the kernels (about 15-25 s, once per "
                                 "machine and release: later runs load them from a cache)")
    warmup.add_argument("--weights", default=None, help=WEIGHTS_HELP)
    warmup.set_defaults(run=_warmup)
    return parser


def _print_warning(message, category, filename, lineno, file=None, line=None):
    """Show an InputWarning as one ``minretarget: warning:`` line, others as Python does;
    above the progress bar, if one is running."""
    text = (f"minretarget: warning: {message}" if issubclass(category, InputWarning) else
            warnings.formatwarning(message, category, filename, lineno, line).rstrip())
    try:
        from tqdm import tqdm
    except ImportError:
        print(text, file=sys.stderr)
    else:
        tqdm.write(text, file=sys.stderr)


COMPILING = "Compiling kernels once (about 15-25 s; cached afterwards)"


def _compiling():
    print(COMPILING, file=sys.stderr, flush=True)


def _kept(args):
    """After a failed run: where the run it was replacing (``--overwrite``) is kept."""
    kept = Path(getattr(args, "out", None) or ".") / PREVIOUS_RUN
    if args.command not in ("retarget", "demo") or not kept.is_dir():
        return ""
    return (f" (the run that was in {args.out} before is kept in {kept} until a run there "
            "completes)")


def main(argv=None):
    """Run the command line; returns the exit status: 0 ok, 1 bad input (or an error of the
    system, e.g. a full disk), 3 missing extra, 4 internal error, 130 interrupted (argparse
    exits with 2 for bad arguments). Messages, never tracebacks, unless
    MINRETARGET_TRACEBACK=1."""
    args = build_parser().parse_args(argv)
    try:
        threads = getattr(args, "threads", None)
        with warnings.catch_warnings(), on_first_compile(_compiling), (
                contextlib.nullcontext() if threads is None else blas_threads(threads)):
            warnings.simplefilter("always", InputWarning)
            warnings.showwarning = _print_warning
            args.run(args)
    except MissingExtra as error:
        print(f"minretarget: {error}", file=sys.stderr)
        return 3
    except (ValueError, OSError) as error:
        print(f"minretarget: error: {error}{_kept(args)}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"minretarget: error: out of memory{_kept(args)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        # A run stopped before its first frame leaves no checkpoint: nothing to resume.
        resumable = args.command == "retarget" and (Path(args.out) / CHECKPOINT).is_file()
        print("minretarget: interrupted" + ("; the frames done are kept: add --resume to "
                                            "continue" if resumable else "") + _kept(args),
              file=sys.stderr)
        return 130
    except Exception as error:  # noqa: BLE001  (a bug: say so in one line, not a traceback)
        if os.environ.get("MINRETARGET_TRACEBACK") == "1":
            raise
        print(f"minretarget: internal error: {type(error).__name__}: {error} (please report "
              "it; MINRETARGET_TRACEBACK=1 shows where)", file=sys.stderr)
        return 4
    return 0
