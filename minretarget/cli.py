"""The ``minretarget`` command: retarget files, draw previews, run the demo.

    minretarget demo [--out DIR] [--weights FILE]
    minretarget retarget SOURCE TARGET --out DIR [--format ply,obj,npz,glb,bvh] [--fps F]
                         [--up-axis y|z] [--units m|cm|mm] [--points N] [--weights FILE]
    minretarget render RESULT --out FILE.png|FILE.gif

SOURCE and TARGET kinds: ``minretarget.sources``; outputs: ``minretarget.outputs``; units and
axes: ``minretarget.units``. Needs the ``cli`` extra (``pip install "minretarget[cli]"``):
without it the command says so instead of failing with a traceback. Bad input (a missing or
malformed file, a wrong shape) is reported in one line naming the file, exit status 1.
"""
import argparse
import sys
import time
from pathlib import Path

from . import __version__
from .extras import MissingExtra, require
from .outputs import FORMATS, frame_name, open_writers, parse_formats
from .render import render
from .retargeter import Retargeter
from .sources import load_sample, open_source, read_target
from .units import CANONICAL, UNITS, UP_AXES, make_space
from .weights import DEFAULT_WEIGHTS

DEFAULT_FORMATS = "ply,npz,glb,bvh"


def load_retargeter(weights=None):
    """A Retargeter with ``weights`` (None: the shipped default), or FileNotFoundError saying
    what to do when the default weights are not installed."""
    if weights is None and not DEFAULT_WEIGHTS.is_file():
        raise FileNotFoundError(
            f"the default weights are not installed ({DEFAULT_WEIGHTS} is missing): they ship "
            "with minretarget once the model is trained. Pass --weights FILE to use a weights "
            "file of your own (python -m training.train ... exports one).")
    return Retargeter.from_weights(weights)


def set_target(retargeter, points, faces, name):
    """``retargeter.set_target(points, faces)``, its errors prefixed with the target's name."""
    try:
        retargeter.set_target(points, faces)
    except ValueError as error:
        raise ValueError(f"{name}: {error}") from None


def retarget_to_files(retargeter, source, out_dir, formats, space, progress=True):
    """Retarget every frame of ``source`` onto the retargeter's target; write ``formats``.

    Args:
        retargeter: Retargeter with weights and a target (``set_target``).
        source: ``sources.Source`` (canonical metres).
        out_dir: output folder; formats: names from ``outputs.FORMATS``.
        space: ``units.Space`` of the outputs.
        progress: show a tqdm progress bar on stderr.
    Returns:
        the number of frames written.
    """
    if source.count == 0:
        raise ValueError(f"{source.path}: holds no frames")
    tqdm = require("tqdm", "the progress bar").tqdm
    step = retargeter.step if source.kind == "points" else retargeter.step_skeleton
    with open_writers(out_dir, formats, retargeter.target, source.count, source.fps,
                      space) as write:
        frames = tqdm(source.frames, total=source.count, unit="frame", desc="retargeting",
                      disable=not progress, file=sys.stderr)
        for index, data in enumerate(frames):
            try:
                frame = step(data)
            except ValueError as error:
                raise ValueError(f"{source.path}: frame {index}: {error}") from None
            write(frame)
    return source.count


def _written(out_dir, formats, count):
    names = [f"{frame_name(0, f)} .. {frame_name(count - 1, f)}" for f in formats
             if f in ("ply", "obj")]
    names += [f"result.{f}" for f in formats if f not in ("ply", "obj")]
    return f"{out_dir}: " + ", ".join(names)


def _retarget(args):
    start = time.perf_counter()
    space = make_space(args.units, args.up_axis)
    formats = parse_formats(args.format)
    retargeter = load_retargeter(args.weights)
    target_points, target_faces = read_target(args.target, space)
    set_target(retargeter, target_points, target_faces, args.target)
    source = open_source(args.source, space, fps=args.fps, points=args.points)
    count = retarget_to_files(retargeter, source, args.out, formats, space)
    print(f"retargeted {count} frames at {source.fps:g} fps in "
          f"{time.perf_counter() - start:.1f} s; wrote {_written(args.out, formats, count)}")


