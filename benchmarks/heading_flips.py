"""How often the source skeleton faces the wrong way or has its legs swapped, on the test set.

    python benchmarks/heading_flips.py --report [--data DIR] [--weights FILE] [--json OUT.json]

--report is required: the counts are of the test split, which is run once per release, for the
report, and never selects anything (accuracy.TEST_SPLIT_RULE).

A point cloud does not say which way its body faces, and SKR sometimes reads a body backwards:
its skeleton then turns half round about the vertical between two frames, the legs and arms
come out crossed, and the feet jump by tens of centimetres, which no smoothing or foot lock
can hide. Per test sequence this counts the frames whose source skeleton faces more than 90
degrees away from the ground truth's (heading as ``minretarget.heading``: the hips' and
shoulders' left-right axis about +Y): as the runtime reads it (SKR, then the joint refiner;
``Retargeter.skeleton``), as SKR alone reads it, and as SMRM sees it in a stream (after the
facing check, ``minretarget.facing``, the smoothing and the denoiser), with the check and
without. With the toes' mean distance from the truth's (both relative to the pelvis) in those
frames and in the others, and the largest turn the ground truth makes between two frames (a
body turning faster than 90 degrees a frame would spin at over 7 turns a second at 30 fps).

It also counts, among the frames facing the right way, those whose legs are read swapped:
where the dancer crosses one foot over the other, SKR puts each foot on its own side, so the
planted foot jumps to the swinging one's place and back (``legs_swapped``: the knees, ankles
and toes lie at least ``SWAP_MARGIN`` nearer the truth's, summed, with the two lower legs or
the two feet exchanged).
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from minretarget.atomic import atomic_write
from minretarget.conventions import JOINT_INDEX
from minretarget.heading import heading_angles, wrapped
from minretarget.metrics import FOOT_JOINTS
from minretarget.retargeter import Retargeter
from minretarget.pipeline import PipelineConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import (add_report_option, command_line, load_measured,  # noqa: E402
                      load_sequence, refuse_test_split)

FLIP = np.pi / 2     # radians off the truth's heading that count as facing the wrong way
TOES = [JOINT_INDEX[name] for name in FOOT_JOINTS]
# Per leg (left, right): knee, ankle, toe.
LOWER_LEGS = np.array([[JOINT_INDEX[f"{side}_{name}"] for name in ("knee", "ankle", "foot")]
                       for side in ("left", "right")])
SWAP_MARGIN = 0.1    # metres, summed over the six joints, that a swapped reading must gain
ROWS = ("SKR and refiner", "SKR alone", "SMRM's input", "SMRM's input, no facing check")


def toe_errors(joints, truth):
    """(T, 2) distances of the toes from the truth's, both relative to the pelvis, metres."""
    def toes(skeleton):
        return skeleton[:, TOES] - skeleton[:, :1]
    return np.linalg.norm(toes(joints) - toes(truth), axis=-1)


def legs_swapped(joints, truth, margin=SWAP_MARGIN):
    """(T,) bool: frames whose lower legs (knee, ankle, toe) are nearer the truth's, summed over
    the six joints, by more than ``margin`` metres with the left and right feet (ankle and toe)
    or whole lower legs exchanged. ``joints``, ``truth``: (T, J, 3), metres."""
    def distance(skeleton):
        return np.linalg.norm(skeleton[:, LOWER_LEGS] - truth[:, LOWER_LEGS], axis=-1).sum((1, 2))
    as_read = distance(joints)
    best = np.full(len(joints), np.inf)
    for exchanged in (LOWER_LEGS[:, 1:], LOWER_LEGS):
        swapped = joints.copy()
        swapped[:, exchanged[0]], swapped[:, exchanged[1]] = (joints[:, exchanged[1]],
                                                              joints[:, exchanged[0]])
        best = np.minimum(best, distance(swapped))
    return best < as_read - margin


def row_skeletons(weights, sequence):
    """{row: (T, J, 3) source skeletons of ``sequence``} for the rows of ``ROWS``."""
    clouds = sequence["source_points"]
    readings = Retargeter(weights, warn=False).skeleton(clouds)
    rows = {"SKR and refiner": readings,
            "SKR alone": Retargeter(weights, PipelineConfig(refine=False, denoise=False),
                warn=False).skeleton(clouds)}
    for row, check in ((ROWS[2], True), (ROWS[3], False)):
        retargeter = Retargeter(weights, PipelineConfig(facing_check=check), warn=False)
        retargeter.set_target(sequence["target_tpose_points"])   # SMRM's input is the same
        rows[row] = np.stack([retargeter.step_skeleton(joints, cloud).source_joints
                              for joints, cloud in zip(readings, clouds)])
    return rows


