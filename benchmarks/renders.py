"""Look at the result: test walks and dances retargeted onto a heavy and a slim target.

    python benchmarks/renders.py --report [--weights FILE] [--data DIR] [--out DIR]

--report is required: the pictures and their numbers are of the test split, which is run once
per release, for the report, and never selects anything (accuracy.TEST_SPLIT_RULE).

Four test sequences of DIR/test (built data, never rebuilt here), each on the target body the
benchmark pairs it with (data/manifest.json, "test_pairs"): the walks 08_01 (slim) and 08_02
(heavy), the dances indian_06 (slim) and indian_04 (heavy). Each is retargeted online, frame by
frame, by minretarget.Retargeter, and OUT (default benchmarks/results/renders/) gets:
    <sequence>_<target>.png   six frames: source cloud and SKR skeleton above; retargeted target
                              points and skeleton (orange) below, with the ground-truth target
                              skeleton (green) moved onto the result's pelvis
    renders.json              every number below, per sequence, for the result and the truth
A markdown table is printed. Numbers (metres, frames at 30 fps):
    jitter        mean acceleration magnitude of the 22 joints, m/frame^2 (metrics.jitter)
    foot sliding  mean horizontal speed of the feet over their contact steps, m/s, and the
                  fraction of steps in contact (metrics.foot_sliding, contact: within 3 cm of
                  the foot's own lowest height in both frames); also the result's feet
                  speed over the steps where the ground truth's feet are in contact
                  ("on truth contacts": does the result slide where the truth stands?)
    bone angle    "twisted limbs", result against truth: per frame the largest angle between a
                  retargeted bone's direction and the same ground-truth bone's, degrees; the
                  mean of that over frames and its maximum (with the bone, named by its
                  child joint: "right_wrist" is the forearm). It counts a body turned as a
                  whole as well as a twisted limb, so it is an upper bound. Also the frames
                  where that largest angle passes TWISTED_DEG, and the longest run of them
                  (a misreading held for many frames, or a single-frame spike?).
    knee backward fraction of frames where a knee bends backwards by 10 to 150 degrees
                  (signed angle between thigh and shank about the pelvis's left axis, positive
                  for a normal bend; beyond 150 degrees either way, a full squat, the sign is
                  not reliable), result and truth. Elbows are not checked: their hinge
                  axis turns with the upper arm's twist, which joint positions do not show.
    lowest point  height of the lowest target point per frame (median, minimum over frames);
                  the ground truth is not always on y = 0 itself, so compare the two.
Plus the accuracy protocol's metrics of the result (benchmarks/accuracy.py).
"""
import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import (CONTACT_HEIGHT, add_report_option, command_line,  # noqa: E402
                      load_measured, load_sequence, refuse_test_split, sequence_metrics,
                      write_text)

from minretarget.atomic import atomic_write  # noqa: E402
from minretarget.conventions import FPS, JOINT_INDEX, JOINT_NAMES, PARENTS, UP_AXIS  # noqa: E402
from minretarget.metrics import foot_contacts, foot_sliding, foot_speeds, jitter  # noqa: E402
from minretarget.render import render  # noqa: E402
from minretarget.retargeter import Retargeter  # noqa: E402

SEQUENCES = (("08_01", "walk"), ("08_02", "walk"), ("indian_06", "dance"),
             ("indian_04", "dance"))
KNEE_BACKWARD_DEG = (10.0, 150.0)  # degrees bent the wrong way that count as backward
TWISTED_DEG = 60.0                 # a bone this far from the truth's counts as twisted


def bone_angles(pred, truth):
    """(T, J, 3), (T, J, 3) -> (T, J - 1) degrees between each bone's directions."""
    child = np.arange(1, len(PARENTS))
    parent = np.asarray(PARENTS[1:])
    a, b = pred[:, child] - pred[:, parent], truth[:, child] - truth[:, parent]
    cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1) + 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def twisted_frames(angles, limit=TWISTED_DEG):
    """(T, J - 1) bone angles, degrees -> (frames whose largest angle passes ``limit``, the
    longest run of such frames in a row)."""
    over = np.asarray(angles).max(axis=1) > limit
    # run lengths: the distance between the edges where ``over`` turns on and off
    edges = np.flatnonzero(np.diff(np.concatenate([[0], over.astype(np.int8), [0]])))
    return int(over.sum()), int((edges[1::2] - edges[::2]).max(initial=0))


