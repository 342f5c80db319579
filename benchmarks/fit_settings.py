"""Candidate settings of the source fit on validation (docs/source_fit.md, "Settings").

    python benchmarks/fit_settings.py [--fit JSON ...] [--set SET] [--draws K] [--cmu DIR]
        [--json OUT.json]

Each ``--fit`` is a JSON object of ``minretarget.fit.FitSettings`` fields (default: one
candidate, ``{}``, the shipped settings). Every sequence of a selection set (``--set``:
validation, the default, ``training.data.datasets.validation_sequences``; or dances, motions,
crossed, more_dances: ``benchmarks/accuracy.py``'s --dances, --motions, --crossed,
--more-dances; never the test split)
is read by the shipped SKR and refiner (``Retargeter.skeleton``), tracked by ``fit.track`` with
each candidate, and the fitted skeletons retargeted by ``Retargeter.step_skeleton`` with the
shipped weights, smoothing and denoiser off. Per candidate: the source skeleton's error
(``metrics.joint_errors``, mm), its jitter (mean second difference, mm), its frames with crossed
legs (``metrics.crossed_feet``), the frames where the start from SKR's reading won, the target's
crossed-legs frames, MPJPE, PA-MPJPE, Acc, PA-Acc (mm) and toe speed on the truth's contacts
(m/s), frame-weighted, and the fit's milliseconds a frame (on this machine, with whatever
else runs).

The fit reads a seeded random subset of each cloud, and which points it draws moves its
figures (the crossed set's crossed frames 47-67 over six draws of the default: docs/
source_fit.md, "How far the figures move with the points drawn"). ``--draws K`` runs every
candidate on the draws 0..K-1 (``FitSettings.draw``) and gives the figures' mean over draws,
each draw's, and each candidate's difference from the first, draw by draw, with its 95 %
interval over the draws (Student's t); in its JSON, "mean", "per_draw" and "minus_first" hold
those, while "summary" and "per_sequence" stay draw 0's.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

from minretarget.fit import FitSettings, body_model, check_fit_settings, track
from minretarget.metrics import crossed_feet, evaluate, foot_contacts, foot_speeds, joint_errors
from minretarget.retargeter import Retargeter
from minretarget.weights import load_weights
from minretarget.pipeline import PipelineConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import CONTACT_HEIGHT, SELECTION_SETS, command_line, write_text  # noqa: E402


def candidate(text):
    """A --fit value: JSON of FitSettings fields -> checked FitSettings."""
    try:
        return check_fit_settings(FitSettings(**json.loads(text)))
    except (json.JSONDecodeError, TypeError, ValueError) as error:
        raise argparse.ArgumentTypeError(f"{text}: {error}") from None


def score(settings, sequence, reading, weights):
    """One candidate on one sequence -> {figure: value}, and the fit's seconds."""
    clouds, truth = sequence["source_points"], sequence["source_joints"]
    start = time.perf_counter()
    fitted, won = track(body_model(), settings, clouds, reading)
    seconds = time.perf_counter() - start
    retargeter = Retargeter(weights, PipelineConfig(smoothing=None, denoise=False))
    retargeter.set_target(sequence["target_tpose_points"])
    frames = [retargeter.step_skeleton(joints) for joints in fitted]
    joints = np.stack([f.joints for f in frames])
    target = evaluate(joints, sequence["target_joints"], np.stack([f.vertices for f in frames]),
                      sequence["target_points"], rest_points=sequence["target_tpose_points"])
    contacts = foot_contacts(sequence["target_joints"], CONTACT_HEIGHT)
    second = np.linalg.norm(fitted[2:] - 2 * fitted[1:-1] + fitted[:-2], axis=2)
    return {**{f"source {group}": 1e3 * error
               for group, error in joint_errors(fitted, truth).items()},
            "source jitter": 1e3 * float(second.mean()) if len(second) else 0.0,
            "crossed": int(crossed_feet(fitted, truth).sum()),
            "result crossed": int(crossed_feet(joints, sequence["target_joints"]).sum()),
            "reading won": int(won[1:].sum()),
            **{name: 1e3 * target[name] for name in ("MPJPE", "PA-MPJPE", "Acc", "PA-Acc")},
            "toes": [float(foot_speeds(joints)[contacts].sum()), int(contacts.sum())]}, seconds


def summarize(runs):
    """Per-sequence figures -> frame-weighted means (sums for counts, pooled toes)."""
    frames = np.array([run["frames"] for run in runs], float)
    out = {}
    for key in runs[0]["figures"]:
        values = [run["figures"][key] for run in runs]
        if key == "toes":
            out[key] = sum(v[0] for v in values) / max(1, sum(v[1] for v in values))
        elif key in ("crossed", "result crossed", "reading won"):
            out[key] = int(sum(values))
        else:
            out[key] = float(np.dot(values, frames) / frames.sum())
    return out


