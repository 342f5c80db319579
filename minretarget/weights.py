"""The weights file: one flat ``.npz`` holding every network, loaded without pickle.

Keys are the dotted paths of the runtime's weight NamedTuples, e.g.
``skr.regressor.point.0.weight`` or ``smrm.encoder.1.hidden_weight``; linear weights are
stored (in, out), the layout the kernels multiply with. Besides the arrays:
    format_version   int scalar, FORMAT_VERSION
    config           JSON string of minretarget.config.ModelConfig
    metadata         JSON string: free-form provenance (recipe, data, commit)
Arrays may be stored as float16 or float32; they are always float32 in memory.

The default weights shipped in ``data/`` are verified at load against the SHA-256 recorded
next to them (``default_weights.sha256``, the ``sha256sum`` format), so a damaged or swapped
file is refused. After replacing them, record the new checksum:

    python -m minretarget.checksum
"""
import hashlib
import io
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .atomic import atomic_write
from .config import ModelConfig
from .formats.npz import load_npz
from .nn import MLP, Dense, GRULayer
from .denoise import DenoiserWeights
from .refine import RefinerWeights
from .rest_pose import NUM_BONES, NUM_FEATURES, RestPoseWeights
from .skr import PointNetWeights, SKRWeights
from .smrm import SMRMWeights

FORMAT_VERSION = 1
DEFAULT_WEIGHTS = Path(__file__).parent / "data" / "default_weights.npz"
_HEADER_KEYS = ("format_version", "config", "metadata")


class Weights(NamedTuple):
    config: ModelConfig
    skr: SKRWeights
    smrm: SMRMWeights
    skin: MLP          # the skinning field
    metadata: dict
    refine: RefinerWeights = None    # the joint refiner, if the config has one
    denoise: DenoiserWeights = None  # the skeleton denoiser, if the config has one
    rest_pose: RestPoseWeights = None  # the rest-pose model, if the config has one
    skr_view: SKRWeights = None      # the one-view SKR, if the config has one


class _Shape(tuple):
    """A leaf of the weight template: the shape an array must have."""


def _dense_chain(in_width, widths):
    """Dense layers in_width -> widths[0] -> ... -> widths[-1], as a tuple of templates."""
    return tuple(Dense(_Shape((a, b)), _Shape((b,)))
                 for a, b in zip((in_width,) + tuple(widths[:-1]), widths))


def _mlp_template(in_width, hidden_widths, out_width):
    width = hidden_widths[-1] if hidden_widths else in_width
    return MLP(_dense_chain(in_width, hidden_widths),
               Dense(_Shape((width, out_width)), _Shape((out_width,))))


def _pointnet_template(in_width, config, out_width):
    widths = config.skr_point_widths
    return PointNetWeights(_dense_chain(in_width, widths),
                           _mlp_template(widths[-1], config.skr_head_widths, out_width))


def _gru_template(in_width, h, depth):
    layers = []
    for i in range(depth):
        layers.append(GRULayer(_Shape((in_width if i == 0 else h, 3 * h)), _Shape((h, 3 * h)),
                               _Shape((3 * h,)), _Shape((3 * h,))))
    return tuple(layers)


def weight_template(config):
    """The nested weight NamedTuples for ``config`` with shapes at the leaves."""
    j, w0, h = config.num_joints, config.skr_point_widths[0], config.smrm_hidden
    skr = SKRWeights(_pointnet_template(3, config, 9),
                     _pointnet_template(w0, config, w0 * w0),
                     _pointnet_template(3, config, j * 3))
    depth = config.smrm_layers
    smrm = SMRMWeights(_gru_template(j * 3 + 3, h, depth), _gru_template(h + j * 3, h, depth),
                       Dense(_Shape((h, j * 4)), _Shape((j * 4,))),
                       Dense(_Shape((h, 3)), _Shape((3,))), config.smrm_analytic_prior)
    skin = _mlp_template(j * 3, config.skin_widths, j)
    stages = {"skr": skr, "smrm": smrm, "skin": skin}
    if config.refines:
        widths = config.refine_point_widths
        stages["refine"] = RefinerWeights(
            _dense_chain(3, widths), _mlp_template(widths[-1] + 4 * j,
                                                   config.refine_head_widths, 3))
    if config.denoises:
        stages["denoise"] = DenoiserWeights(
            _gru_template(j * 3 + 3, config.denoise_hidden, config.denoise_layers),
            Dense(_Shape((config.denoise_hidden, j * 3)), _Shape((j * 3,))))
    if config.rest_pose:
        stages["rest_pose"] = RestPoseWeights(_Shape((NUM_FEATURES, 3 * NUM_BONES)))
    if config.skr_view:
        stages["skr_view"] = skr
    return stages


def _leaves(tree, prefix):
    """Yield (dotted key, leaf) for every array leaf of nested NamedTuples and tuples (flags
    such as ``SMRMWeights.analytic_prior`` come from the config, not the file)."""
    if isinstance(tree, (_Shape, np.ndarray)):
        yield prefix, tree
    elif isinstance(tree, tuple):
        names = tree._fields if hasattr(tree, "_fields") else range(len(tree))
        for name, child in zip(names, tree):
            yield from _leaves(child, f"{prefix}.{name}")


def _rebuild(tree, prefix, arrays):
    """Replace every array leaf of ``tree`` by ``arrays[its dotted key]`` (flags stay)."""
    if isinstance(tree, (_Shape, np.ndarray)):
        return arrays[prefix]
    if not isinstance(tree, tuple):
        return tree
    if hasattr(tree, "_fields"):
        return type(tree)(*(_rebuild(c, f"{prefix}.{n}", arrays)
                            for n, c in zip(tree._fields, tree)))
    return tuple(_rebuild(c, f"{prefix}.{i}", arrays) for i, c in enumerate(tree))


