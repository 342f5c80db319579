"""Training recipes: one JSON file holds the model sizes and every stage's schedule.

    training/recipes/paper.json   the paper's sizes and schedule (for a GPU)
    training/recipes/cpu.json     shrunk to finish within about 2 hours on 2 CPU cores
Unknown keys are errors, so a typo cannot silently fall back to a default.
"""
import dataclasses
import json
import math
from pathlib import Path

from minretarget.config import ModelConfig

RECIPES = Path(__file__).parent / "recipes"


@dataclasses.dataclass(frozen=True)
class SKRStage:
    steps: int = 20_000
    batch_size: int = 32
    learning_rate: float = 1e-4
    points: int = 2048           # source points per training cloud (a random subset per batch)
    tpose_fraction: float = 0.125  # of each batch: bodies in T-pose (skr_tpose_*.npz)
    eval_every: int = 1000


@dataclasses.dataclass(frozen=True)
class RefineStage:
    steps: int = 3000
    batch_size: int = 32
    learning_rate: float = 1e-3
    min_points: int = 1024       # each batch's clouds: a random subset of min_points to all
    tpose_fraction: float = 0.125
    eval_every: int = 250


@dataclasses.dataclass(frozen=True)
class DenoiseStage:
    steps: int = 3000
    batch_size: int = 64
    learning_rate: float = 1e-3
    window: int = 64             # frames of a training window (random, inside one trial)
    acceleration: float = 2.0    # weight of the acceleration error against the joint error
    foot_velocity: float = 0.0   # weight of the feet's velocity error on ground contacts
    eval_every: int = 250


@dataclasses.dataclass(frozen=True)
class SKINStage:
    steps: int = 10_000
    batch_size: int = 8
    learning_rate: float = 1e-4
    points: int = 1024           # surface points per sample
    joint_noise: float = 0.02    # metres: T-pose joints are jittered so SKR's errors do no harm
    eval_every: int = 1000


@dataclasses.dataclass(frozen=True)
class SMRMStage:
    steps: int = 40_000
    batch_size: int = 64
    learning_rate: float = 1e-4
    discriminator_learning_rate: float = 1e-4
    discriminator_width: int = 256
    clip_frames: int = 30        # frames of a training clip: random windows of the data's clips
    input_noise: float = 0.01    # metres of Gaussian noise on source joints, as SKR makes
    # Or noise shaped like SKR's measured error (python -m training.skr_noise): per joint,
    # the std (metres) of a part constant along a clip and of a part that changes from frame
    # to frame with this lag-1 autocorrelation. Empty: white noise of ``input_noise``.
    input_noise_bias: tuple = ()
    input_noise_frame: tuple = ()
    input_noise_autocorrelation: float = 0.0
    # Loss weights: joint cycle A -> B -> A, reconstruction A -> A, adversarial, rotation
    # cycle and smoothness (the last two as in the paper).
    cycle: float = 1.0
    reconstruction: float = 1.0
    adversarial: float = 0.01
    rotation_cycle: float = 0.01
    smoothness: float = 0.001
    eval_every: int = 1000


@dataclasses.dataclass(frozen=True)
class Recipe:
    name: str = "paper"
    seed: int = 0
    model: ModelConfig = ModelConfig()
    skr: SKRStage = SKRStage()
    refine: RefineStage = RefineStage()
    denoise: DenoiseStage = DenoiseStage()
    skin: SKINStage = SKINStage()
    smrm: SMRMStage = SMRMStage()

    def to_json(self):
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)


STAGES = (SKRStage, RefineStage, DenoiseStage, SKINStage, SMRMStage)


def _checked(value, default, where):
    """``value`` if it has the type of the field's ``default`` (an int for a float is fine; a
    list for a tuple, as JSON has no tuples) and, in a stage, a sensible range: counts at
    least 1, rates above 0, weights and noise at least 0, fractions at most 1."""
    kind = type(default)
    numbers = (int,) if kind is int else (int, float) if kind is float else None
    if kind is tuple and isinstance(value, list):
        value = tuple(value)
    if (isinstance(value, bool) and kind is not bool) or not isinstance(
            value, numbers or kind):
        raise ValueError(f"{where}: expected {kind.__name__}, got {value!r}")
    return value


def _in_range(key, value, default, where):
    if isinstance(default, tuple):
        bad = not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                      and math.isfinite(v) and v >= 0 for v in value)
    elif isinstance(default, int):
        bad = value < 1
    elif "autocorrelation" in key:
        bad = not -1 <= value <= 1
    else:
        bad = (not math.isfinite(value) or value < 0 or (value <= 0 and "rate" in key)
               or (value > 1 and "fraction" in key))
    if bad:
        raise ValueError(f"{where}: {value!r} is out of range (counts at least 1, learning "
                         "rates above 0, weights and noise at least 0, fractions at most 1, "
                         "autocorrelations in [-1, 1])")


def _build(cls, values, where):
    if not isinstance(values, dict):
        raise ValueError(f"{where}: expected an object, got {values!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown}; known: {sorted(fields)}")
    kwargs = {}
    for key, value in values.items():
        default = fields[key].default
        if dataclasses.is_dataclass(default):
            kwargs[key] = _build(type(default), value, f"{where}.{key}")
            continue
        kwargs[key] = _checked(value, default, f"{where}.{key}")
        if cls in STAGES:
            _in_range(key, kwargs[key], default, f"{where}.{key}")
        elif key == "seed" and value < 0:
            raise ValueError(f"{where}.seed: must be 0 or more, got {value}")
    return cls(**kwargs)


def load_recipe(path, overrides=()):
    """A recipe from a JSON file (a path, or the name of a file in training/recipes), with
    ``overrides``: "stage.key=value" strings (value in JSON, e.g. "smrm.clip_frames=10")."""
    path = Path(path)
    if not path.exists() and (RECIPES / f"{path}.json").exists():
        path = RECIPES / f"{path}.json"
    try:
        values = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: cannot read the recipe ({error})") from None
    for override in overrides:
        key, _, text = override.partition("=")
        *parents, leaf = key.split(".")
        where = values
        for part in parents:
            where = where.setdefault(part, {})
            if not isinstance(where, dict):
                raise ValueError(f"override {override!r}: {part!r} is not a section")
        try:
            where[leaf] = json.loads(text)
        except json.JSONDecodeError:
            raise ValueError(f"override {override!r}: expected key=value with a JSON value, "
                             "e.g. smrm.clip_frames=10") from None
    return _build(Recipe, values, str(path))
