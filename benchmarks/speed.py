"""Speed of the minretarget runtime, batch 1 streaming (one frame at a time, as online use).

    python benchmarks/speed.py [--quick] [--weights FILE] [--json OUT.json]

Reports, for each (P source points, V target points): milliseconds per frame per stage (SKR,
SMRM step, FK, LBS) and end to end, frames per second; and numba's compile time, cold (empty
cache) and warm (from the on-disk cache), measured in fresh processes, apart from steady state.
Without --weights it uses paper-size weights drawn at random (speed does not depend on them).
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from minretarget.config import ModelConfig
from minretarget.kinematics import forward_kinematics, skinning_transforms
from minretarget.retargeter import Retargeter
from minretarget.skin import linear_blend_skinning
from minretarget.skr import regress_joints
from minretarget.smrm import retarget_step
from minretarget.weights import load_weights, weight_template, weights_from_arrays, _leaves


def random_weights(config=ModelConfig(), seed=0):
    """Weights of the right shapes with values ~ N(0, 1/fan_in)."""
    rng = np.random.default_rng(seed)
    arrays = {"format_version": np.array(1), "config": np.array(config.to_json()),
              "metadata": np.array('{"purpose": "speed benchmark, random"}')}
    for stage, tree in weight_template(config).items():
        for key, shape in _leaves(tree, stage):
            arrays[key] = (rng.standard_normal(shape) / np.sqrt(shape[0])).astype(np.float32)
    return weights_from_arrays(arrays)


def body_cloud(rng, count):
    """A body-sized cloud (count, 3), metres."""
    return (rng.standard_normal((count, 3)) * [0.25, 0.45, 0.12] + [0, 0.9, 0]).astype(np.float32)


def time_per_call(function, repeats, warmup=2):
    """Median seconds per call."""
    for _ in range(warmup):
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def measure(weights, source_points, target_points, repeats):
    rng = np.random.default_rng(0)
    retargeter = Retargeter(weights)
    retargeter.set_target(body_cloud(rng, target_points))
    target = retargeter.target
    frames = [body_cloud(rng, source_points) for _ in range(8)]
    source_joints = regress_joints(frames[0], weights.skr)
    rotations, root, state = retarget_step(weights.smrm, None, source_joints, target.tpose_joints)
    joints, global_rotations = forward_kinematics(rotations, root, target.tpose_joints)
    transforms = skinning_transforms(joints, global_rotations, target.tpose_joints)
    cycle = iter(range(10**9))
    stages = {
        "skr": lambda: regress_joints(frames[next(cycle) % 8], weights.skr),
        "smrm_step": lambda: retarget_step(weights.smrm, state, source_joints,
                                           target.tpose_joints),
        "fk": lambda: forward_kinematics(rotations, root, target.tpose_joints),
        "lbs": lambda: linear_blend_skinning(target.points, target.skin_weights, transforms),
        "end_to_end": lambda: retargeter.step(frames[next(cycle) % 8]),
    }
    ms = {name: 1e3 * time_per_call(f, repeats) for name, f in stages.items()}
    return {"P": source_points, "V": target_points, "ms": ms,
            "fps_end_to_end": 1e3 / ms["end_to_end"]}


COMPILE_SCRIPT = """
import time; start = time.perf_counter()
import numpy as np, sys
sys.path.insert(0, {here!r})
from speed import random_weights, body_cloud
from minretarget.retargeter import Retargeter
imported = time.perf_counter()
weights = random_weights()
loaded = time.perf_counter()
r = Retargeter(weights); rng = np.random.default_rng(0)
r.set_target(body_cloud(rng, 256)); r.step(body_cloud(rng, 256))
done = time.perf_counter()
print(imported - start, done - loaded)
"""


def compile_times():
    """(import s, first-call s) in a fresh process: cold cache, then warm from the cache."""
    with tempfile.TemporaryDirectory() as cache:
        environment = {**os.environ, "NUMBA_CACHE_DIR": cache}
        script = COMPILE_SCRIPT.format(here=os.path.dirname(os.path.abspath(__file__)))
        out = {}
        for label in ("cold", "warm"):
            result = subprocess.run([sys.executable, "-c", script], env=environment,
                                    capture_output=True, text=True, check=True)
            seconds = [float(v) for v in result.stdout.split()]
            out[label] = {"import_s": seconds[0], "first_frame_s": seconds[1]}
        return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="default setting only, fewer repeats")
    parser.add_argument("--weights", help="a weights file (default: random paper-size weights)")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    weights = load_weights(args.weights) if args.weights else random_weights()
    settings = [(2048, 13718)] if args.quick else [(p, v) for p in (1024, 2048, 6890)
                                                   for v in (6890, 13718)]
    results = {"config": json.loads(weights.config.to_json()),
               "threads": int(os.environ.get("NUMBA_NUM_THREADS", os.cpu_count())),
               "compile": compile_times(), "settings": []}
    print(f"compile (fresh process): cold {results['compile']['cold']}, "
          f"warm {results['compile']['warm']}")
    print(f"{'P':>6} {'V':>6} " + " ".join(f"{k:>11}" for k in
                                            ("skr", "smrm_step", "fk", "lbs", "end_to_end", "fps")))
    for p, v in settings:
        row = measure(weights, p, v, repeats=10 if args.quick else 30)
        results["settings"].append(row)
        print(f"{p:>6} {v:>6} " + " ".join(f"{row['ms'][k]:>9.3f}ms" for k in row["ms"])
              + f" {row['fps_end_to_end']:>11.1f}")
    if args.json:
        with open(args.json, "w") as file:
            json.dump(results, file, indent=2)


if __name__ == "__main__":
    main()