def flatten_weights(weights):
    """Weights -> {key: array} with the header keys, ready for ``np.savez``."""
    arrays = {"format_version": np.array(FORMAT_VERSION),
              "config": np.array(weights.config.to_json()),
              "metadata": np.array(json.dumps(weights.metadata, sort_keys=True))}
    for stage in ("skr", "smrm", "skin", "refine", "denoise", "rest_pose", "skr_view"):
        if getattr(weights, stage) is not None:
            arrays.update(_leaves(getattr(weights, stage), stage))
    return arrays


def weights_from_arrays(arrays, source="weights"):
    """Check a {key: array} mapping and build Weights; errors name ``source`` and the key."""
    def header(key):
        if key not in arrays:
            raise ValueError(f"{source}: missing key '{key}'")
        value = np.asarray(arrays[key])
        if value.ndim != 0:
            raise ValueError(f"{source}: key '{key}' must be a scalar, got shape {value.shape}")
        return value[()]

    version = header("format_version")
    version = int(version) if isinstance(version, (int, np.integer)) else version
    if version != FORMAT_VERSION:
        raise ValueError(f"{source}: format_version is {version!r}; this minretarget reads "
                         f"version {FORMAT_VERSION}")
    try:
        config = ModelConfig.from_json(str(header("config")))
        metadata = json.loads(str(header("metadata")))
    except (ValueError, TypeError) as error:
        raise ValueError(f"{source}: bad config or metadata: {error}") from None

    template = weight_template(config)
    expected = {key: shape for stage, tree in template.items() for key, shape in _leaves(tree, stage)}
    missing = sorted(set(expected) - set(arrays))
    extra = sorted(set(arrays) - set(expected) - set(_HEADER_KEYS))
    if missing or extra:
        raise ValueError(f"{source}: key set does not match the config; "
                         f"missing {missing[:5]}{'...' if len(missing) > 5 else ''}, "
                         f"unexpected {extra[:5]}{'...' if len(extra) > 5 else ''}")
    loaded = {}
    for key, shape in expected.items():
        array = np.asarray(arrays[key])
        if array.dtype not in (np.float32, np.float16):
            raise ValueError(f"{source}: key '{key}' has dtype {array.dtype}; "
                             "float32 or float16 expected")
        if array.shape != tuple(shape):
            raise ValueError(f"{source}: key '{key}' has shape {array.shape}; "
                             f"expected {tuple(shape)}")
        if not np.isfinite(array).all():
            raise ValueError(f"{source}: key '{key}' holds NaN or inf")
        loaded[key] = np.ascontiguousarray(array, dtype=np.float32)
    stages = {stage: _rebuild(tree, stage, loaded) for stage, tree in template.items()}
    return Weights(config=config, metadata=metadata, **stages)


def load_weights(path=None):
    """Load a weights file (``None``: the default weights shipped with minretarget).

    Raises FileNotFoundError if the file is absent and ValueError naming the file and the key
    if its content is not a valid weights file (pickled objects are refused, never loaded).
    """
    path = Path(DEFAULT_WEIGHTS if path is None else path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    if path.resolve() != Path(DEFAULT_WEIGHTS).resolve():
        return _load_npz(path, path)
    data = path.read_bytes()                  # checked and loaded from the same bytes
    verify_checksum(path, hashlib.sha256(data).hexdigest())
    return _load_npz(io.BytesIO(data), path)


def _load_npz(file, path):
    return weights_from_arrays(load_npz(file, path), source=str(path))


def checksum_path(path):
    """Where the SHA-256 of a shipped weights file is recorded: ``<name>.sha256`` beside it."""
    return Path(path).with_suffix(".sha256")


def file_sha256(path):
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def verify_checksum(path, actual=None):
    """Raise ValueError unless ``path`` (or its bytes' hex SHA-256 ``actual``) matches the
    SHA-256 recorded in ``checksum_path(path)``."""
    record = checksum_path(path)
    try:
        expected = record.read_text(encoding="ascii").split()[0].lower()
    except (OSError, UnicodeDecodeError, IndexError):
        raise ValueError(f"{path}: no readable recorded checksum ({record}); if these are "
                         "the intended default weights, record it: python -m "
                         "minretarget.checksum") from None
    actual = file_sha256(path) if actual is None else actual
    if actual != expected:
        raise ValueError(f"{path}: SHA-256 {actual} differs from the recorded {expected} "
                         f"({record}): the file is damaged or was replaced; reinstall "
                         "minretarget, or record the new file's checksum with python -m "
                         "minretarget.checksum")


def record_checksum(path=None):
    """Check that ``path`` (None: the default weights) loads, then write its SHA-256 to
    ``checksum_path(path)`` in the ``sha256sum`` format. Returns the hex digest."""
    path = Path(DEFAULT_WEIGHTS if path is None else path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    _load_npz(path, path)
    digest = file_sha256(path)
    with atomic_write(checksum_path(path)) as file:
        file.write(f"{digest}  {path.name}\n".encode("ascii"))
    return digest


def save_weights(path, weights, dtype=np.float32):
    """Write Weights to ``path`` atomically; floating-point arrays stored as ``dtype``."""
    arrays = {key: (value.astype(dtype) if value.dtype.kind == "f" else value)
              for key, value in flatten_weights(weights).items()}
    with atomic_write(path) as file:
        np.savez(file, **arrays)