def over_draws(per_draw, first=None):
    """Per-draw summaries (``summarize``) -> their mean; with ``first`` (the first
    candidate's), also each figure's mean difference from it, draw by draw, and its 95 %
    interval over the draws (None for one draw)."""
    keys = list(per_draw[0])
    values = {key: np.array([summary[key] for summary in per_draw], float) for key in keys}
    out = {"mean": {key: float(value.mean()) for key, value in values.items()}}
    if first is not None:
        out["minus_first"] = {}
        for key in keys:
            difference = values[key] - np.array([summary[key] for summary in first], float)
            half = (None if len(difference) < 2 else float(
                stats.t.ppf(0.975, len(difference) - 1) * difference.std(ddof=1)
                / np.sqrt(len(difference))))
            mean = float(difference.mean())
            out["minus_first"][key] = {"difference": mean, "interval": None if half is None
                                       else [mean - half, mean + half]}
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fit", type=candidate, action="append",
                        help="FitSettings fields as JSON, e.g. '{\"race_iterations\": 4}'")
    parser.add_argument("--cmu", default=str(Path(__file__).resolve().parents[2] / "shared"
                                              / "data" / "cmu"))
    parser.add_argument("--set", choices=SELECTION_SETS, default="validation",
                        help="the selection set (default: validation)")
    parser.add_argument("--draws", type=int, default=1,
                        help="run every candidate on this many draws of the clouds' points "
                             "(FitSettings.draw 0..K-1; default 1: the candidate's own)")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args(argv)
    if args.draws < 1:
        parser.error(f"--draws must be at least 1, got {args.draws}")
    if not Path(args.cmu).is_dir():
        parser.error(f"--cmu {args.cmu}: no such folder (the {args.set} trials are read there)")
    from training.data import datasets
    candidates = args.fit or [FitSettings()]
    if args.draws > 1 and any(settings.draw for settings in candidates):
        parser.error("--draws runs every candidate on draws 0..K-1: leave out their draw")
    several = args.draws > 1              # else: each candidate on its own draw, once
    draws = list(range(args.draws)) if several else [None]
    weights = load_weights()
    reader = Retargeter(weights)
    runs = {(index, draw): [] for index in range(len(candidates)) for draw in draws}
    fit_seconds = np.zeros(len(candidates))
    for held_out in getattr(datasets, SELECTION_SETS[args.set][1])(args.cmu):
        sequence = held_out.build()
        reading = reader.skeleton(sequence["source_points"])
        for (index, draw), kept in runs.items():
            settings = candidates[index]
            figures, seconds = score(settings if draw is None else settings._replace(draw=draw),
                                     sequence, reading, weights)
            fit_seconds[index] += seconds / len(draws)
            kept.append({"sequence": held_out.name, "frames": held_out.frames,
                         "figures": figures})
        print(f"{held_out.name} ({held_out.frames} frames) done", flush=True)
    results, first = [], None
    for index, settings in enumerate(candidates):
        per_draw = [summarize(runs[index, draw]) for draw in draws]
        total = sum(run["frames"] for run in runs[index, draws[0]])
        results.append({"settings": settings._asdict(), "summary": per_draw[0],
                        "fit_ms_per_frame": 1e3 * fit_seconds[index] / total,
                        "per_sequence": runs[index, draws[0]]})
        if several:
            results[-1].update({"draws": draws, "per_draw": per_draw,
                                "per_draw_sequences": [runs[index, d] for d in draws],
                                **over_draws(per_draw, first)})
            first = per_draw if first is None else first
        row = results[-1].get("mean", per_draw[0])
        print(json.dumps({key: v for key, v in settings._asdict().items()
                          if v != FitSettings._field_defaults[key]})
              + (f" (mean of {len(draws)} draws)" if several else "") + ": "
              + ", ".join(f"{key} {value:.3f}" if key == "toes" else
                          f"{key} {value:.2f}" if isinstance(value, float) else
                          f"{key} {value}" for key, value in row.items())
              + f", {results[-1]['fit_ms_per_frame']:.1f} ms a frame")
        if several:
            print("  crossed per draw: " + ", ".join(str(s["crossed"]) for s in per_draw)
                  + "; source all, mm: " + ", ".join(f"{s['source all']:.2f}" for s in per_draw))
        for key, paired in results[-1].get("minus_first", {}).items():
            if key in ("crossed", "result crossed", "source all", "MPJPE", "PA-MPJPE", "Acc"):
                low, high = paired["interval"]
                print(f"  {key} minus the first: {paired['difference']:+.2f} "
                      f"[{low:+.2f}, {high:+.2f}]")
    if args.json:
        write_text(args.json, json.dumps({"set": args.set, "candidates": results}, indent=2))


if __name__ == "__main__":
    command_line(main)
