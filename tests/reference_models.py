"""Seeded torch reference models with every parameter random, for parity tests and goldens.

Default initialisation leaves the STN output layers at zero and batch norm at identity
statistics, which would hide mistakes in those paths; here every parameter and every batch
norm statistic is drawn at random, at scales that keep activations in a useful range.
"""
import numpy as np
import torch

from minretarget.config import ModelConfig
from training.models.pipeline import ReferenceRetargeter

TINY_CONFIG = ModelConfig(skr_point_widths=(16, 24, 48), skr_head_widths=(32, 24),
                          smrm_hidden=32, smrm_layers=2, skin_widths=(32, 32),
                          refine_point_widths=(16, 24), refine_head_widths=(24,),
                          refine_neighbours=40, denoise_hidden=16, denoise_layers=2)


def random_reference(config=TINY_CONFIG, seed=0):
    torch.manual_seed(seed)
    model = ReferenceRetargeter(config)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in model.parameters():
            fan_in = parameter.shape[-1] if parameter.ndim > 1 else 10
            parameter.copy_(torch.randn(parameter.shape, generator=generator) / np.sqrt(fan_in))
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm1d):
                module.running_mean.normal_(0.0, 0.1, generator=generator)
                module.running_var.uniform_(0.5, 1.5, generator=generator)
    return model.eval()


def random_stream(seed=0, frames=60, target_points=256, min_points=200, max_points=260):
    """A target cloud (V, 3) and source frames (P_t, 3) of changing size drifting along +X."""
    rng = np.random.default_rng(seed)
    target = (rng.normal(size=(target_points, 3)) * [0.3, 0.8, 0.15]).astype(np.float32)
    sources = [(rng.normal(size=(rng.integers(min_points, max_points), 3)) * [0.3, 0.8, 0.15]
                + [0.02 * t, 0.9, 0.0]).astype(np.float32) for t in range(frames)]
    return target, sources
