"""Export the torch reference to the runtime's weights file (minretarget.weights).

Batch norm (eval statistics) is folded into the preceding linear layer, and every linear
weight is transposed to the runtime's (in, out) layout.
"""
import numpy as np
import torch

from minretarget.nn import MLP, Dense
from minretarget.skr import PointNetWeights, SKRWeights
from minretarget.smrm import GRULayer, SMRMWeights
from minretarget.weights import Weights, save_weights, weights_from_arrays, flatten_weights


def _array(tensor):
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=np.float32)


def _dense(linear, batch_norm=None):
    """nn.Linear or 1x1 nn.Conv1d (+ BatchNorm1d in eval mode) -> Dense (in, out)."""
    weight = linear.weight.detach().reshape(linear.weight.shape[0], -1).double()  # (out, in)
    bias = linear.bias.detach().double()
    if batch_norm is not None:
        scale = batch_norm.weight.double() / torch.sqrt(batch_norm.running_var.double()
                                                        + batch_norm.eps)
        weight = weight * scale[:, None]
        bias = (bias - batch_norm.running_mean.double()) * scale + batch_norm.bias.double()
    return Dense(_array(weight.T), _array(bias))


def _point_layers(point_layers):
    """PointLayers -> tuple of Dense (each Sequential is conv, batch norm, ReLU)."""
    return tuple(_dense(layer[0], layer[1]) for layer in point_layers.layers)


def _head(head):
    """skr.Head -> MLP: hidden is [Linear, BatchNorm1d, ReLU]* (+ Dropout)."""
    modules = [m for m in head.hidden if not isinstance(m, (torch.nn.ReLU, torch.nn.Dropout))]
    hidden = tuple(_dense(modules[i], modules[i + 1]) for i in range(0, len(modules), 2))
    return MLP(hidden, _dense(head.output))


def _gru(gru):
    return tuple(GRULayer(_array(getattr(gru, f"weight_ih_l{i}").T),
                          _array(getattr(gru, f"weight_hh_l{i}").T),
                          _array(getattr(gru, f"bias_ih_l{i}")),
                          _array(getattr(gru, f"bias_hh_l{i}")))
                 for i in range(gru.num_layers))


def runtime_weights(skr, smrm, skin, metadata=None):
    """The three torch modules -> minretarget Weights (checked against their config)."""
    config = smrm.config

    def transform(net):
        return PointNetWeights(_point_layers(net.points), _head(net.head))

    skr_weights = SKRWeights(
        transform(skr.input_transform), transform(skr.feature_transform),
        PointNetWeights(_point_layers(skr.first) + _point_layers(skr.rest), _head(skr.head)))
    smrm_weights = SMRMWeights(_gru(smrm.encoder), _gru(smrm.decoder),
                               _dense(smrm.rotation_head), _dense(smrm.root_head))
    linears = [m for m in skin.hidden if isinstance(m, torch.nn.Linear)]
    skin_weights = MLP(tuple(_dense(m) for m in linears), _dense(skin.output))
    weights = Weights(config, skr_weights, smrm_weights, skin_weights, dict(metadata or {}))
    # Round-trip through the loader's checks so a wrong export fails here, not at load.
    return weights_from_arrays(flatten_weights(weights), source="exported weights")


def export_weights(path, skr, smrm, skin, metadata=None, dtype=np.float32):
    """Write the three torch modules as one runtime weights file at ``path``."""
    save_weights(path, runtime_weights(skr, smrm, skin, metadata), dtype=dtype)

