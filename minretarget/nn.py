"""Layers shared by the networks: weight containers and their numba kernels.

Weights are NamedTuples of float32 arrays (numba passes them into kernels as they are);
a linear layer maps rows: ``x (N, in) @ weight (in, out) + bias (out,)``.
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel


class Dense(NamedTuple):
    weight: np.ndarray   # (in, out) float32
    bias: np.ndarray     # (out,) float32


class MLP(NamedTuple):
    hidden: tuple        # Dense layers, each followed by ReLU
    output: Dense        # the last layer, no activation


@kernel
def dense(x, layer, relu):
    """x (N, in) -> (N, out); ReLU applied if ``relu``."""
    y = np.dot(x, layer.weight)
    n, m = y.shape
    for i in range(n):
        for k in range(m):
            value = y[i, k] + layer.bias[k]
            y[i, k] = max(value, np.float32(0.0)) if relu else value
    return y


@kernel
def mlp(x, weights):
    """x (N, in) -> (N, out) through ``weights.hidden`` (ReLU) and ``weights.output``."""
    for layer in weights.hidden:
        x = dense(x, layer, True)
    return dense(x, weights.output, False)


@kernel
def sigmoid(x):
    return np.float32(1.0) / (np.float32(1.0) + np.exp(-x))
