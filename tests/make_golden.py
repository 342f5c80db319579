"""Regenerate tests/golden/: a tiny random model's weights, inputs and torch outputs; or
(--shipped) every pipeline preset's output on the shipped weights and sample.

    python tests/make_golden.py [--shipped]
The runtime's tests compare against these files, so they run where torch is not installed;
test_parity.py checks that the tiny model's still match the current torch reference. The
shipped outputs change only when a release changes the pipeline on purpose: regenerate them
then, and say so in the commit.
"""
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))   # `training`, from the checkout
from reference_models import random_reference, random_stream  # noqa: E402

from conftest import SHIPPED_FRAMES, SHIPPED_VERTEX_STRIDE, one_sided  # noqa: E402
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


def shipped_outputs():
    """Each preset of minretarget.pipeline streamed over the shipped sample's first
    SHIPPED_FRAMES clouds with the shipped weights (one BLAS thread): {f"{preset}_{field}"};
    and the fitted preset told a camera on those clouds' one-sided halves (``one_sided``):
    {f"fitted_viewpoint_{field}"}."""
    from threadpoolctl import threadpool_limits

    from minretarget.pipeline import PRESETS
    from minretarget.retargeter import Retargeter
    from minretarget.sources import load_sample
    source, target_points, faces, _ = load_sample()
    clouds = [cloud for cloud, _ in zip(source.frames, range(SHIPPED_FRAMES))]
    outputs = {}
    told, camera = one_sided(clouds)
    with threadpool_limits(1):
        for name, (preset, streamed, viewpoint) in {
                **{name: (name, clouds, None) for name in PRESETS},
                "fitted_viewpoint": ("fitted", told, camera)}.items():
            retargeter = Retargeter.from_weights(None, preset, warn=False)
            retargeter.set_target(target_points, faces)
            frames = list(retargeter.run(streamed, viewpoint))
            for field in ("joints", "rotations", "root", "source_joints"):
                outputs[f"{name}_{field}"] = np.stack([getattr(f, field) for f in frames])
            outputs[f"{name}_vertices"] = np.stack(
                [f.vertices[::SHIPPED_VERTEX_STRIDE] for f in frames])
    return outputs


if __name__ == "__main__":
    if sys.argv[1:] == ["--shipped"]:
        np.savez_compressed(GOLDEN / "shipped_presets.npz", **shipped_outputs())
    elif not sys.argv[1:]:
        main()
    else:
        sys.exit(__doc__)