def _render(args):
    count = render(args.result, args.out)
    print(f"drew {count} frames into {args.out}")


def _demo(args):
    start = time.perf_counter()
    retargeter = load_retargeter(args.weights)
    source, target_points, target_faces, metadata = load_sample()
    print(f"demo: {metadata['description']}")
    out = Path(args.out)
    set_target(retargeter, target_points, target_faces, "the sample's target")
    count = retarget_to_files(retargeter, source, out, FORMATS, CANONICAL)
    clouds = load_sample()[0].frames                # a fresh pass over the source clouds
    render(out / "result.npz", out / "preview.png", source_points=clouds)
    print(f"retargeted {count} frames in {time.perf_counter() - start:.1f} s; wrote "
          f"{_written(out, FORMATS, count)}, preview.png")


def _positive_int(text):
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def _positive_float(text):
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def build_parser():
    parser = argparse.ArgumentParser(
        prog="minretarget", description="Correspondence-free online human motion retargeting: "
        "make a T-pose target body perform a source motion.")
    parser.add_argument("--version", action="version", version=f"minretarget {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    weights_help = "weights .npz (default: the weights shipped with minretarget)"

    demo = commands.add_parser("demo", help="retarget the shipped sample, write every output "
                               "and a preview")
    demo.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    demo.add_argument("--weights", default=None, help=weights_help)
    demo.set_defaults(run=_demo)

    retarget = commands.add_parser(
        "retarget", help="retarget a motion onto a target body",
        description="Retarget SOURCE (a folder of per-frame .ply/.obj/.xyz/.npy point clouds, "
        "a .npy/.npz array (T, P, 3) of frames, or a .bvh skeleton motion) onto TARGET (a "
        ".ply/.obj mesh or point cloud, or a .xyz/.npy (V, 3) file, in T-pose).")
    retarget.add_argument("source", help="SOURCE motion")
    retarget.add_argument("target", help="TARGET body in T-pose")
    retarget.add_argument("--out", required=True, help="output folder")
    retarget.add_argument("--format", default=DEFAULT_FORMATS,
                          help=f"comma-separated outputs among {','.join(FORMATS)} "
                          f"(default {DEFAULT_FORMATS})")
    retarget.add_argument("--fps", type=_positive_float, default=None,
                          help="source frame rate (default 30 for clouds, the header's for "
                          "BVH, which is resampled to 30)")
    retarget.add_argument("--up-axis", choices=tuple(UP_AXES), default="y",
                          help="up axis of the input and output files (z: Z up, facing -Y); "
                          ".glb is always Y up")
    retarget.add_argument("--units", choices=tuple(UNITS), default="m",
                          help="length unit of the input and output files; .glb is always m")
    retarget.add_argument("--points", type=_positive_int, default=None,
                          help="resample every source cloud to N points (random subset, fixed "
                          "seed)")
    retarget.add_argument("--weights", default=None, help=weights_help)
    retarget.set_defaults(run=_retarget)

    preview = commands.add_parser("render", help="draw a result's source and target over time")
    preview.add_argument("result", help="a result.npz written by retarget or demo")
    preview.add_argument("--out", required=True, help="FILE.png (a strip) or FILE.gif")
    preview.set_defaults(run=_render)
    return parser


def main(argv=None):
    """Run the command line; returns the exit status (0 ok, 1 bad input, 3 missing extra)."""
    args = build_parser().parse_args(argv)
    try:
        args.run(args)
    except MissingExtra as error:
        print(f"minretarget: {error}", file=sys.stderr)
        return 3
    except (ValueError, OSError) as error:
        print(f"minretarget: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("minretarget: interrupted", file=sys.stderr)
        return 130
    return 0
