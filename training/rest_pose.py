"""Fit the rest-pose model (minretarget.rest_pose) on anny bodies (its torch twin:
training.models.rest_pose).

The map from a body's features (its bone lengths) to its rest bone directions is linear, fitted
by ridge regression on the T-poses of ``bodies`` training bodies (their seeds, as
``training.data.bodies.sampled_body_seeds`` draws them; no validation or test body). The
lengths the runtime measures are SKR's, off by 5 to 12 % per bone, so each body enters
``copies`` times with its bone lengths scaled by 1 + ``noise`` x N(0, 1): a fit on exact
lengths reads that noise as shape (the analytic retargeting of the validation trials' runtime
skeletons then scores PA-MPJPE 0.0241 against the plain prior's 0.0226; with 8 % noise
0.0222), one on noisy lengths keeps what they can predict.

    python -m training.rest_pose --init minretarget/data/default_weights.npz \\
        --out runs/rest_pose/weights.npz [--bodies 2000] [--noise 0.08]

writes the weights of ``--init`` with the model added (``config.rest_pose``), provenance in
its metadata, in about 90 s on this machine (anny builds the 2,000 bodies).
"""
import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

from minretarget.conventions import PARENTS
from minretarget.rest_pose import RestPoseWeights, bone_lengths, rest_pose_features
from minretarget.weights import load_weights, save_weights
from training.export import with_selection
from training.train import current_commit

RIDGE = 1e-4
COPIES = 20         # noisy copies of each body


def bone_directions(joints):
    """(..., J, 3) joints -> (..., B, 3) unit bone directions (bone b ends at joint b + 1)."""
    joints = np.asarray(joints, dtype=np.float64)
    bones = joints[..., 1:, :] - joints[..., np.asarray(PARENTS[1:]), :]
    return bones / np.linalg.norm(bones, axis=-1, keepdims=True)


def fit_rest_pose(tpose_joints, noise=0.08, copies=COPIES, ridge=RIDGE, seed=0):
    """Ridge regression of rest bone directions on features of noisy bone lengths.

    Args:
        tpose_joints: (N, J, 3) float32 T-pose joints of N bodies, metres.
        noise: relative standard deviation of the noise put on each bone length.
        copies: noisy copies of each body (1 with ``noise`` 0).
        ridge: the regression's ridge (on the sums over all rows).
        seed: seed of the noise.
    Returns:
        RestPoseWeights.
    """
    tpose_joints = np.asarray(tpose_joints, dtype=np.float32)
    rng = np.random.default_rng(seed)
    lengths = np.repeat(bone_lengths(tpose_joints), copies, axis=0).astype(np.float64)
    lengths *= 1.0 + noise * rng.standard_normal(lengths.shape)
    features = rest_pose_features(np.abs(lengths).astype(np.float32)).astype(np.float64)
    directions = np.repeat(bone_directions(tpose_joints).reshape(len(tpose_joints), -1),
                           copies, axis=0)
    # A little ridge: the relative lengths sum to one, so the features are collinear.
    gram = features.T @ features + ridge * np.eye(features.shape[1])
    solution = np.linalg.solve(gram, features.T @ directions)
    return RestPoseWeights(np.ascontiguousarray(solution, dtype=np.float32))


# ----------------------------------------------------------------------------- command line

def training_tpose_joints(count):
    """(count, J, 3) T-pose joints of the first ``count`` sampled training bodies (built with
    anny, not cached: 2,000 bodies would fill the cache with 3 GB of meshes)."""
    from tqdm import tqdm
    from training.data.bodies import build_body, phenotype_from_seed, sampled_body_seeds
    seeds = sampled_body_seeds(count, "train")
    return np.stack([build_body(phenotype_from_seed(seed), f"seed_{seed}").joints
                     for seed in tqdm(seeds, desc="bodies", file=sys.stderr)])


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m training.rest_pose",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--init", type=Path, required=True,
                        help="weights file to add the rest-pose model to")
    parser.add_argument("--out", type=Path, required=True, help="weights file to write")
    parser.add_argument("--bodies", type=int, default=2000,
                        help="training bodies to fit on (default 2000)")
    parser.add_argument("--noise", type=float, default=0.08,
                        help="relative noise put on their bone lengths (default 0.08)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch threads (anny)")
    args = parser.parse_args(argv)
    if args.bodies < 30 or not 0 <= args.noise < 1:
        parser.error("--bodies must be at least 30 and --noise in [0, 1)")
    torch.set_num_threads(args.threads)
    weights = load_weights(args.init)
    if not weights.config.smrm_analytic_prior:
        parser.error(f"{args.init}: its SMRM has no analytic prior for the rest poses to move")
    model = fit_rest_pose(training_tpose_joints(args.bodies), args.noise, seed=args.seed)
    metadata = with_selection(dict(weights.metadata, rest_pose={
        "bodies": args.bodies, "noise": args.noise, "copies": COPIES, "ridge": RIDGE,
        "seed": args.seed, "fitted_on": "sampled training bodies (training.data.bodies)",
        "commit": current_commit()}))
    weights = weights._replace(config=dataclasses.replace(weights.config, rest_pose=True),
                               rest_pose=model, metadata=metadata)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_weights(args.out, weights)
    print(f"wrote {args.out}: rest-pose model fitted on {args.bodies} bodies")


if __name__ == "__main__":
    main()
