"""The worst test sequence, before and after: the regressed preset against the fitted default.

    python benchmarks/worst_sequence.py --report [--results FILE] [--weights FILE]
                                        [--data DIR] [--out DIR]

--report is required: the picture and its numbers are of the test split, which is run once per
release, for the report, and never selects anything (accuracy.TEST_SPLIT_RULE). This script
selects nothing either: it reads the release's saved test run (FILE, default
benchmarks/results/accuracy_test_fitted.json, written by ``accuracy.py --report --json``) and
draws the sequence that WORST_RULE names there:

    the sequence where the regressed preset's result has the most crossed-legs frames
    (``skeleton["regressed preset"]["crossed_legs"]``); ties: the higher regressed PA-MPJPE,
    then the first in the file.

That sequence (DIR/test/<name>.npz, built data) is retargeted online, frame by frame, onto its
own target body (the one in the sequence file) with the shipped weights (or FILE), twice:
``Retargeter(weights, "regressed")`` (the default until this release, "before") and
``Retargeter(weights, "fitted")`` (the new default, "after"). OUT (default docs/) gets ONE
picture, worst_sequence.png:
    top       six frames (``strip_frames``: the middles of the regressed preset's three
              longest runs of crossed-legs frames and of the fitted preset's three, in time
              order, filled with evenly spread frames): the source cloud with the true source skeleton (green); below it the
              target's points and skeleton (orange) for "regressed", then for "fitted", each
              with the ground-truth target skeleton (green) moved onto the result's pelvis;
              a panel whose legs are crossed says so in red
    bottom    top-down (x-z ground plane) paths of both toes over the whole sequence: the
              truth's, the regressed preset's and the fitted preset's (the truth's faint under
              both), with the frames where that result's legs are crossed
              (``metrics.crossed_feet``) marked x
and the figures it shows are printed for both presets: crossed-legs frames, toe speed on the
truth's contact steps (``metrics.foot_contacts`` at accuracy.CONTACT_HEIGHT and
``metrics.foot_speeds``, as accuracy.py's feet row), the truth's own, MPJPE and PA-MPJPE.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import (add_report_option, command_line, feet_on_contacts,  # noqa: E402
                      load_measured, load_results, load_sequence, refuse_test_split,
                      sequence_metrics)
from renders import retarget, shrink  # noqa: E402

from minretarget.atomic import atomic_write  # noqa: E402
from minretarget.conventions import FPS, JOINT_INDEX, UP_AXIS  # noqa: E402
from minretarget.metrics import FOOT_JOINTS, crossed_feet  # noqa: E402
from minretarget.render import (_RESULT_COLOR, _TRUTH_COLOR, MAX_POINTS,  # noqa: E402
                                STRIP_FRAMES, _draw, _limits)

WORST_RULE = ("the sequence where the regressed preset's result has the most crossed-legs "
              "frames; ties: the higher regressed PA-MPJPE, then the first in the file")
PRESETS = (("regressed", "regressed preset"), ("fitted", "model"))   # (preset, its JSON row)
DEFAULT_RESULTS = "benchmarks/results/accuracy_test_fitted.json"
PNG_NAME = "worst_sequence.png"
_TOE_COLORS = {"left_foot": "tab:red", "right_foot": "tab:blue"}


def pick_worst(per_sequence):
    """The entry of a saved run's ``per_sequence`` that ``WORST_RULE`` names."""
    if not per_sequence:
        raise ValueError("the saved run has no sequences")
    row = dict(PRESETS)["regressed"]
    # max() keeps the first of equal keys: "then the first in the file".
    return max(per_sequence, key=lambda r: (r["skeleton"][row]["crossed_legs"],
                                            r["metrics"][row]["PA-MPJPE"]))


