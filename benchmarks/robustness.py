"""Robustness of the runtime to its input: accuracy against source point count, point noise and
dropped frames (issue 4, item 4).

    OMP_NUM_THREADS=1 python benchmarks/robustness.py --report [--weights FILE] [--data DIR]
                                                      [--out DIR] [--json OUT.json] [--frames N]
                                                      [--seed S]

--report is required: the sweep scores test sequences, and the test split is run once per
release, for the report, and never selects anything (accuracy.TEST_SPLIT_RULE).

(OMP_NUM_THREADS=1: with another process on one of the two cores, NumPy's two BLAS threads
wait on each other and the sweep takes twice as long.)

Sequences: ``accuracy.select_sequences(paths, quick=True)`` (the first two test sequences of each
motion category), each cut to its first ``--frames`` frames. Each condition runs
``accuracy.run_sequence`` (the runtime, online, frame by frame) and scores its ``model`` and
``analytic`` rows with ``accuracy.sequence_metrics`` (``minretarget.metrics.evaluate``; the
other rows are not computed). Sweeps, one variable at a time, the
others at the benchmark's input (its stored clouds, no noise, no drop):
    points   points per source cloud: 256 ... 13,718 (the anny mesh's vertex count). The stored
             count (2048) uses the stored clouds; every other count re-samples each frame
             area-uniformly from the posed source body surface, as the data build does
             (bodies.posed_clouds with the file's rotations and source root, on the cached test
             body named by ``source_body``), so 13,718 is a dense
             surface sample, not the mesh vertices themselves.
    noise    i.i.d. Gaussian noise per point and axis on the stored clouds: sigma 0 ... 2 cm.
    drop     a seeded random fraction (0 ... 50 %) of frames removed from the stream; the model
             sees the kept frames only, and every metric is taken on the kept frames against
             their ground truth. Acc and PA-Acc stay metres per frame^2 at 30 fps: they are
             averaged over the kept frames whose two neighbours in the original stream were
             kept too, so no second difference spans a gap (NaN if there is none). As the
             kept frames differ from the whole sequence, each drop value is also shown for
             the undropped stream scored on the same kept frames ("every frame seen", dotted):
             the gap between the two is what dropping costs.
Within a sweep every value of a sequence draws from the same seed (common random numbers): the
noise is one standard normal draw scaled by sigma, and the frames dropped at 10 % are among
those dropped at 25 %. Results are means over sequences weighted by the frames each metric
averages. Writes ``robustness_{points,noise,drop}.png`` to --out, prints a table per sweep and
the wall time, and writes every number to --json. Needs the data build (``data/test``) and its
cached test bodies (``training.data.bodies``, which names them through anny).
"""
import argparse
import json
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np

from accuracy import (add_report_option, command_line, load_measured, load_sequence,
                      refuse_test_split, run_sequence, select_sequences, sequence_metrics,
                      write_text)
from minretarget.atomic import atomic_write
from minretarget.metrics import (ACCELERATION_FRAMES, METRIC_NAMES, acceleration_error,
                                 procrustes_align)

sys.path.insert(1, str(Path(__file__).resolve().parent.parent))   # `training`, from the checkout
from training.data.bodies import benchmark_bodies, posed_clouds  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)

POINT_COUNTS = (256, 512, 1024, 2048, 4096, 8192, 13_718)
NOISE_SIGMAS = (0.0, 0.0025, 0.005, 0.01, 0.015, 0.02)        # metres
DROP_FRACTIONS = (0.0, 0.1, 0.25, 0.5)
ROWS = ("model", "analytic")
# The benchmark's own input (stored clouds, no noise, no drop), and what the drop sweep calls
# its rows restricted to the kept frames: the same frames scored, the stream left whole.
BENCHMARK_INPUT = (None, 0.0, 0.0)
REFERENCE = "every frame seen"
# The per-frame arrays that run_sequence and sequence_metrics read.
FRAME_KEYS = ("source_points", "source_joints", "target_joints", "target_points")
# What each figure shows: metric, its scale to the plotted unit, the axis label.
PANELS = (("MPJPE", 100, "MPJPE (cm)"), ("PA-MPJPE", 100, "PA-MPJPE (cm)"),
          ("MPVD", 100, "MPVD (cm)"), ("Acc", 100, "Acc (cm / frame², 30 fps)"))
