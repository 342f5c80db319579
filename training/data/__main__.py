"""Command line: build the datasets, or draw a preview of bodies walking.

    python -m training.data build (--cmu ../shared/data/cmu | --pack FILE) --out data
                                  [--bodies N] [--frames N]
                                  [--seed S] [--points P] [--skin-samples N] [--skin-points Q]
                                  [--clip-stride K] [--clip-frames C] [--category-power P]
                                  [--seated-fraction F] [--crossed-fraction F]
                                  [--include-broken] [--keep-broken-ankles]
                                  [--body-cache DIR] [--only KIND [KIND ...]]
    python -m training.data pack --cmu ../shared/data/cmu --out data/pack.npz [--bodies N]
                                 [--include-broken] [--keep-broken-ankles]
                                 [--body-cache DIR]
    python -m training.data preview --out preview.png [--cmu DIR] [--trial 07_01]
    python -m training.data sample --out minretarget/data/sample.npz [--cmu DIR] [--trial 08_01]
                                   [--points P] [--seed S]
    python -m training.data bodies --out minretarget/data/bodies.npz
    python -m training.data body --out BODY.obj|.ply [--gender G] [--age A] [--weight W]
                                 [--height H] [--muscle M] [--proportions P]
"""
import argparse
import math
import sys
import time
from pathlib import Path

from minretarget.cli import int_at_least

from .datasets import DATASETS, BuildConfig, build, cmu_motions, first_bodies

_DEFAULTS = BuildConfig()


def _fraction(text):
    value = _finite_float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return value


def _size(num_bytes):
    """Decimal units (1 MB = 10^6 bytes), as the docs quote file sizes."""
    for unit in ("B", "kB", "MB", "GB"):
        if num_bytes < 1000 or unit == "GB":
            return f"{num_bytes:.1f} {unit}" if unit != "B" else f"{num_bytes} B"
        num_bytes /= 1000


