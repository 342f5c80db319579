"""The per-frame pipeline, declared once: which stages run, in what order, with what settings.

A source frame goes down these stages, in this order (``stages.build_stages`` makes the list,
``Retargeter`` folds each frame down it):

    stage            module              setting            what it does
    0  thinning      sampling            cloud_points       a seeded subset of each cloud
    1  SKR           skr                 (always)           the cloud's skeleton, regressed
    1a one view      skr                 skr_view           ... by the one-view SKR, told the camera
                                                            (then neither mirrored nor refined)
    1b mirror        skr                 mirror_source      ... averaged with its mirror image's
    1c refiner       refine              refine             each joint moved by the points near it
    1d facing check  facing              facing_check       a reading facing away read again turned
    1e source fit    fit                 fit_source         a calibrated body model tracked in the
                                                            cloud: its joints replace the reading
    2a smoothing     smoothing           smoothing          alpha-beta filter over time
    2b denoiser      denoise             denoise            a GRU trained on SKR's skeletons
    3  SMRM          smrm (+ rest_pose)  rest_pose          rotations and root for the target
    4  FK            kinematics          (always)           the target's joints, once a frame
    5  foot lock     contacts            foot_lock          planted toes held, legs bent to them
    6  LBS           skin                (always)           the target's points, posed
and once per target: SKR on its T-pose (``mirror_target``: and on its mirror image) and SKIN.

``PipelineConfig`` holds every setting; ``PRESETS`` names the ones that are measured and
supported: ``paper`` (SKR -> SMRM -> FK -> LBS, the paper's pipeline and the torch
reference's), ``regressed`` (SKR's reading, refined, checked for facing, smoothed and
denoised) and ``fitted`` (SKR's refined reading, then the source fit, neither smoothed nor
denoised). ``DEFAULT_PRESET`` is the one ``Retargeter`` runs unless told otherwise:
docs/source_fit.md says how it was chosen.

Some settings are coupled to how the weights were trained: the denoiser learned SKR's
refined readings after ``Smoothing()``, so it refuses skeletons from another smoothing or
from the source fit (``check_pipeline``). Weights exported since carry their couplings in
their metadata (``pipeline``); older files get the ones they were trained with.
"""
import dataclasses
import json

import numpy as np

from .contacts import FootLock, check_foot_lock
from .conventions import MIN_POINTS
from .fit import FitSettings, check_fit_settings
from .smoothing import Smoothing, check_smoothing

# The stage settings that are NamedTuples of numbers (None: the stage is off).
_TUPLE_SETTINGS = {"smoothing": (Smoothing, check_smoothing),
                   "foot_lock": (FootLock, check_foot_lock),
                   "fit_source": (FitSettings, check_fit_settings)}
_FLAGS = ("mirror_target", "mirror_source", "refine", "skr_view", "facing_check", "denoise",
          "rest_pose", "allow_untrained")


@dataclasses.dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    """Every stage's setting (the module's table); frozen: ``replace`` makes a changed copy.
    The defaults are the ``regressed`` preset's."""
    # Each source cloud thinned to this many points (a subset seeded by the frame's index in the
    # stream) before every stage, or None for all its points.
    cloud_points: int | None = None
    mirror_target: bool = True
    mirror_source: bool = False
    refine: bool = True
    # A frame given its viewpoint is read by the weights' one-view SKR, if they have one.
    skr_view: bool = True
    facing_check: bool = True
    fit_source: FitSettings | None = None
    smoothing: Smoothing | None = Smoothing()
    denoise: bool = True
    rest_pose: bool = True
    foot_lock: FootLock | None = FootLock()
    # Run a stage on inputs unlike those it was trained on (``check_pipeline`` would refuse):
    # for parity checks and ablations, whose figures are then not the weights' own.
    allow_untrained: bool = False

    def __post_init__(self):
        for name in _FLAGS:
            value = getattr(self, name)
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError(f"PipelineConfig.{name} must be True or False, got {value!r}")
            object.__setattr__(self, name, bool(value))
        for name, (_, check) in _TUPLE_SETTINGS.items():
            object.__setattr__(self, name, check(getattr(self, name)))
        points = self.cloud_points
        if points is not None and (not isinstance(points, (int, np.integer))
                                   or isinstance(points, bool) or points < MIN_POINTS):
            raise ValueError(f"PipelineConfig.cloud_points must be None or an integer >= "
                             f"{MIN_POINTS}, got {points!r}")
        if points is not None:
            object.__setattr__(self, "cloud_points", int(points))

    def replace(self, **changes):
        """This config with ``changes`` (stage settings by name)."""
        unknown = set(changes) - {field.name for field in dataclasses.fields(self)}
        if unknown:
            raise TypeError(f"PipelineConfig has no setting {', '.join(sorted(unknown))}; "
                            f"its settings: {', '.join(f.name for f in dataclasses.fields(self))}")
        return dataclasses.replace(self, **changes)

    def to_dict(self):
        """Plain JSON values: flags, and the tuple settings as objects of their fields (or
        None)."""
        return {field.name: (value._asdict() if isinstance(value, tuple) else value)
                for field in dataclasses.fields(self)
                for value in (getattr(self, field.name),)}

    @classmethod
    def from_dict(cls, values):
        """The inverse of ``to_dict``; a missing setting takes its default; ValueError names
        an unknown one or a bad value."""
        if not isinstance(values, dict):
            raise ValueError(f"a pipeline config must be a JSON object, got {values!r}")
        known = {field.name for field in dataclasses.fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown pipeline settings {sorted(unknown)}; known: "
                             f"{sorted(known)}")
        parsed = {}
        for name, value in values.items():
            if name in _TUPLE_SETTINGS and value is not None:
                kind = _TUPLE_SETTINGS[name][0]
                if not isinstance(value, dict) or set(value) - set(kind._fields):
                    raise ValueError(f"pipeline setting {name} must be null or an object of "
                                     f"{', '.join(kind._fields)}, got {value!r}")
                value = kind(**value)
            parsed[name] = value
        try:
            return cls(**parsed)
        except TypeError as error:
            raise ValueError(str(error)) from None

    def to_json(self):
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text):
        return cls.from_dict(json.loads(text))

    def preset_name(self):
        """The name of the preset this config is, or None."""
        return next((name for name, preset in PRESETS.items() if preset == self), None)