SWEEP_AXES = {"points": "source points per frame", "noise": "noise sigma per axis (cm)",
              "drop": "frames dropped (%)"}
DEFAULT_FRAMES = 40          # 13 sequences x 40 frames: about 10 minutes on 2 busy cores


# ----------------------------------------------------------------------------- perturbations

def add_noise(points, sigma, rng):
    """(..., P, 3) points, metres -> the same plus i.i.d. N(0, sigma^2) per point and axis,
    float32; sigma 0 returns ``points`` itself and draws nothing."""
    if sigma == 0:
        return points
    noise = rng.standard_normal(np.shape(points))
    return (np.asarray(points, np.float64) + sigma * noise).astype(np.float32)


def drop_frames(count, fraction, rng):
    """Drop round(fraction * count) of ``count`` frames at random -> (K,) int64 sorted indices
    of the kept frames. The same rng state drops nested sets as ``fraction`` grows."""
    dropped = rng.permutation(count)[:round(fraction * count)]
    return np.setdiff1d(np.arange(count), dropped).astype(np.int64)


def consecutive_centres(kept):
    """(K,) sorted kept frame indices -> (M,) int64 positions i in ``kept`` whose neighbours
    kept[i - 1] and kept[i + 1] are the original frames just before and after kept[i]."""
    kept = np.asarray(kept)
    middle = np.arange(1, len(kept) - 1)
    return middle[(kept[middle] - kept[middle - 1] == 1) & (kept[middle + 1] - kept[middle] == 1)]


def gap_free_acceleration(pred, gt, centres):
    """Acc and PA-Acc over the second differences centred on ``centres`` only.

    Args:
        pred: (K, J, 3) predicted joints of the kept frames, metres.
        gt: (K, J, 3) their ground truth.
        centres: (M,) positions in 1..K-2 (``consecutive_centres``).
    Returns:
        (Acc, PA-Acc) in metres per frame^2, NaN when M = 0.
    """
    if len(centres) == 0:
        return float("nan"), float("nan")
    triples = np.asarray(centres)[None] + np.arange(-1, 2)[:, None]       # (3, M)
    aligned = procrustes_align(pred, gt)                                  # (K, J, 3)

    def stacked(x):                      # (K, J, 3) -> (3, M * J, 3): one "frame" per offset
        return x[triples].reshape(3, -1, 3)
    return (acceleration_error(stacked(pred), stacked(gt)),
            acceleration_error(stacked(aligned), stacked(gt)))


# ----------------------------------------------------------------------------- conditions

def conditions(stored_points):
    """Every (points, sigma, fraction) to run, and each sweep's list of them, in value order.

    ``points`` is None for the stored clouds; the stored count maps to them."""
    def count(p):
        return None if p == stored_points else p
    # The points sweep holds BENCHMARK_INPUT and comes first: it runs before any drop.
    sweeps = {"points": [(count(p), 0.0, 0.0) for p in POINT_COUNTS],
              "noise": [(None, s, 0.0) for s in NOISE_SIGMAS],
              "drop": [(None, 0.0, f) for f in DROP_FRACTIONS]}
    return list(dict.fromkeys(c for cs in sweeps.values() for c in cs)), sweeps


def perturb(sequence, condition, index, seed, bodies):
    """The sequence as one condition feeds it to the runtime.

    Args:
        sequence: a ``load_sequence`` dict of T frames.
        condition: (points per cloud, or None for the stored clouds; noise sigma, metres;
            fraction of frames dropped).
        index: the sequence's number (with ``seed``, seeds its draws).
        seed: the run's seed.
        bodies: {name: ``Body``}: the test bodies, to re-sample clouds from.
    Returns:
        the perturbed copy (``FRAME_KEYS`` arrays cut to the K kept frames) and the (K,) kept
        frame indices.
    """
    points, sigma, fraction = condition
    frames = len(sequence["source_points"])
    out = dict(sequence)
    if points is not None:
        out["source_points"], joints = posed_clouds(
            bodies[str(sequence["source_body"])], sequence["rotations"],
            sequence["source_root"], points, np.random.default_rng([seed, 0, index, points]))
        error = np.abs(joints - sequence["source_joints"]).max()
        if error > 1e-4:
            raise RuntimeError(f"{sequence['name']}: the cached body {sequence['source_body']} "
                               f"poses its joints {error:.2g} m off the stored ones")
    out["source_points"] = add_noise(out["source_points"], sigma,
                                     np.random.default_rng([seed, 1, index]))
    kept = drop_frames(frames, fraction, np.random.default_rng([seed, 2, index]))
    out.update({key: out[key][kept] for key in FRAME_KEYS})
    return out, kept


