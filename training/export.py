"""Export the torch reference to the runtime's weights file (minretarget.weights), and back.

Batch norm (eval statistics) is folded into the preceding linear layer, and every linear
weight is transposed to the runtime's (in, out) layout. ``import_weights`` goes the other way,
so training can start from an exported file (the shipped weights, say): its batch norms come
back folded, as ``nn.Identity``.

Every exported file's metadata says which splits may choose it (``selected_on``,
``SELECTED_ON``): validation and the training dances, never the test split.
"""
import dataclasses
import numpy as np
import torch

from minretarget.denoise import DenoiserWeights
from minretarget.nn import MLP, Dense, GRULayer
from minretarget.refine import RefinerWeights
from minretarget.rest_pose import RestPoseWeights
from minretarget.skr import PointNetWeights, SKRWeights
from minretarget.smoothing import Smoothing
from minretarget.smrm import SMRMWeights
from minretarget.weights import Weights, save_weights, weights_from_arrays, flatten_weights


# The splits that choose weights: between checkpoints, settings and candidates, and whether a
# candidate ships (docs/training.md, "How a candidate is chosen"). The test split is not among
# them: it is scored once per release, for the report (the benchmarks refuse it without
# --report). Written into the metadata of every exported file as ``selected_on``.
SELECTED_ON = ("validation", "training dances")


def with_selection(metadata):
    """A copy of ``metadata`` (a dict, or None) with ``selected_on``: the splits the file
    may be chosen on (``SELECTED_ON``), replacing any an ``--init`` file carried."""
    return {**(metadata or {}), "selected_on": list(SELECTED_ON)}


def with_couplings(metadata, refine):
    """``metadata`` with ``pipeline``, what the denoiser learned from, unless it says already
    (``minretarget.pipeline.couplings``): ``training.train``'s denoiser learns SKR's readings,
    refined if the weights have a refiner, after ``Smoothing()`` (``smoothed_skeletons``)."""
    if "pipeline" in metadata:
        return metadata
    return {**metadata, "pipeline": {"denoiser_input": {
        "smoothing": Smoothing()._asdict(), "refine": refine, "fit_source": False}}}


def _array(tensor):
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=np.float32)


def _dense(linear, batch_norm=None):
    """nn.Linear or 1x1 nn.Conv1d (+ BatchNorm1d in eval mode) -> Dense (in, out)."""
    weight = linear.weight.detach().reshape(linear.weight.shape[0], -1).double()  # (out, in)
    bias = linear.bias.detach().double()
    if isinstance(batch_norm, torch.nn.BatchNorm1d):   # an imported model has Identity here
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
    # [Linear, BatchNorm1d or Identity] per hidden layer
    hidden = tuple(_dense(modules[i], modules[i + 1]) for i in range(0, len(modules), 2))
    return MLP(hidden, _dense(head.output))


def _linears(sequential):
    """The nn.Linear layers of a Sequential (activations between them) -> tuple of Dense."""
    return tuple(_dense(m) for m in sequential if isinstance(m, torch.nn.Linear))


def _gru(gru):
    return tuple(GRULayer(_array(getattr(gru, f"weight_ih_l{i}").T),
                          _array(getattr(gru, f"weight_hh_l{i}").T),
                          _array(getattr(gru, f"bias_ih_l{i}")),
                          _array(getattr(gru, f"bias_hh_l{i}")))
                 for i in range(gru.num_layers))


def skr_runtime_weights(skr):
    """SkeletonRegressor (eval-mode batch norm folded) -> the runtime's SKRWeights."""
    def transform(net):
        return PointNetWeights(_point_layers(net.points), _head(net.head))

    return SKRWeights(
        transform(skr.input_transform), transform(skr.feature_transform),
        PointNetWeights(_point_layers(skr.first) + _point_layers(skr.rest), _head(skr.head)))


def refine_runtime_weights(refine):
    """JointRefiner -> the runtime's RefinerWeights."""
    return RefinerWeights(_linears(refine.point),
                          MLP(_linears(refine.hidden), _dense(refine.output)))


def runtime_weights(skr, smrm, skin, metadata=None, refine=None, denoise=None, skr_view=None):
    """The torch modules -> minretarget Weights (checked against their config); ``refine``
    the JointRefiner and ``denoise`` the SkeletonDenoiser, if the config has them; SMRM's
    ``rest_directions`` (its config's ``rest_pose``) become the rest-pose model; ``skr_view``
    the one-view SKR's runtime SKRWeights, carried as they are (``training.skr_view``)."""
    config = smrm.config if refine is not None else smrm.config.without_refiner()
    config = config if denoise is not None else config.without_denoiser()
    config = dataclasses.replace(config, skr_view=skr_view is not None)
    skr_weights = skr_runtime_weights(skr)
    smrm_weights = SMRMWeights(_gru(smrm.encoder), _gru(smrm.decoder),
                               _dense(smrm.rotation_head), _dense(smrm.root_head),
                               smrm.config.smrm_analytic_prior)
    skin_weights = MLP(_linears(skin.hidden), _dense(skin.output))
    refine_weights = None if refine is None else refine_runtime_weights(refine)
    denoise_weights = None if denoise is None else DenoiserWeights(_gru(denoise.gru),
                                                                   _dense(denoise.head))
    rest_pose = (RestPoseWeights(_array(smrm.rest_directions)) if smrm.config.rest_pose
                 else None)
    metadata = with_couplings(with_selection(metadata), refine is not None)
    weights = Weights(config, skr_weights, smrm_weights, skin_weights, metadata,
                      refine_weights, denoise_weights, rest_pose, skr_view)
    # Round-trip through the loader's checks so a wrong export fails here, not at load.
    return weights_from_arrays(flatten_weights(weights), source="exported weights")


