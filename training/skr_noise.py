"""Measure the errors SKR (and the joint refiner) make on moving validation bodies, to train
SMRM to absorb them.

    python -m training.skr_noise [--weights FILE] [--cmu DIR] [--sequences N] [--frames T]

SMRM is trained on ground-truth skeletons plus noise (``SMRMStage.input_noise``, or
``input_noise_bias``, ``input_noise_frame`` and ``input_noise_autocorrelation``). At run time
its input is SKR's estimate, whose error has two parts that a recurrent network must treat
differently: a part that stays nearly constant along a clip (the body's shape misjudged, a
bone too long) and a part that changes every frame (jitter from the fresh point sample). This
plays validation trials (held-out subjects) on validation bodies, samples clouds as the test
benchmark does, runs the runtime's SKR (then the joint refiner, if the weights have one:
the skeleton before smoothing and the denoiser) and splits the residual r_t (T, J, 3) of
each sequence into its mean over the sequence (the bias) and the rest. It prints the standard
deviation of each (metres, per coordinate), overall and per joint, and the lag-1
autocorrelation of the rest (0: white jitter).
Never the test split.
"""
import argparse
import json

import numpy as np

from minretarget.atomic import atomic_write
from minretarget.conventions import JOINT_NAMES
from minretarget.retargeter import Retargeter
from minretarget.weights import load_weights
from training.data.bodies import body_from_seed, posed_clouds, sampled_body_seeds
from training.data.datasets import cmu_motions


def residuals(weights, motions, bodies, actor_hip_height, frames, points, rng):
    """The source skeleton's error on each motion, played on a body in turn: list of
    (T, J, 3), metres."""
    skeleton = Retargeter(weights, warn=False).skeleton
    out = []
    for index, motion in enumerate(motions):
        body = bodies[index % len(bodies)]
        rotations = np.asarray(motion.rotations[:frames], np.float32)
        root = (motion.root[:frames] * (body.hip_height / actor_hip_height)).astype(np.float32)
        clouds, joints = posed_clouds(body, rotations, root, points, rng)
        out.append(skeleton(clouds) - joints)
    return out


def noise_statistics(errors):
    """list of (T, J, 3) residuals -> bias and jitter standard deviations (metres)."""
    bias = np.stack([e.mean(axis=0) for e in errors])                     # (S, J, 3)
    rests = [e - e.mean(axis=0) for e in errors]                         # each (T, J, 3)
    rest = np.concatenate(rests)                                          # (sum T, J, 3)
    autocorrelation = (sum(float((r[1:] * r[:-1]).sum()) for r in rests)
                       / sum(float((r[:-1] ** 2).sum()) for r in rests))
    return {"bias_std": float(bias.std()), "frame_std": float(rest.std()),
            "total_rms": float(np.sqrt(np.mean(np.concatenate(errors) ** 2))),
            "frame_lag1_autocorrelation": autocorrelation,
            "per_joint": {name: {"bias_std": float(bias[:, j].std()),
                                 "frame_std": float(rest[:, j].std())}
                          for j, name in enumerate(JOINT_NAMES)}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--cmu", default="../shared/data/cmu")
    parser.add_argument("--sequences", type=int, default=12, help="validation trials to play")
    parser.add_argument("--frames", type=int, default=150, help="frames of each trial")
    parser.add_argument("--points", type=int, default=2048, help="points per cloud")
    parser.add_argument("--json", help="write the statistics here")
    args = parser.parse_args(argv)
    weights = load_weights(args.weights)
    motions, actor_hip_height = cmu_motions(args.cmu)
    bodies = [body_from_seed(seed) for seed in sampled_body_seeds(15, "val")]
    rng = np.random.default_rng(0)
    chosen = [motions["val"][i] for i in rng.permutation(len(motions["val"]))[:args.sequences]]
    statistics = noise_statistics(residuals(weights, chosen, bodies, actor_hip_height,
                                            args.frames, args.points, rng))
    print(json.dumps({k: v for k, v in statistics.items() if k != "per_joint"}, indent=1))
    for name, values in statistics["per_joint"].items():
        print(f"{name:>16}: bias {100 * values['bias_std']:.1f} cm, "
              f"frame {100 * values['frame_std']:.1f} cm")
    if args.json:
        with atomic_write(args.json) as file:
            file.write(json.dumps(statistics, indent=1).encode())


if __name__ == "__main__":
    main()