def knee_bend(joints):
    """(T, J, 3) -> (T, 2) signed knee bend (left, right), degrees: the angle from the thigh to
    the shank about the pelvis's left axis (left hip minus right hip), positive for a normal
    (backward-swinging shank) bend, negative for a knee bending the wrong way."""
    left = joints[:, JOINT_INDEX["left_hip"]] - joints[:, JOINT_INDEX["right_hip"]]
    left /= np.linalg.norm(left, axis=-1, keepdims=True)
    out = []
    for side in ("left", "right"):
        hip, knee, ankle = (joints[:, JOINT_INDEX[f"{side}_{name}"]]
                            for name in ("hip", "knee", "ankle"))
        thigh, shank = knee - hip, ankle - knee
        sine = (np.cross(thigh, shank) * left).sum(-1)
        out.append(np.degrees(np.arctan2(sine, (thigh * shank).sum(-1))))
    return np.stack(out, axis=-1)


def feet_speed_on(joints, contact):
    """(T, J, 3), (T - 1, 2) bool -> mean horizontal speed (m/s) of the feet over ``contact``."""
    return float(foot_speeds(joints)[contact].mean()) if contact.any() else float("nan")


def motion_numbers(joints, points):
    """Numbers of one sequence alone: jitter, feet, knees, lowest point."""
    bend = knee_bend(joints)
    lowest = points[..., UP_AXIS].min(axis=1)
    return {"jitter": jitter(joints),
            "foot_sliding": foot_sliding(joints, FPS, CONTACT_HEIGHT),
            "contact_fraction": float(foot_contacts(joints, CONTACT_HEIGHT).mean()),
            "knee_backward_fraction": float(((-bend >= KNEE_BACKWARD_DEG[0])
                                              & (-bend <= KNEE_BACKWARD_DEG[1])).any(axis=1)
                                             .mean()),
            "lowest_point_median": float(np.median(lowest)),
            "lowest_point_min": float(lowest.min())}


def retarget(weights, sequence, config="default"):
    """Online retargeting of the source clouds by the ``config`` pipeline (a preset's name or
    a ``PipelineConfig``) -> joints, vertices, SKR joints, seconds."""
    retargeter = Retargeter(weights, config)
    retargeter.set_target(sequence["target_tpose_points"], sequence["target_faces"])
    start = time.perf_counter()
    frames = list(retargeter.run(sequence["source_points"]))
    seconds = time.perf_counter() - start
    return (np.stack([f.joints for f in frames]), np.stack([f.vertices for f in frames]),
            np.stack([f.source_joints for f in frames]), seconds)


def shrink(png, colors=96):
    """Rewrite the PNG with a palette (about a third of the size; the strips are flat colour)."""
    from PIL import Image
    with Image.open(png) as image:
        palette = image.convert("RGB").quantize(colors=colors)
    with atomic_write(png) as file:
        palette.save(file, format="PNG", optimize=True)