def export_weights(path, skr, smrm, skin, metadata=None, dtype=np.float32, refine=None,
                   denoise=None, skr_view=None):
    """Write the torch modules as one runtime weights file at ``path``."""
    save_weights(path, runtime_weights(skr, smrm, skin, metadata, refine, denoise, skr_view),
                 dtype=dtype)



# ----------------------------------------------------------------------------- import

def _set_dense(linear, dense):
    """Dense (in, out) -> nn.Linear or 1x1 nn.Conv1d weights (out, in[, 1])."""
    with torch.no_grad():
        linear.weight.copy_(torch.from_numpy(dense.weight.T.copy()).view_as(linear.weight))
        linear.bias.copy_(torch.from_numpy(dense.bias))


def _import_point_layers(point_layers, denses):
    for layer, dense in zip(point_layers.layers, denses, strict=True):
        _set_dense(layer[0], dense)
        layer[1] = torch.nn.Identity()


def _import_head(head, mlp):
    linears = [i for i, m in enumerate(head.hidden) if isinstance(m, torch.nn.Linear)]
    for i, dense in zip(linears, mlp.hidden, strict=True):
        _set_dense(head.hidden[i], dense)
        head.hidden[i + 1] = torch.nn.Identity()
    _set_dense(head.output, mlp.output)


def _import_linears(sequential, denses):
    linears = [m for m in sequential if isinstance(m, torch.nn.Linear)]
    for linear, dense in zip(linears, denses, strict=True):
        _set_dense(linear, dense)


def _import_gru(gru, layers):
    with torch.no_grad():
        for i, layer in enumerate(layers):
            for name, array in zip(("weight_ih", "weight_hh", "bias_ih", "bias_hh"),
                                   (layer.input_weight.T, layer.hidden_weight.T,
                                    layer.input_bias, layer.hidden_bias)):
                getattr(gru, f"{name}_l{i}").copy_(torch.from_numpy(array.copy()))


def import_skr(skr, runtime):
    """The runtime's SKRWeights into a SkeletonRegressor, in place (batch norms folded, as
    ``import_weights``)."""
    for net, weights in ((skr.input_transform, runtime.input_transform),
                         (skr.feature_transform, runtime.feature_transform)):
        _import_point_layers(net.points, weights.point)
        _import_head(net.head, weights.head)
    first = len(skr.first.layers)
    _import_point_layers(skr.first, runtime.regressor.point[:first])
    _import_point_layers(skr.rest, runtime.regressor.point[first:])
    _import_head(skr.head, runtime.regressor.head)


def import_weights(weights, skr, smrm, skin, refine=None, denoise=None):
    """Load runtime Weights into the torch modules, in place (their config must match).

    Folded batch norms become ``nn.Identity``, so the imported SKR computes exactly what
    the file does and trains on as a network without batch norm.
    """
    # Without a refiner to load, weights from before it (no refiner) fit modules with one;
    # the analytic prior changes what SMRM's rotation head means, not the shapes (see
    # train.initial_models, which then resets that head); the rest-pose model is loaded when
    # both have one (train.main gives the modules one when the weights have it); a one-view
    # SKR is not trained by ``train`` (training.skr_view): the caller carries it along.
    mine, theirs = (dataclasses.replace(c, smrm_analytic_prior=False, rest_pose=False,
                                        skr_view=False)
                    for c in (smrm.config, weights.config))
    if refine is None:
        mine, theirs = mine.without_refiner(), theirs.without_refiner()
    if denoise is None:
        mine, theirs = mine.without_denoiser(), theirs.without_denoiser()
    if mine != theirs:
        raise ValueError(f"the weights' config {weights.config} is not the modules' "
                         f"{smrm.config}")
    import_skr(skr, weights.skr)
    _import_gru(smrm.encoder, weights.smrm.encoder)
    _import_gru(smrm.decoder, weights.smrm.decoder)
    _set_dense(smrm.rotation_head, weights.smrm.rotation_head)
    _set_dense(smrm.root_head, weights.smrm.root_head)
    if smrm.config.rest_pose != (weights.rest_pose is not None):
        raise ValueError(f"the modules' config has rest_pose={smrm.config.rest_pose}, the "
                         f"weights {'have' if weights.rest_pose is not None else 'have no'} "
                         "rest-pose model (training.rest_pose fits one)")
    if weights.rest_pose is not None:
        with torch.no_grad():
            smrm.rest_directions.copy_(torch.from_numpy(weights.rest_pose.directions))
    _import_linears(skin.hidden, weights.skin.hidden)
    _set_dense(skin.output, weights.skin.output)
    if refine is not None:
        _import_linears(refine.point, weights.refine.point)
        _import_linears(refine.hidden, weights.refine.head.hidden)
        _set_dense(refine.output, weights.refine.head.output)
    if denoise is not None:
        _import_gru(denoise.gru, weights.denoise.gru)
        _set_dense(denoise.head, weights.denoise.head)