def runs_of(flags):
    """(T,) bool -> list of (start, stop) of its runs of True, longest first (ties: earlier)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(flags, np.int8), [0]])))
    runs = list(zip(edges[::2].tolist(), edges[1::2].tolist()))
    return sorted(runs, key=lambda run: (run[0] - run[1], run[0]))


def strip_frames(crossed, count=STRIP_FRAMES):
    """[(T,) bool, ...] each preset's crossed-legs frames -> up to ``count`` sorted frame
    indices: for each preset in turn, the middles of its longest runs of crossed frames
    (``count // len(crossed)`` each), then evenly spread frames until there are ``count``."""
    total = len(crossed[0])
    wanted, chosen = min(count, total), []
    for flags in crossed:
        middles = [(start + stop - 1) // 2 for start, stop in runs_of(flags)]
        chosen += [t for t in middles if t not in chosen][:count // len(crossed)]
    spread = np.linspace(0, total - 1, count).round().astype(int).tolist()
    for frame in [*spread, *range(total)]:     # short sequences: any frame left
        if len(chosen) >= wanted:
            break
        if frame not in chosen:
            chosen.append(frame)
    return sorted(chosen)


def figures(runs, sequence):
    """{preset: {crossed_legs, toe_speed_on_truth_contacts, MPJPE, PA-MPJPE}} and the truth's
    toe speed on its own contacts, for ``runs`` {preset: (joints, vertices)}."""
    truth = sequence["target_joints"]
    feet = feet_on_contacts(runs, sequence)             # {name: [sum of speeds, steps]}
    metrics = sequence_metrics(runs, sequence)
    out = {name: {"crossed_legs": int(crossed_feet(joints, truth).sum()),
                  "toe_speed_on_truth_contacts": feet[name][0] / max(1, feet[name][1]),
                  "MPJPE": metrics[name]["MPJPE"], "PA-MPJPE": metrics[name]["PA-MPJPE"]}
           for name, (joints, _) in runs.items()}
    truth_feet = feet["ground truth"]
    return out, truth_feet[0] / max(1, truth_feet[1])


_ACROSS = [axis for axis in range(3) if axis != UP_AXIS]        # the ground plane: x, z
_TOES = [JOINT_INDEX[name] for name in FOOT_JOINTS]


def _toe_paths(axes, joints, crossed, title, limits, reference=None):
    """Top-down (x, z) paths of both toes within ``limits`` ((x0, x1), (z0, z1));
    ``crossed`` frames marked x; ``reference`` joints' paths faint under them."""
    across, toes = _ACROSS, _TOES
    if reference is not None:
        for toe in toes:
            axes.plot(*reference[:, toe][:, across].T, color="0.8", lw=0.8)
    for name, toe in zip(FOOT_JOINTS, toes):
        path = joints[:, toe][:, across]
        axes.plot(*path.T, color=_TOE_COLORS[name], lw=0.8, label=name.replace("_foot", " toe"))
        if crossed is not None and crossed.any():
            axes.scatter(*path[crossed].T, marker="x", color="black", s=9, linewidths=0.7,
                         zorder=3, label="legs crossed" if name == FOOT_JOINTS[0] else None)
    axes.set_title(title, fontsize=8)
    axes.set_xlim(*limits[0])
    axes.set_ylim(*limits[1])
    axes.set_aspect("equal")
    axes.tick_params(labelsize=6)
    axes.set_xlabel("x (m)", fontsize=7)


def draw_figure(sequence, runs, png, title=None):
    """Write the before/after picture of one sequence (see the module's docstring) to ``png``.

    Args:
        sequence: a test sequence (``accuracy.load_sequence``): source_points,
            source_joints, target_joints.
        runs: {"regressed": (joints, vertices), "fitted": (joints, vertices)}, (T, 22, 3) and
            (T, V, 3) metres.
        png: the output path (written atomically, then reduced to a palette).
        title: optional line above the picture.
    Returns:
        the strip's frame indices.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    truth = np.asarray(sequence["target_joints"], np.float64)
    crossed = {name: crossed_feet(joints, truth) for name, (joints, _) in runs.items()}
    shown = strip_frames(list(crossed.values()))
    subset = np.random.default_rng(0).permutation(next(iter(runs.values()))[1].shape[1])
    subset = subset[:MAX_POINTS]
    source = [{"source_joints": np.asarray(sequence["source_joints"][t], np.float64),
               "source_points": np.asarray(sequence["source_points"][t], np.float64),
               "truth_joints": None} for t in shown]
    panels = {name: [{"joints": np.asarray(joints[t], np.float64),
                      "vertices": np.asarray(vertices[t][subset], np.float64),
                      "truth_joints": truth[t] - truth[t, :1] + joints[t, :1]} for t in shown]
              for name, (joints, vertices) in runs.items()}
    source_limits = _limits(source, "source_joints", "source_points")
    result_limits = _limits([f for frames in panels.values() for f in frames],
                            "joints", "vertices")
    heights = [(limits[1][1] - limits[1][0]) / (2 * limits[0])
               for limits in (source_limits, *[result_limits] * len(runs))]
    paths_height = 1.1 * sum(heights) / len(heights)
    columns = len(shown)
    figure = Figure(figsize=(2.0 * max(columns, 3), 2.0 * (sum(heights) + paths_height) + 0.8),
                    dpi=100)
    grid = figure.add_gridspec(len(heights) + 1, 6, height_ratios=[*heights, paths_height])
    width = 6 // max(1, columns)
    for column, (t, frame) in enumerate(zip(shown, source)):
        axes = figure.add_subplot(grid[0, column * width:(column + 1) * width])
        _draw(axes, frame["source_joints"], frame["source_points"], _TRUTH_COLOR,
              source_limits, shaded=False)
        axes.set_title(f"frame {t} (t = {t / FPS:.2f} s)", fontsize=8)
        if column == 0:
            axes.set_ylabel("source cloud", fontsize=8)
        for row, (name, frames) in enumerate(panels.items(), start=1):
            axes = figure.add_subplot(grid[row, column * width:(column + 1) * width])
            _draw(axes, frames[column]["joints"], frames[column]["vertices"], _RESULT_COLOR,
                  result_limits, shaded=True, truth=frames[column]["truth_joints"])
            if crossed[name][t]:
                axes.text(0.03, 0.03, "legs crossed", color="tab:red", fontsize=7,
                          transform=axes.transAxes)
            if column == 0:
                axes.set_ylabel(name, fontsize=8)
    bottom = len(heights)
    ground = np.concatenate([np.asarray(joints)[:, _TOES][..., _ACROSS].reshape(-1, 2)
                             for joints in (truth, *(joints for joints, _ in runs.values()))])
    low, high = ground.min(axis=0), ground.max(axis=0)
    margin = 0.05 * (high - low).max() + 0.02
    limits = tuple((a - margin, b + margin) for a, b in zip(low, high))
    axes = figure.add_subplot(grid[bottom, 0:2])
    _toe_paths(axes, truth, None, "ground truth: toes from above", limits)
    axes.set_ylabel("z (m)", fontsize=7)
    for k, (name, (joints, _)) in enumerate(runs.items(), start=1):
        axes = figure.add_subplot(grid[bottom, 2 * k:2 * k + 2])
        _toe_paths(axes, np.asarray(joints, np.float64), crossed[name],
                   f"{name}: {int(crossed[name].sum())} frames with the legs crossed",
                   limits, reference=truth)
    axes.legend(fontsize=6, loc="best")
    if title:
        figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    with atomic_write(png) as file:
        FigureCanvasAgg(figure).print_png(file)
    shrink(png)
    return shown


def table(numbers, truth_speed):
    lines = ["| preset | crossed-legs frames | toes on the truth's contacts (m/s) | MPJPE (m) "
             "| PA-MPJPE (m) |", "|---|---|---|---|---|"]
    for name, row in numbers.items():
        lines.append(f"| {name} | {row['crossed_legs']} | "
                     f"{row['toe_speed_on_truth_contacts']:.3f} | {row['MPJPE']:.4f} | "
                     f"{row['PA-MPJPE']:.4f} |")
    lines.append(f"| ground truth | 0 | {truth_speed:.3f} | | |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", default=DEFAULT_RESULTS,
                        help="the release's saved test run (accuracy.py --report --json)")
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--data", default="data", help="built data directory (uses DIR/test)")
    parser.add_argument("--out", default="docs", help=f"output folder (gets {PNG_NAME})")
    add_report_option(parser)
    args = parser.parse_args(argv)
    refuse_test_split(parser, args)
    saved = load_results(args.results)
    if saved["split"] != "test":
        parser.error(f"{args.results} is a run of {saved['split']!r}, not of the test split")
    worst = pick_worst(saved["per_sequence"])
    path = Path(args.data) / "test" / f"{worst['sequence']}.npz"
    if not path.is_file():
        parser.error(f"no {path}: build the test data first (python -m training.data build "
                     "--only test)")
    weights, record = load_measured(args.weights)
    if record["weights_sha256"] != saved.get("weights_sha256"):
        print(f"note: these weights are not the ones {args.results} measured", flush=True)
    sequence = load_sequence(path)
    if str(sequence["target_body"]) != worst["target_body"]:
        raise ValueError(f"{path}: target body {sequence['target_body']}, the saved run's "
                         f"{worst['target_body']}")
    print(f"worst test sequence ({WORST_RULE}): {worst['sequence']} onto "
          f"{worst['target_body']}, {worst['frames']} frames", flush=True)
    started, runs = time.perf_counter(), {}
    for name, _ in PRESETS:
        joints, vertices, _, seconds = retarget(weights, sequence, name)
        runs[name] = (joints, vertices)
        print(f"{name}: {1e3 * seconds / len(joints):.1f} ms per frame", flush=True)
    numbers, truth_speed = figures(runs, sequence)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    png = out / PNG_NAME
    shown = draw_figure(sequence, runs, png, title=(
        f"{worst['sequence']} ({worst['category']}) onto {worst['target_body']}: source "
        "cloud (green: its true skeleton);\nresult (orange) of the regressed preset (before) "
        "and the fitted default (after), ground truth on the result's pelvis (green)"))
    print(f"{png} ({png.stat().st_size // 1024} kB), frames {shown}")
    print(table(numbers, truth_speed))
    print("\nthe saved run's figures for this sequence:")
    print(table({name: {"crossed_legs": worst["skeleton"][row]["crossed_legs"],
                        "toe_speed_on_truth_contacts": worst["feet"][row][0]
                        / max(1, worst["feet"][row][1]),
                        "MPJPE": worst["metrics"][row]["MPJPE"],
                        "PA-MPJPE": worst["metrics"][row]["PA-MPJPE"]}
                 for name, row in PRESETS},
                worst["feet"]["ground truth"][0] / max(1, worst["feet"]["ground truth"][1])))
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    command_line(main)