def _finite_float(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


def _build(args):
    start = time.perf_counter()
    bodies = None
    if args.pack is not None:         # motions and bodies from a pack (training.data.pack)
        from .pack import load_pack, without_broken_ankles
        try:
            pack = load_pack(args.pack)
        except ValueError as error:
            sys.exit(str(error))
        if args.include_broken and not pack.include_broken:
            sys.exit(f"--include-broken: {args.pack} was packed without the broken captures")
        if args.keep_broken_ankles and not pack.keep_broken_ankles:
            sys.exit(f"--keep-broken-ankles: {args.pack} was packed without the broken feet")
        if not args.keep_broken_ankles:     # an older pack holds them: cut as --cmu would
            pack = without_broken_ankles(pack)
        if args.only is not None and "test" in args.only:
            sys.exit(f"--only test: {args.pack} holds no test split; build it with --cmu")
        args.only = args.only or tuple(kind for kind in DATASETS if kind != "test")
        args.include_broken = pack.include_broken
        motions, actor_hip_height, bodies = pack.motions, pack.actor_hip_height, pack.bodies
    args.only = args.only or DATASETS
    config = BuildConfig(seed=args.seed, bodies=args.bodies, frames=args.frames,
                         points=args.points, skin_samples=args.skin_samples,
                         skin_points=args.skin_points, clip_stride=args.clip_stride,
                         clip_frames=args.clip_frames, category_power=args.category_power,
                         seated_fraction=args.seated_fraction,
                         crossed_fraction=args.crossed_fraction,
                         include_broken=args.include_broken,
                         keep_broken_ankles=args.keep_broken_ankles)
    if args.pack is None:
        motions, actor_hip_height = cmu_motions(args.cmu, include_broken=args.include_broken,
                                                keep_broken_ankles=args.keep_broken_ankles)
    else:
        try:
            bodies = first_bodies(bodies, config)
        except ValueError as error:
            sys.exit(f"--bodies {config.bodies}: {error} by {args.pack}")
    summary = build(motions, actor_hip_height, args.out, config, cache_dir=args.body_cache,
                    datasets=args.only, bodies=bodies)
    counts = summary["counts"]
    print(f"\nbuilt {args.out} in {time.perf_counter() - start:.0f} s "
          f"(datasets {summary['seconds']:.0f} s), {_size(summary['total_bytes'])} in all")
    print(f"  motions: {counts['trials_train']} train / {counts['trials_val']} val / "
          f"{counts['trials_test']} test motions (trials, or runs of them without broken "
          f"feet); {counts['motion_frames_train']} train and "
          f"{counts['motion_frames_val']} val frames at 30 fps; actor hip height "
          f"{actor_hip_height:.3f} m")
    print(f"  bodies: {counts['bodies_train']} train, {counts['bodies_val']} val"
          + (", 8 test" if "test" in args.only else ""))
    for kind, unit in (("skr", "frames"), ("skin", "samples"), ("smrm", "clips"),
                       ("sequences", "frames")):
        if kind not in args.only:
            continue
        sizes = [summary["files"][f"{kind}_{s}.npz"] for s in ("train", "val")]
        print(f"  {kind}: {counts[kind + '_train']} train / {counts[kind + '_val']} val {unit} "
              f"({_size(sizes[0])} + {_size(sizes[1])})")
    if "test" not in args.only:
        return
    test_bytes = sum(v for k, v in summary["files"].items() if k.startswith("test/"))
    print(f"  test: {counts['test_sequences']} sequences, {counts['test_frames']} frames "
          f"({_size(test_bytes)})")


def _pack(args):
    from .pack import make_pack
    arrays = make_pack(args.cmu, args.out, args.bodies, args.include_broken, args.body_cache,
                       keep_broken_ankles=args.keep_broken_ankles)
    splits = arrays["motion_splits"].tolist()
    print(f"wrote {args.out}: {splits.count('train')} train and {splits.count('val')} val "
          f"motions ({len(arrays['motion_root'])} frames), "
          f"{len(arrays['body_names'])} bodies, {_size(Path(args.out).stat().st_size)}")


def _preview(args):
    from . import cmu
    from .preview import render
    trials = {t.name: t for t in cmu.list_trials(args.cmu, include_broken=True)}
    if args.trial not in trials:
        sys.exit(f"no trial {args.trial!r} under {args.cmu}")
    motion = cmu.load_motion(trials[args.trial].path)
    render(motion, float(cmu.cmu_tpose_joints(trials[args.trial].path)[0, 1]), args.out,
           cache_dir=args.body_cache)
    print(f"wrote {args.out}")


def _sample(args):
    from .sample import build_sample, write_sample
    arrays = build_sample(args.cmu, trial=args.trial, points=args.points, seed=args.seed,
                          cache_dir=args.body_cache)
    write_sample(args.out, arrays)
    print(f"wrote {args.out}: {arrays['source_points'].shape[0]} frames, "
          f"{_size(Path(args.out).stat().st_size)}")


def _bodies(args):
    from .sample import build_bodies, write_sample
    arrays = build_bodies(cache_dir=args.body_cache)
    write_sample(args.out, arrays)
    print(f"wrote {args.out}: {', '.join(arrays['names'])}; {_size(Path(args.out).stat().st_size)}")


def _body(args):
    from minretarget.formats.mesh import write_mesh

    from .bodies import get_body
    phenotype = {label: getattr(args, label) for label in PHENOTYPE if getattr(args, label)
                 is not None}
    body = get_body(phenotype, Path(args.out).stem, args.body_cache)
    write_mesh(args.out, body.vertices, body.faces)
    print(f"wrote {args.out}: a T-pose body {body.height:.2f} m tall (metres, +Y up, facing +Z)")


# anny's phenotype values, each in [0, 1] (0.5 when not given): what ``body`` takes.
PHENOTYPE = {"gender": "0 male .. 1 female", "age": "0 baby, 0.25 child, 0.8 about 30 years, "
             "1 old", "weight": "0 thin .. 1 heavy", "height": "0 short .. 1 tall",
             "muscle": "0 .. 1", "proportions": "0 .. 1 (body proportions)"}


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m training.data", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    build_parser = commands.add_parser("build", help="build every dataset (deterministic)")
    source = build_parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--cmu", help="the CMU BVH folder")
    source.add_argument("--pack", help="a data pack (python -m training.data pack) instead of "
                        "the CMU folder and the body cache: every dataset but the test split")
    build_parser.add_argument("--out", required=True, help="output folder")
    for name, help_text in (
            ("seed", "random seed"),
            ("bodies", "training bodies (validation: an eighth, at least 2; paper: 120)"),
            ("frames", "SKR training frames (validation: a tenth; paper: ~65,000)"),
            ("points", "points per source cloud (SKR and test frames)"),
            ("skin_samples", "SKIN training samples (validation: a tenth)"),
            ("skin_points", "surface points per SKIN sample"),
            ("clip_stride", "frames between the starts of consecutive SMRM clips"),
            ("clip_frames", "frames of an SMRM clip")):
        build_parser.add_argument("--" + name.replace("_", "-"),
                                  type=int_at_least(0 if name == "seed" else
                                                    2 if name == "clip_frames" else 1),
                                  default=getattr(_DEFAULTS, name),
                                  help=f"{help_text} (default {getattr(_DEFAULTS, name)})")
    build_parser.add_argument("--category-power", type=_finite_float,
                              default=_DEFAULTS.category_power,
                              help="SKR frames (training and validation): each motion "
                                   "category's share is proportional to its frame count to "
                                   "this power (1: as the motions come; otherwise drawn with "
                                   "replacement; 0: every category alike; default 1)")
    build_parser.add_argument("--seated-fraction", type=_fraction,
                              default=_DEFAULTS.seated_fraction,
                              help="SKR frames (training and validation) whose legs are bent "
                                   "as if seated or crouched (datasets.seated_legs), in [0, 1] "
                                   "(default 0)")
    build_parser.add_argument("--crossed-fraction", type=_fraction,
                              default=_DEFAULTS.crossed_fraction,
                              help="SKR frames (training and validation) with one leg crossed "
                                   "over the other (datasets.crossed_legs), in [0, 1] "
                                   "(default 0)")
    build_parser.add_argument("--include-broken", action="store_true",
                              help="keep the broken captures (cmu.BROKEN_TRIALS), as the "
                                   "shipped weights' data did")
    build_parser.add_argument("--keep-broken-ankles", action="store_true",
                              help="keep the frames whose feet turn further than an ankle can "
                                   "(cmu.broken_ankle_frames), as the shipped weights' data did")
    build_parser.add_argument("--only", nargs="+", choices=DATASETS, default=None,
                              metavar="KIND", help=f"build only these of {DATASETS} "
                              "(e.g. smrm with --clip-frames 60 into another folder)")
    pack_parser = commands.add_parser("pack", help="pack the training and validation motions "
                                      "and bodies into one file (for a machine without them)")
    pack_parser.add_argument("--cmu", required=True, help="the CMU BVH folder")
    pack_parser.add_argument("--out", required=True, help="output .npz")
    pack_parser.add_argument("--bodies", type=int_at_least(1), default=_DEFAULTS.bodies,
                             help="training bodies, with the validation bodies a build of "
                             f"that many uses (default {_DEFAULTS.bodies})")
    pack_parser.add_argument("--include-broken", action="store_true",
                             help="keep the broken captures (cmu.BROKEN_TRIALS)")
    pack_parser.add_argument("--keep-broken-ankles", action="store_true",
                             help="keep the frames with broken feet (cmu.broken_ankle_frames)")
    preview_parser = commands.add_parser("preview", help="draw bodies walking into a png")
    preview_parser.add_argument("--out", required=True, help="output .png")
    preview_parser.add_argument("--cmu", default="../shared/data/cmu", help="the CMU BVH folder")
    preview_parser.add_argument("--trial", default="07_01", help="CMU trial to play (a walk)")
    sample_parser = commands.add_parser("sample", help="write the demo's sample .npz")
    sample_parser.add_argument("--out", required=True, help="output .npz "
                               "(the shipped one: minretarget/data/sample.npz)")
    sample_parser.add_argument("--cmu", default="../shared/data/cmu", help="the CMU BVH folder")
    sample_parser.add_argument("--trial", default="08_01", help="CMU test-split trial (a walk)")
    sample_parser.add_argument("--points", type=int_at_least(64), default=2048,
                               help="points per cloud")
    sample_parser.add_argument("--seed", type=int_at_least(0), default=0, help="random seed")
    bodies_parser = commands.add_parser("bodies", help="write the shipped target bodies "
                                        "(minretarget/data/bodies.npz)")
    bodies_parser.add_argument("--out", required=True, help="output .npz")
    body_parser = commands.add_parser("body", help="write one T-pose body made with anny, as "
                                      "a TARGET for minretarget retarget")
    body_parser.add_argument("--out", required=True, help="output .obj or .ply")
    for label, meaning in PHENOTYPE.items():
        body_parser.add_argument(f"--{label}", type=_fraction, default=None,
                                 help=f"anny's {label}: {meaning} (default 0.5)")
    for sub in (build_parser, pack_parser, preview_parser, sample_parser, bodies_parser,
                body_parser):
        sub.add_argument("--body-cache", default=None,
                         help="body cache folder (default $MINRETARGET_CACHE/bodies or "
                              "~/.cache/minretarget/bodies)")
    args = parser.parse_args(argv)
    try:
        {"build": _build, "pack": _pack, "preview": _preview, "sample": _sample,
         "bodies": _bodies, "body": _body}[args.command](args)
    except (ValueError, OSError) as error:    # bad input: one line, not a traceback
        sys.exit(f"{parser.prog} {args.command}: error: {error}")


if __name__ == "__main__":
    main()
