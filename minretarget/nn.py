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


class GRULayer(NamedTuple):
    input_weight: np.ndarray    # (in, 3H) float32, gates in torch's order: reset, update, new
    hidden_weight: np.ndarray   # (H, 3H)
    input_bias: np.ndarray      # (3H,)
    hidden_bias: np.ndarray     # (3H,)


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


@kernel
def gru_layer_step(x, hidden, layer):
    """One GRU cell step, torch's equations. x (1, in), hidden (1, H) -> new hidden (1, H)."""
    h = hidden.shape[1]
    gates_x = dense(x, Dense(layer.input_weight, layer.input_bias), False)       # (1, 3H)
    gates_h = dense(hidden, Dense(layer.hidden_weight, layer.hidden_bias), False)
    out = np.empty_like(hidden)
    for k in range(h):
        reset = sigmoid(gates_x[0, k] + gates_h[0, k])
        update = sigmoid(gates_x[0, h + k] + gates_h[0, h + k])
        new = np.tanh(gates_x[0, 2 * h + k] + reset * gates_h[0, 2 * h + k])
        out[0, k] = (np.float32(1.0) - update) * new + update * hidden[0, k]
    return out


@kernel
def gru_step(x, hidden, layers):
    """Stacked GRU step; updates ``hidden`` (layers, H) in place, returns the top output."""
    for i in range(len(layers)):
        x = gru_layer_step(x, hidden[i:i + 1], layers[i])
        for k in range(x.shape[1]):     # not hidden[i] = x[0]: numba compiles slice
            hidden[i, k] = x[0, k]      # assignments' shape check slowly (issue 40)
    return x