def predict(weights, sequence):
    """``run_sequence``'s model and analytic rows: {row: (joints (T, J, 3), vertices (T, V, 3))}."""
    return run_sequence(weights, sequence, ROWS)[0]


def score(rows, sequence, kept):
    """Metrics of ``predict``'s rows against ``sequence``'s (kept) frames, Acc gap-free, with
    the frame counts to weight them by."""
    metrics = sequence_metrics(rows, sequence)
    centres = consecutive_centres(kept)
    for row in ROWS:
        metrics[row]["Acc"], metrics[row]["PA-Acc"] = gap_free_acceleration(
            rows[row][0], sequence["target_joints"], centres)
    return {"frames": len(kept), "acc_frames": len(centres), "metrics": metrics}


def pooled(results, key="metrics"):
    """Per-sequence scores -> {row: {metric: mean of ``result[key]`` weighted by the frames
    it averages}}."""
    out = {}
    for row in ROWS:
        out[row] = {}
        for name in METRIC_NAMES:
            weight = "acc_frames" if name in ("Acc", "PA-Acc") else "frames"
            used = [r for r in results if r[weight] > 0]
            total = sum(r[weight] for r in used)
            out[row][name] = (sum(r[key][row][name] * r[weight] for r in used) / total
                              if total else float("nan"))
    return out


# ----------------------------------------------------------------------------- reporting

def sweep_values(name):
    """The swept values as reported: points, sigma in cm, fraction in %."""
    return {"points": list(POINT_COUNTS), "noise": [100 * s for s in NOISE_SIGMAS],
            "drop": [100 * f for f in DROP_FRACTIONS]}[name]


def markdown_table(name, values, rows, references=None):
    """One sweep as markdown: a line per value and row (and reference row, if any)."""
    lines = [f"**{SWEEP_AXES[name]}**", "",
             "| value | row | " + " | ".join(METRIC_NAMES) + " |",
             "|---|---|" + "---|" * len(METRIC_NAMES)]
    for index, value in enumerate(values):
        shown = [(row, rows[index][row]) for row in ROWS]
        if references:
            shown += [(f"{row}, {REFERENCE}", references[index][row]) for row in ROWS]
        for row, metrics in shown:
            lines.append(f"| {value:g} | {row} | "
                         + " | ".join(f"{metrics[m]:.4f}" for m in METRIC_NAMES) + " |")
    return "\n".join(lines)