def sequence_flips(rows, sequence):
    """Per row of ``rows`` ({name: (T, J, 3) skeletons of ``sequence``}): the frames whose
    skeleton faces the wrong way, and the sums of the toe errors (``toe_errors``) over them
    and over the other frames; the frames facing the right way with legs swapped
    (``legs_swapped``) and their toe errors' sum; and the truth's largest turn between two
    frames."""
    truth_joints = sequence["source_joints"]
    truth = heading_angles(truth_joints)
    found = {}
    for name, joints in rows.items():
        flipped = np.abs(wrapped(heading_angles(joints) - truth)) > FLIP
        swapped = legs_swapped(joints, truth_joints) & ~flipped
        errors = toe_errors(joints, truth_joints)
        found[name] = {"flipped": int(flipped.sum()),
                       "toe_error_sum_flipped": float(errors[flipped].sum()),
                       "toe_error_sum_other": float(errors[~flipped].sum()),
                       "legs_swapped": int(swapped.sum()),
                       "toe_error_sum_legs_swapped": float(errors[swapped].sum())}
    return {"sequence": str(sequence["name"]), "category": str(sequence["category"]),
            "frames": len(truth), "found": found,
            "truth_largest_turn_degrees": float(np.degrees(np.abs(wrapped(np.diff(truth)))
                                                           .max(initial=0.0)))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="data", help="built data directory (uses DIR/test)")
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--json", help="write the counts as JSON here")
    add_report_option(parser)
    args = parser.parse_args(argv)
    refuse_test_split(parser, args)
    paths = sorted((Path(args.data) / "test").glob("*.npz"))
    if not paths:
        parser.error(f"no test sequences in {Path(args.data) / 'test'}: build them with "
                     f"python -m training.data build --cmu ../shared/data/cmu --out {args.data} "
                     "--only test")
    weights, record = load_measured(args.weights)
    started, results = time.perf_counter(), []
    for path in paths:
        sequence = load_sequence(path)
        r = sequence_flips(row_skeletons(weights, sequence), sequence)
        results.append(r)
        if any(found["flipped"] or found["legs_swapped"] for found in r["found"].values()):
            print(f"{r['sequence']} ({r['category']}, {r['frames']} frames): flipped / legs "
                  "swapped " + ", ".join(f"{n} {r['found'][n]['flipped']} / "
                                         f"{r['found'][n]['legs_swapped']}" for n in ROWS)
                  + f"; the truth turns at most {r['truth_largest_turn_degrees']:.1f} degrees "
                  "a frame", flush=True)
    frames = sum(r["frames"] for r in results)
    summary = {}
    for name in ROWS:
        flipped = sum(r["found"][name]["flipped"] for r in results)
        toes = {part: sum(r["found"][name][f"toe_error_sum_{part}"] for r in results)
                / max(1, 2 * count) for part, count in (("flipped", flipped),
                                                        ("other", frames - flipped))}
        swapped = sum(r["found"][name]["legs_swapped"] for r in results)
        swapped_toes = (sum(r["found"][name]["toe_error_sum_legs_swapped"] for r in results)
                        / max(1, 2 * swapped))
        summary[name] = {"flipped": flipped, "toe_error_flipped": toes["flipped"],
                         "toe_error_other": toes["other"],
                         "sequences": sum(r["found"][name]["flipped"] > 0 for r in results),
                         "legs_swapped": swapped, "toe_error_legs_swapped": swapped_toes,
                         "sequences_legs_swapped": sum(r["found"][name]["legs_swapped"] > 0
                                                       for r in results)}
        print(f"{name}: {flipped} of {frames} frames ({100 * flipped / frames:.2f} %) flipped, "
              f"in {summary[name]['sequences']} of {len(results)} sequences; toes "
              f"{toes['flipped']:.3f} m from the truth's there, {toes['other']:.3f} m in the "
              f"other frames; legs swapped in {swapped} more "
              f"({summary[name]['sequences_legs_swapped']} sequences), toes {swapped_toes:.3f} "
              "m from the truth's there")
    largest = max(r["truth_largest_turn_degrees"] for r in results)
    seconds = time.perf_counter() - started
    print(f"the truth turns at most {largest:.1f} degrees a frame ({seconds:.0f} s)")
    if args.json:
        with atomic_write(args.json) as file:
            file.write(json.dumps({"frames": frames, "summary": summary,
                                   "truth_largest_turn_degrees": largest,
                                   "per_sequence": results, "seconds": round(seconds, 1),
                                   **record},
                                  indent=2).encode())


if __name__ == "__main__":
    command_line(main)