def table(results):
    lines = ["| sequence | target | frames | jitter res / gt (m/frame^2) | foot sliding res / gt "
             "(m/s) | res on gt contacts (m/s) | contact res / gt | bone angle mean-max / max (deg) "
             f"| frames > {TWISTED_DEG:g} deg (longest run) | knee backward "
             "res / gt | lowest point res / gt (m, median) | MPJPE |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        res, gt = r["result"], r["truth"]
        lines.append(
            f"| {r['sequence']} ({r['kind']}) | {r['target_body']} | {r['frames']} | "
            f"{res['jitter']:.4f} / {gt['jitter']:.4f} | "
            f"{res['foot_sliding']:.3f} / {gt['foot_sliding']:.3f} | "
            f"{res['foot_sliding_on_truth_contacts']:.3f} | "
            f"{res['contact_fraction']:.2f} / {gt['contact_fraction']:.2f} | "
            f"{res['bone_angle_max_deg_mean']:.1f} / {res['bone_angle_max_deg']:.1f} "
            f"({res['bone_angle_max_bone']}) | "
            f"{res['bone_angle_frames_over']} ({res['bone_angle_longest_run_over']}) | "
            f"{res['knee_backward_fraction']:.2f} / {gt['knee_backward_fraction']:.2f} | "
            f"{res['lowest_point_median']:.3f} / {gt['lowest_point_median']:.3f} | "
            f"{r['accuracy']['MPJPE']:.3f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--data", default="data", help="built data directory (uses DIR/test)")
    parser.add_argument("--out", default="benchmarks/results/renders", help="output folder")
    add_report_option(parser)
    args = parser.parse_args(argv)
    refuse_test_split(parser, args)
    out = Path(args.out)
    paths = [Path(args.data) / "test" / f"{name}.npz" for name, _ in SEQUENCES]
    missing = [str(path) for path in paths if not path.is_file()]
    if missing:                                # refused now, not after minutes
        parser.error(f"no {', '.join(missing)}: build the test data first (python -m "
                     "training.data build --only test)")
    weights, record = load_measured(args.weights)
    out.mkdir(parents=True, exist_ok=True)
    # The pictures are drawn aside and moved in together at the end, so that a failed run
    # leaves the folder's set (PNGs and renders.json) as it was.
    with tempfile.TemporaryDirectory(prefix=".renders-", dir=out) as staging:
        results, seconds = draw(weights, SEQUENCES, paths, Path(staging), out)
        for png in Path(staging).glob("*.png"):
            os.replace(png, out / png.name)
    write_text(out / "renders.json", json.dumps(
        {"per_sequence": results, "contact_height": CONTACT_HEIGHT,
         "knee_backward_deg": KNEE_BACKWARD_DEG, "twisted_deg": TWISTED_DEG,
         **record, "seconds": round(seconds, 1)}, indent=2))


def draw(weights, sequences, paths, staging, out):
    """Retarget and draw each sequence into ``staging``: (their results, PNGs named as in
    ``out``; the seconds it took)."""
    started, results = time.perf_counter(), []
    for (name, kind), path in zip(sequences, paths):
        sequence = load_sequence(path)
        joints, vertices, source_joints, seconds = retarget(weights, sequence)
        truth_joints = sequence["target_joints"].astype(np.float64)
        body = str(sequence["target_body"])
        angles = bone_angles(joints.astype(np.float64), truth_joints)      # (T, J-1)
        worst = np.unravel_index(angles.argmax(), angles.shape)
        result = motion_numbers(joints, vertices)
        result["foot_sliding_on_truth_contacts"] = feet_speed_on(
            joints, foot_contacts(truth_joints, CONTACT_HEIGHT))
        result.update({"bone_angle_max_deg_mean": float(angles.max(axis=1).mean()),
                       "bone_angle_max_deg": float(angles.max()),
                       "bone_angle_max_bone": JOINT_NAMES[worst[1] + 1],
                       "bone_angle_max_frame": int(worst[0]),
                       "bone_angle_mean_deg": float(angles.mean())})
        result["bone_angle_frames_over"], result["bone_angle_longest_run_over"] = \
            twisted_frames(angles)
        png = staging / f"{name}_{body}.png"
        with tempfile.TemporaryDirectory() as scratch:
            result_npz = Path(scratch) / "result.npz"
            np.savez(result_npz, joints=joints, source_joints=source_joints, vertices=vertices,
                     fps=np.int64(FPS), units="m", up_axis="y")
            on_pelvis = truth_joints - truth_joints[:, :1] + joints[:, :1]
            render(result_npz, png, source_points=sequence["source_points"],
                   truth_joints=on_pelvis,
                   title=f"{name} ({kind}) onto {body}: source (blue, SKR joints), result "
                         f"(orange), ground truth on the result's pelvis (green)")
        shrink(png)
        results.append({
            "sequence": name, "kind": kind, "target_body": body,
            "frames": len(joints), "png": str(out / png.name),
            "retarget_seconds": round(seconds, 2),
            "result": result,
            "truth": motion_numbers(truth_joints, sequence["target_points"]),
            "accuracy": sequence_metrics({"model": (joints, vertices)}, sequence)["model"]})
        print(f"{name}: {len(joints)} frames, {1e3 * seconds / len(joints):.1f} ms per frame, "
              f"{out / png.name} ({png.stat().st_size // 1024} kB)", flush=True)
    seconds = time.perf_counter() - started
    print(table(results))
    print(f"\n{seconds:.0f} s")
    return results, seconds


if __name__ == "__main__":
    command_line(main)
