"""Regenerate tests/golden/: a tiny random model's weights, inputs and torch outputs.

    python tests/make_golden.py
The runtime's tests compare against these files, so they run where torch is not installed;
test_parity.py checks that the files still match the current torch reference.
"""
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))   # `training`, from the checkout
from reference_models import random_reference, random_stream  # noqa: E402

from minretarget.pipeline import UNCOUPLED  # noqa: E402
from training.export import export_weights  # noqa: E402

GOLDEN = Path(__file__).parent / "golden"


def reference_outputs(model, target, sources):
    """Stream the frames through the torch reference: dict of stacked outputs."""
    model.set_target(torch.from_numpy(target))
    steps = [model.step(torch.from_numpy(points)) for points in sources]
    outputs = {key: torch.stack([s[key] for s in steps]).numpy() for key in steps[0]}
    outputs["tpose_joints"] = model.tpose_joints.numpy()
    outputs["skin_weights"] = model.skin_weights.numpy()
    return outputs


def main():
    GOLDEN.mkdir(exist_ok=True)
    model = random_reference(seed=0)
    target, sources = random_stream(seed=0)
    export_weights(GOLDEN / "tiny_weights.npz", model.skr, model.smrm, model.skin,
                   metadata={"purpose": "tests: random tiny model", "seed": 0,
                             "pipeline": UNCOUPLED},
                   refine=model.refine, denoise=model.denoise)
    outputs = reference_outputs(model, target, sources)
    counts = np.array([len(s) for s in sources])
    np.savez_compressed(GOLDEN / "tiny_stream.npz", target=target,
                        source_points=np.concatenate(sources), source_counts=counts,
                        **{f"torch_{key}": value for key, value in outputs.items()})


if __name__ == "__main__":
    main()
