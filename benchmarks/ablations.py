"""Ablations of SMRM training (issue 4 item 3; the paper's Tables 2 and 3): the training clip
length (5, 10, 15, 30, 60 frames) and the rotation cycle loss (on, off).

    python benchmarks/ablations.py --report [--train] [--runs DIR] [--recipe ablation]
                                   [--data DIR] [--quick] [--json OUT.json] [--markdown OUT.md]

--report is required (refused before any training): the variants are scored on the test split,
which is run once per release, for the report, and never selects anything
(accuracy.TEST_SPLIT_RULE).

--train first trains each variant that has no ``DIR/<variant>/weights.npz`` yet, one after the
other (``python -m training.train smrm --init <shipped> --scratch smrm --recipe ablation
--set ...``): SMRM from random initialisation with the recipe's schedule and one thing changed;
SKR and SKIN are the shipped ones, so every variant sees the same source skeletons and target
rig. The 60-frame variant trains on ``DATA/clip60`` (built first when absent: ``python -m
training.data build --only smrm --clip-frames 60``); shorter clips are random windows of the
30-frame clips. On this 2-core machine (one core each, the other busy) the 1000-step variants
took 4 min (5 frames), 7, 9, 23 (30), 34 (60) and 20 (no rotation cycle): 95 minutes in all.

Then every variant retargets the test benchmark online (``accuracy.py``'s sequences; --quick:
its subset): SKR runs once per sequence (the shipped SKR, shared by all variants) and each
SMRM streams (a) those SKR source skeletons, checked for facing and smoothed as
``Retargeter`` does by default (the stored quick run predates the facing check): the whole
pipeline, and (b) the true source joints, unsmoothed: SMRM alone. Prints and writes one
table per input, rows = variants, the metrics of ``minretarget.metrics`` averaged over frames.
"""
import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from accuracy import (add_report_option, load_sequence, refuse_test_split, select_sequences,
                      stream, training_env, write_text)
from minretarget.metrics import METRIC_NAMES, evaluate
from minretarget.retargeter import Retargeter
from minretarget.weights import DEFAULT_WEIGHTS, load_weights
from minretarget.pipeline import PipelineConfig

# variant -> (run folder under --runs, recipe overrides, data folder under --data or None)
VARIANTS = {
    "clip 5": ("clip05", ["smrm.clip_frames=5"], None),
    "clip 10": ("clip10", ["smrm.clip_frames=10"], None),
    "clip 15": ("clip15", ["smrm.clip_frames=15"], None),
    "clip 30": ("clip30", [], None),
    "clip 60": ("clip60", ["smrm.clip_frames=60"], "clip60"),
    "clip 30, no rotation cycle": ("clip30_no_rotation_cycle", ["smrm.rotation_cycle=0"], None),
}
INPUTS = ("SKR source joints", "true source joints")


def train_variant(variant, args):
    folder, overrides, subfolder = VARIANTS[variant]
    data = Path(args.data) / subfolder if subfolder else Path(args.data)
    if subfolder and not (data / "smrm_train.npz").exists():
        frames = int(overrides[0].split("=")[1])
        subprocess.run([sys.executable, "-m", "training.data", "build", "--cmu", args.cmu,
                        "--out", str(data), "--only", "smrm", "--clip-frames", str(frames)],
                       check=True, env=training_env())
    command = [sys.executable, "-m", "training.train", "smrm", "--recipe", args.recipe,
               "--init", str(DEFAULT_WEIGHTS), "--scratch", "smrm", "--data", str(data),
               "--out", str(Path(args.runs) / folder), "--threads", "1",
               "--resume"]      # an interrupted variant goes on; a new one starts
    for override in overrides:
        command += ["--set", override]
    print(" ".join(command), flush=True)
    subprocess.run(command, check=True, env=training_env())


