"""Choose the foot contacts' settings (minretarget.contacts.FootLock) on validation motion.

    python -m training.tune_contacts [--weights FILE] [--cmu DIR] [--cache DIR]

Validation only, never the test split: trials of the held-out training subjects (06
basketball, 09 running and walking), at most 240 frames each, played on held-out validation
bodies (source and target differ), sampled into clouds as the test benchmark does. The
shipped runtime (smoothing and denoiser on, foot lock off) retargets each once; its rotations
are cached in ``--cache``, then every setting of a grid runs ``contacts.plant_feet`` over them.
For each setting it prints the toe speed over the ground truth's contacts (pooled over those
steps, m/s; ``benchmarks/accuracy.py``'s foot-sliding table), MPJPE, PA-MPJPE and Acc of
the joints (metres). The choice: among the settings whose toes move no faster on the truth's
contacts than the truth's own do, those within ``TIE`` of the least PA-MPJPE (closer is noise:
the 1 cm leashes of the grid all land within 0.04 mm), and of those the one whose toes move
slowest.
"""
import argparse
import hashlib
import itertools
import sys
from pathlib import Path

import numpy as np

import minretarget
from minretarget.contacts import FootLock, plant_feet
from minretarget.kinematics import forward_kinematics
from minretarget.metrics import acceleration_error, foot_contacts, foot_speeds, mpjpe, pa_mpjpe
from minretarget.retargeter import Retargeter
from minretarget.smoothing import Smoothing
from minretarget.weights import flatten_weights, load_weights
from minretarget.pipeline import PipelineConfig
from training.data.datasets import validation_sequences

TRIALS, MAX_FRAMES, CONTACT_HEIGHT = 12, 240, 0.03
TIE = 1e-5          # metres of PA-MPJPE (0.01 mm): settings closer than this are tied
GRID = {"plant_speed": (1.0, 2.0, 3.0), "lift_speed": (2.0, 3.0), "speed_cutoff": (12.0,),
        "height_margin": (0.05,), "max_offset": (0.01, 0.02, 0.03, 0.05, 0.1),
        "release_decay": (0.5,), "anchor_follow": (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4)}


def validation_streams(weights, cmu_dir, cache_dir):
    """[(name, SMRM rotations (T, J, 4), root (T, 3), target T-pose (J, 3), truth joints
    (T, J, 3))]: built and retargeted once, then read from ``cache_dir``/<weights' hash>."""
    cache_dir = Path(cache_dir) / cache_key(weights, Smoothing())[:16]
    cache_dir.mkdir(parents=True, exist_ok=True)
    streams = []
    for trial, _, _, build in validation_sequences(cmu_dir, TRIALS, MAX_FRAMES):
        path = cache_dir / f"{trial.name}.npz"
        if not path.is_file():
            sequence = build()
            retargeter = Retargeter(weights, PipelineConfig(smoothing=Smoothing(), foot_lock=None),
                warn=False)
            retargeter.set_target(sequence["target_tpose_points"])
            frames = retargeter.retarget_sequence(sequence["source_points"])
            np.savez(path, rotations=frames.rotations, root=frames.root,
                     tpose=retargeter.target.tpose_joints, truth=sequence["target_joints"])
            print(f"{trial.name} ({trial.category}): {len(frames.root)} frames", flush=True)
        with np.load(path) as data:
            streams.append((trial.name, data["rotations"], data["root"], data["tpose"],
                            data["truth"]))
    return streams


def cache_key(weights, smoothing):
    """SHA-256 of the weights' arrays, the source smoothing the streams are made with (the
    runtime's default) and the runtime's source files, so that a cache made with other
    weights, another filter or another runtime is not reused."""
    digest = hashlib.sha256(repr(smoothing).encode())
    for path in sorted(Path(minretarget.__file__).parent.glob("*.py")):
        digest.update(path.read_bytes())
    for name, array in sorted(flatten_weights(weights).items()):
        digest.update(name.encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def score(weights, streams, foot_lock):
    """Pooled toe speed on the truth's contacts, the truth's own, then frame-weighted MPJPE,
    PA-MPJPE and Acc of the joints with ``foot_lock`` (None: SMRM's alone)."""
    speed = truth_speed = steps = 0.0
    errors, frames = np.zeros(3), 0
    for _, rotations, root, tpose, truth in streams:
        state, out = None, rotations.copy()
        for t in range(len(rotations) if foot_lock is not None else 0):
            out[t], state = plant_feet(rotations[t], root[t], tpose, state, foot_lock)
        joints = forward_kinematics(out, root, tpose)[0]
        contacts = foot_contacts(truth, CONTACT_HEIGHT)
        speed += foot_speeds(joints)[contacts].sum()
        truth_speed += foot_speeds(truth)[contacts].sum()
        steps += contacts.sum()
        errors += len(joints) * np.array([mpjpe(joints, truth), pa_mpjpe(joints, truth),
                                          acceleration_error(joints, truth)])
        frames += len(joints)
    return speed / steps, truth_speed / steps, *(errors / frames)


def choose(results, tie=TIE):
    """The module's choice rule over ``results`` [(setting, score(...))]: the (setting, score)
    whose toes move slowest among those no faster than the truth's on its contacts and within
    ``tie`` metres of their least PA-MPJPE; None if no setting is as still as the truth."""
    fitting = [(setting, result) for setting, result in results if result[0] <= result[1]]
    if not fitting:
        return None
    least = min(result[3] for _, result in fitting)
    return min(((setting, result) for setting, result in fitting if result[3] <= least + tie),
               key=lambda item: item[1][0])


def report(label, result):
    """One printed row: toe speed (the truth's), then MPJPE, PA-MPJPE and Acc."""
    speed, truth, *errors = result
    return f"{label:<60} {speed:.3f} ({truth:.3f})  " + "  ".join(f"{e:.5f}" for e in errors)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--cmu", default="../shared/data/cmu", help="CMU data directory")
    parser.add_argument("--cache", default="runs/tune_contacts", help="validation cache")
    args = parser.parse_args(argv)
    weights = load_weights(args.weights)
    streams = validation_streams(weights, args.cmu, args.cache)
    none = score(weights, streams, None)
    print(f"{'setting':<60} toe speed (truth)  MPJPE  PA-MPJPE  Acc")
    print(report("no foot lock", none), flush=True)
    results = []
    for values in itertools.product(*GRID.values()):
        lock = FootLock(**dict(zip(GRID, values)))
        if lock.plant_speed > lock.lift_speed:
            continue
        result = score(weights, streams, lock)
        results.append((lock, result))
        print(report(str(tuple(lock)), result), flush=True)
    chosen = choose(results)
    if chosen is None:
        sys.exit("no setting keeps the toes as still as the truth's")
    lock, result = chosen
    print(f"chosen: {lock}\n  toe speed {result[0]:.3f} m/s (truth {result[1]:.3f}, no lock "
          f"{none[0]:.3f}); MPJPE {none[2]:.5f} -> {result[2]:.5f}, PA-MPJPE {none[3]:.5f} -> "
          f"{result[3]:.5f}, Acc {none[4]:.5f} -> {result[4]:.5f}")


if __name__ == "__main__":
    main()