PRESETS = {
    "paper": PipelineConfig(mirror_target=False, refine=False, facing_check=False,
                            smoothing=None, denoise=False, rest_pose=False, foot_lock=None),
    "regressed": PipelineConfig(),
    # The facing check went: with the fit it changed nothing beyond noise (docs/source_fit.md).
    "fitted": PipelineConfig(fit_source=FitSettings(), facing_check=False, smoothing=None,
                             denoise=False),
}
DEFAULT_PRESET = "fitted"

# What the weights' stages were trained on, for files from before weights said so (metadata
# "pipeline"): the denoiser learned SKR's refined readings after the default smoothing.
LEGACY_COUPLINGS = {"denoiser_input": {"smoothing": Smoothing()._asdict(), "refine": True,
                                       "fit_source": False}}
# Weights that learned nothing a pipeline setting could break (random ones, in tests).
UNCOUPLED = {"denoiser_input": None}


def preset(name):
    """The preset ``name`` (``PRESETS``; "default": ``DEFAULT_PRESET``)."""
    key = DEFAULT_PRESET if name == "default" else name
    if key not in PRESETS:
        raise ValueError(f"no pipeline preset {name!r}; presets: default, "
                         f"{', '.join(PRESETS)}")
    return PRESETS[key]


def as_config(config):
    """A PipelineConfig from a config or a preset's name (None: the default)."""
    if config is None:
        return preset("default")
    if isinstance(config, str):
        return preset(config)
    if not isinstance(config, PipelineConfig):
        raise TypeError(f"config must be a PipelineConfig or a preset's name "
                        f"({', '.join(['default', *PRESETS])}), got {type(config).__name__}")
    return config


def couplings(weights):
    """What ``weights``' stages were trained on: their metadata's ``pipeline`` entry, or
    ``LEGACY_COUPLINGS`` for files from before it."""
    return weights.metadata.get("pipeline", LEGACY_COUPLINGS)


def check_pipeline(weights, config):
    """``config`` if ``weights`` were trained for it (or it says ``allow_untrained``), else
    ValueError saying which coupling breaks: a denoiser (when the weights have one and
    ``denoise`` is on) fed skeletons unlike those it learned (another smoothing, no refiner,
    or the source fit's)."""
    learned = couplings(weights)["denoiser_input"]
    if (config.denoise and weights.denoise is not None and learned is not None
            and not config.allow_untrained):
        smoothing = None if learned["smoothing"] is None else Smoothing(**learned["smoothing"])
        fed = {"smoothing": config.smoothing, "refine": config.refine and
               weights.refine is not None, "fit_source": config.fit_source is not None}
        wanted = {"smoothing": smoothing, "refine": learned["refine"],
                  "fit_source": learned["fit_source"]}
        broken = [name for name in fed if fed[name] != wanted[name]]
        if broken:
            raise ValueError(
                "these weights' denoiser was trained on skeletons with "
                + ", ".join(f"{name}={wanted[name]}" for name in broken) + "; this pipeline "
                "feeds it " + ", ".join(f"{name}={fed[name]}" for name in broken)
                + ": set denoise=False, use a preset (" + ", ".join(PRESETS) + "), or "
                "allow_untrained=True to run it all the same")
    return config