def variant_metrics(weights, sequence, skr_joints, rig):
    """{input: metrics} for one variant's SMRM on one sequence; ``rig``: the shipped SKR and
    SKIN's ``Target`` (every variant carries them unchanged, so they run once). No foot lock:
    the variants differ in SMRM, and the lock would blur what SMRM did to the legs."""
    retargeter = Retargeter(weights, PipelineConfig(foot_lock=None), warn=False)
    retargeter.set_target(rig.points, tpose_joints=rig.tpose_joints,
                          skin_weights=rig.skin_weights)
    truth = sequence["target_joints"], sequence["target_points"]
    out = {}
    # SKR's joints smoothed (and denoised) as the Retargeter does by default; the true joints
    # as they are, SMRM alone.
    for name, source_joints, config in zip(INPUTS, (skr_joints, sequence["source_joints"]),
                                           (retargeter.config, retargeter.config.replace(
                                               smoothing=None, denoise=False))):
        retargeter.reset()
        retargeter.config = config
        joints, vertices = stream(retargeter, source_joints)
        out[name] = evaluate(joints, truth[0], vertices, truth[1],
                             rest_points=sequence["target_tpose_points"])
    return out


def markdown_table(rows, title):
    lines = [f"**{title}**", "", "| variant | " + " | ".join(METRIC_NAMES) + " |",
             "|---|" + "---|" * len(METRIC_NAMES)]
    lines += [f"| {name} | " + " | ".join(f"{m[k]:.4f}" for k in METRIC_NAMES) + " |"
              for name, m in rows.items()]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", action="store_true", help="train the missing variants first")
    parser.add_argument("--runs", default="runs/ablation", help="one run folder per variant")
    parser.add_argument("--recipe", default="ablation", help="the recipe every variant shares")
    parser.add_argument("--data", default="data", help="built data (DIR/test, DIR/clip60)")
    parser.add_argument("--cmu", default="../shared/data/cmu", help="CMU data, to build clip60")
    parser.add_argument("--quick", action="store_true", help="accuracy.py's quick subset")
    parser.add_argument("--json", help="write the results as JSON here")
    parser.add_argument("--markdown", help="write the tables as markdown here")
    add_report_option(parser)
    args = parser.parse_args(argv)
    refuse_test_split(parser, args)     # before any variant is trained
    paths = {v: Path(args.runs) / folder / "weights.npz" for v, (folder, *_) in VARIANTS.items()}
    if args.train:
        for variant, path in paths.items():
            if not path.exists():
                train_variant(variant, args)
    missing = [str(p) for p in paths.values() if not p.exists()]
    if missing:
        sys.exit(f"no weights for {missing}: run with --train")
    variants = {v: load_weights(p) for v, p in paths.items()}
    shipped = Retargeter(load_weights(), PipelineConfig(smoothing=None, denoise=False),
        warn=False)  # raw joints
    sequence_paths, frames = select_sequences(sorted((Path(args.data) / "test").glob("*.npz")),
                                              args.quick)
    started, totals, count = time.perf_counter(), {}, 0
    for index, path in enumerate(sequence_paths):
        sequence = load_sequence(path, frames)
        shipped.set_target(sequence["target_tpose_points"])
        skr_joints = np.stack([f.source_joints for f in shipped.run(sequence["source_points"])])
        length = len(skr_joints)
        for variant, weights in variants.items():
            for name, metrics in variant_metrics(weights, sequence, skr_joints,
                                                        shipped.target).items():
                row = totals.setdefault(name, {}).setdefault(variant, dict.fromkeys(
                    METRIC_NAMES, 0.0))
                for key in METRIC_NAMES:
                    row[key] += metrics[key] * length
        count += length
        print(f"[{index + 1}/{len(sequence_paths)}] {path.stem} ({length} frames)", flush=True)
    tables = {name: {v: {k: total / count for k, total in row.items()} for v, row in rows.items()}
              for name, rows in totals.items()}
    seconds = time.perf_counter() - started
    text = "\n\n".join(markdown_table(rows, f"SMRM ablations, {name} ({len(sequence_paths)} "
                                            f"sequences, {count} frames)")
                       for name, rows in tables.items())
    print(text + f"\n\n{seconds:.0f} s")
    if args.markdown:
        write_text(args.markdown, text + "\n")
    if args.json:
        write_text(args.json, json.dumps(
            {"tables": tables, "frames": count, "sequences": len(sequence_paths),
             "quick": args.quick, "seconds": round(seconds, 1),
             "recipes": {v: w.metadata.get("recipe") for v, w in variants.items()}}, indent=2))


if __name__ == "__main__":
    main()