def plot_sweep(name, values, rows, path, marks=(), references=None):
    """One PNG: a panel per ``PANELS`` metric against the swept value, a curve per row (and a
    dotted one per reference row). ``marks``: (x, label) vertical reference lines."""
    figure, axes = plt.subplots(1, len(PANELS), figsize=(4 * len(PANELS), 3.4))
    for axis, (metric, scale, label) in zip(axes, PANELS):
        for row, style, colour in zip(ROWS, ("o-", "s--"), ("C0", "C1")):
            axis.plot(values, [scale * r[row][metric] for r in rows], style, color=colour,
                      label=row)
            if references:
                axis.plot(values, [scale * r[row][metric] for r in references], ":",
                          color=colour, label=f"{row}, {REFERENCE}")
        for x, text in marks:
            axis.axvline(x, color="grey", linewidth=0.8, linestyle=":")
            axis.annotate(text, (x, 0.03), xycoords=("data", "axes fraction"), rotation=90,
                          va="bottom", ha="right", fontsize=7, color="grey")
        if name == "points":
            axis.set_xscale("log", base=2)
            axis.set_xticks(values, [f"{v:,}" for v in values], rotation=45, fontsize=8)
            axis.minorticks_off()
        axis.set_ylim(bottom=0)
        axis.set_xlabel(SWEEP_AXES[name])
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    figure.suptitle(f"Robustness: {SWEEP_AXES[name]}")
    figure.tight_layout()
    with atomic_write(path) as file:
        figure.savefig(file, format="png", dpi=90)
    plt.close(figure)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--data", default="data", help="built data directory (uses DIR/test)")
    parser.add_argument("--out", default="benchmarks/results", help="folder for the PNGs")
    parser.add_argument("--json", help="write every number as JSON here")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                        help="first frames of each sequence")
    parser.add_argument("--seed", type=int, default=0, help="seed of every perturbation")
    add_report_option(parser)
    args = parser.parse_args(argv)
    fewest_kept = len(drop_frames(args.frames, max(DROP_FRACTIONS), np.random.default_rng()))
    if fewest_kept < ACCELERATION_FRAMES:        # refused now, not after minutes
        parser.error(f"--frames {args.frames}: dropping {max(DROP_FRACTIONS):.0%} of them "
                     f"leaves {fewest_kept}, and the metrics need at least "
                     f"{ACCELERATION_FRAMES} (use 6 or more)")
    refuse_test_split(parser, args)
    started = time.perf_counter()
    weights, record = load_measured(args.weights)
    paths, _ = select_sequences(sorted((Path(args.data) / "test").glob("*.npz")), quick=True)
    if not paths:
        raise SystemExit(f"no test sequence in {Path(args.data) / 'test'}: build the data first")
    sequences = [load_sequence(path, args.frames) for path in paths]
    stored = sequences[0]["source_points"].shape[1]
    targets, sources = benchmark_bodies()
    bodies = {body.name: body for body in targets + sources}
    todo, sweeps = conditions(stored)
    results, unperturbed = {}, {}
    for number, condition in enumerate(todo):
        clock, results[condition] = time.perf_counter(), []
        for index, sequence in enumerate(sequences):
            perturbed, kept = perturb(sequence, condition, index, args.seed, bodies)
            rows = predict(weights, perturbed)
            if condition == BENCHMARK_INPUT:
                unperturbed[index] = rows
            results[condition].append(score(rows, perturbed, kept))
            if condition[2]:
                results[condition][-1]["reference"] = score(
                    {row: (joints[kept], vertices[kept])
                     for row, (joints, vertices) in unperturbed[index].items()},
                    perturbed, kept)["metrics"]
        points, sigma, fraction = condition
        print(f"[{number + 1}/{len(todo)}] points {points or stored}, sigma {sigma * 100:g} cm, "
              f"drop {fraction * 100:g} %: model MPJPE "
              f"{pooled(results[condition])['model']['MPJPE']:.4f} "
              f"({time.perf_counter() - clock:.0f} s)", flush=True)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    skr_points = weights.metadata.get("recipe", {}).get("skr", {}).get("points")
    marks = {"points": [(stored, f"test clouds ({stored})")]
             + ([(skr_points, f"SKR trained ({skr_points})")] if skr_points else [])}
    report, tables = {}, []
    for name, chosen in sweeps.items():
        values, rows = sweep_values(name), [pooled(results[c]) for c in chosen]
        references = ([pooled(results[c], "reference") if c[2] else rows[i]
                       for i, c in enumerate(chosen)] if name == "drop" else None)
        plot_sweep(name, values, rows, out / f"robustness_{name}.png", marks.get(name, ()),
                   references)
        tables.append(markdown_table(name, values, rows, references))
        report[name] = {"axis": SWEEP_AXES[name], "values": values, "rows": rows,
                        "frames": [sum(r["frames"] for r in results[c]) for c in chosen],
                        "acc_frames": [sum(r["acc_frames"] for r in results[c])
                                       for c in chosen]}
        if references:
            report[name]["reference_rows"] = references
    seconds = time.perf_counter() - started
    print("\n\n".join(tables))
    print(f"\n{len(sequences)} sequences, {sum(len(s['source_points']) for s in sequences)} "
          f"frames, {len(todo)} conditions in {seconds:.0f} s; figures in {out}")
    if args.json:
        write_text(args.json, json.dumps(
            {"sweeps": report, "sequences": [str(s["name"]) for s in sequences],
             "frames_per_sequence": args.frames, "stored_points": stored, "seed": args.seed,
             **record, "seconds": round(seconds, 1)}, indent=2))


if __name__ == "__main__":
    command_line(main)
