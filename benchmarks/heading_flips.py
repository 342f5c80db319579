"""How often the source skeleton faces the wrong way, on the test benchmark.

    python benchmarks/heading_flips.py [--data DIR] [--weights FILE] [--json OUT.json]

A point cloud does not say which way its body faces, and SKR sometimes reads a body backwards:
its skeleton then turns half round about the vertical between two frames, the legs and arms
come out crossed, and the feet jump by tens of centimetres, which no smoothing or foot lock
can hide. Per test sequence this counts the frames whose source skeleton faces more than 90
degrees away from the ground truth's (heading as ``minretarget.heading``: the hips' and
shoulders' left-right axis about +Y), as the runtime finds it (SKR, then the joint refiner)
and as SKR alone finds it, and gives the largest turn the ground truth makes between two
frames (a body turning faster than 90 degrees a frame would spin at over 7 turns a second at
30 fps).
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from minretarget.atomic import atomic_write
from minretarget.heading import heading_features
from minretarget.retargeter import Retargeter
from minretarget.weights import load_weights

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import load_sequence  # noqa: E402

FLIP = np.pi / 2     # radians off the truth's heading that count as facing the wrong way


def headings(joints):
    """(T, J, 3) skeletons -> (T,) headings about +Y, radians."""
    turns = [heading_features(frame, frame[0])[1:] for frame in joints.astype(np.float32)]
    return np.array([np.arctan2(sin, cos) for sin, cos in turns])


def wrapped(angles):
    """Angles into [-pi, pi)."""
    return (angles + np.pi) % (2 * np.pi) - np.pi


def sequence_flips(retargeters, sequence):
    """The frames of ``sequence`` each of ``retargeters`` ({name: Retargeter}) finds facing
    the wrong way, and the truth's largest turn between two frames."""
    truth = headings(sequence["source_joints"])
    flipped = {name: int((np.abs(wrapped(headings(retargeter.skeleton(sequence["source_points"]))
                                          - truth)) > FLIP).sum())
               for name, retargeter in retargeters.items()}
    return {"sequence": str(sequence["name"]), "category": str(sequence["category"]),
            "frames": len(truth), "flipped": flipped,
            "truth_largest_turn_degrees": float(np.degrees(np.abs(wrapped(np.diff(truth)))
                                                           .max(initial=0.0)))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data", help="built data directory (uses DIR/test)")
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--json", help="write the counts as JSON here")
    args = parser.parse_args(argv)
    paths = sorted((Path(args.data) / "test").glob("*.npz"))
    if not paths:
        parser.error(f"no test sequences in {Path(args.data) / 'test'}: build them with "
                     "python -m training.data build --only test")
    weights = load_weights(args.weights)
    retargeters = {"SKR and refiner": Retargeter(weights, warn=False),
                   "SKR alone": Retargeter(weights, warn=False, refine=False)}
    started, results = time.perf_counter(), []
    for path in paths:
        r = sequence_flips(retargeters, load_sequence(path))
        results.append(r)
        if any(r["flipped"].values()):
            print(f"{r['sequence']} ({r['category']}, {r['frames']} frames): flipped "
                  + ", ".join(f"{n} {r['flipped'][n]}" for n in retargeters)
                  + f"; the truth turns at most {r['truth_largest_turn_degrees']:.0f} degrees "
                  "a frame", flush=True)
    frames = sum(r["frames"] for r in results)
    flipped = {n: sum(r["flipped"][n] for r in results) for n in retargeters}
    for name, count in flipped.items():
        print(f"{name}: {count} of {frames} frames ({100 * count / frames:.2f} %) flipped, in "
              f"{sum(r['flipped'][name] > 0 for r in results)} of {len(results)} sequences")
    print(f"the truth turns at most "
          f"{max(r['truth_largest_turn_degrees'] for r in results):.0f} degrees a frame "
          f"({time.perf_counter() - started:.0f} s)")
    if args.json:
        with atomic_write(args.json) as file:
            file.write(json.dumps({"flipped": flipped, "frames": frames, "per_sequence": results,
                                   "weights": args.weights or "shipped default"},
                                  indent=2).encode())


if __name__ == "__main__":
    main()
