"""Largest difference between the runtime and the torch reference, per stage, on one stream.

    python benchmarks/parity.py [--frames 60] [--points 2048] [--target 13718]

The model: the paper recipe's sizes (the paper's, the joint refiner and the skeleton denoiser),
every parameter random (tests/reference_models.py).
The stream is a synthetic body-sized cloud drifting forward; the target a body-sized cloud.
"""
import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))   # `training`, from the checkout
from reference_models import random_reference, random_stream  # noqa: E402

from minretarget.cli import int_at_least  # noqa: E402
from minretarget.retargeter import Retargeter  # noqa: E402
from training.export import runtime_weights  # noqa: E402
from training.models.pipeline import RUNTIME_CONFIG  # noqa: E402
from training.recipe import load_recipe  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int_at_least(1), default=60)
    parser.add_argument("--points", type=int_at_least(64), default=2048)
    parser.add_argument("--target", type=int_at_least(64), default=13718)
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = random_reference(load_recipe("paper").model, seed=0)
    # Synthetic Gaussian clouds, not bodies: the unit and T-pose warnings do not apply.
    weights = runtime_weights(model.skr, model.smrm, model.skin, refine=model.refine,
                              denoise=model.denoise)
    # SMRM's output as it comes, as the torch reference gives it, its denoiser included.
    retargeter = Retargeter(weights, RUNTIME_CONFIG, warn=False)
    target, sources = random_stream(seed=0, frames=args.frames, target_points=args.target,
                                    min_points=args.points, max_points=args.points + 1)
    retargeter.set_target(target)
    model.set_target(torch.from_numpy(target))
    errors = {"SKR + refiner target (m)": np.abs(retargeter.target.tpose_joints
                                                 - model.tpose_joints.numpy()).max(),
              "SKIN weights": np.abs(retargeter.target.skin_weights
                                     - model.skin_weights.numpy()).max()}
    worst = {"source joints (m)": 0.0, "SMRM rotations": 0.0, "SMRM root (m)": 0.0,
             "FK joints (m)": 0.0, "LBS vertices (m)": 0.0}
    keys = {"source joints (m)": "source_joints", "SMRM rotations": "rotations",
            "SMRM root (m)": "root", "FK joints (m)": "joints", "LBS vertices (m)": "vertices"}
    for points in sources:
        ours, theirs = retargeter.step(points), model.step(torch.from_numpy(points))
        for label, key in keys.items():
            worst[label] = max(worst[label],
                               float(np.abs(getattr(ours, key) - theirs[key].numpy()).max()))
    errors.update(worst)
    print(f"max |runtime - torch| over {args.frames} frames, P = {args.points}, "
          f"V = {args.target}, paper-size random weights:")
    for label, value in errors.items():
        print(f"  {label:<26} {value:.2e}")


if __name__ == "__main__":
    main()
