"""Layer sizes of the networks, shared by the runtime and the torch reference.

The defaults are the paper's sizes (Rekik et al. 2024, supplementary tables); smaller
configurations (narrower layers, one GRU layer) are valid too and are what CPU training uses.
The config travels inside every weights file as JSON, so a file always says its own shape.
"""
import dataclasses
import json

from .conventions import NUM_JOINTS


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    # SKR: PointNet. Per-point 1x1 convolutions 3 -> w0 (then the w0 x w0 feature transform)
    # -> w1 -> w2, max-pool over points, MLP w2 -> h0 -> h1 -> J*3. The 3x3 and w0 x w0
    # transform networks (STN) use the same point widths and head widths.
    skr_point_widths: tuple = (64, 128, 1024)
    skr_head_widths: tuple = (512, 256)
    # SMRM: encoder and decoder GRUs, each `smrm_layers` deep and `smrm_hidden` wide.
    smrm_hidden: int = 512
    smrm_layers: int = 2
    # SKIN: per-point MLP (J*3 offsets) -> widths -> J, softmax.
    skin_widths: tuple = (256, 256)
    # Joint refinement (not in the paper; none when refine_point_widths is empty): per-point
    # layers 3 -> widths on each joint's refine_neighbours nearest points, max-pool, MLP
    # (pooled + J*3 + J) -> refine_head_widths -> 3.
    refine_point_widths: tuple = ()
    refine_head_widths: tuple = ()
    refine_neighbours: int = 96
    num_joints: int = NUM_JOINTS
    # Not in the paper: SMRM predicts a correction to the analytic retargeting
    # (minretarget.analytic, each target bone turned onto its source bone) instead of the whole
    # rotation; each joint's predicted quaternion is applied after the analytic one, in the
    # joint's own frame. False: the paper's SMRM (the root's rotation relative to the heading).
    # This and the fields after it come last, so that positional configs from before them keep
    # their meaning.
    smrm_analytic_prior: bool = False
    # Not in the paper: the source skeleton's denoiser (minretarget.denoise), a GRU
    # denoise_layers deep and denoise_hidden wide; none when denoise_hidden is 0.
    denoise_hidden: int = 0
    denoise_layers: int = 1
    # Not in the paper: the rest-pose model (minretarget.rest_pose) SMRM's analytic prior uses
    # to allow for the two bodies' rest poses.
    rest_pose: bool = False
    # Not in the paper: a second SKR of the same sizes, trained on what one depth camera sees
    # (``Weights.skr_view``; ``skr.read_from_view``), read when a frame comes with its viewpoint.
    skr_view: bool = False

    def __post_init__(self):
        # Accept lists (from JSON) and store tuples so the config stays hashable.
        for field in ("skr_point_widths", "skr_head_widths", "skin_widths",
                      "refine_point_widths", "refine_head_widths"):
            object.__setattr__(self, field, tuple(int(w) for w in getattr(self, field)))
        for flag in ("smrm_analytic_prior", "rest_pose", "skr_view"):
            if not isinstance(getattr(self, flag), bool):
                raise ValueError(f"{flag} must be true or false, got {getattr(self, flag)!r}")
        if self.rest_pose and not self.smrm_analytic_prior:
            raise ValueError("rest_pose needs smrm_analytic_prior: the rest-pose model moves "
                             "the analytic prior, which SMRM without it does not have")
        if len(self.skr_point_widths) != 3 or len(self.skr_head_widths) != 2:
            raise ValueError("skr_point_widths needs 3 widths and skr_head_widths 2, got "
                             f"{self.skr_point_widths} and {self.skr_head_widths}")
        if not self.skin_widths or self.smrm_layers < 1 or self.smrm_hidden < 1:
            raise ValueError(f"invalid config {self}")
        if self.num_joints != NUM_JOINTS:
            raise ValueError(f"num_joints must be {NUM_JOINTS}, got {self.num_joints}")
        if min(self.skr_point_widths + self.skr_head_widths + self.skin_widths
               + self.refine_point_widths + self.refine_head_widths) < 1:
            raise ValueError(f"every width must be positive, got {self}")
        if self.refine_neighbours < 1 or (self.refine_head_widths
                                          and not self.refine_point_widths):
            raise ValueError(f"invalid refiner config {self}")
        if self.denoise_hidden < 0 or self.denoise_layers < 1:
            raise ValueError(f"invalid denoiser config {self}")

    @property
    def refines(self):
        """Whether the weights hold a joint refiner (``minretarget.refine``)."""
        return bool(self.refine_point_widths)

    @property
    def denoises(self):
        """Whether the weights hold a skeleton denoiser (``minretarget.denoise``)."""
        return self.denoise_hidden > 0

    def without_refiner(self):
        """These sizes with no joint refiner (what weights from before it have)."""
        return dataclasses.replace(self, refine_point_widths=(), refine_head_widths=(),
                                   refine_neighbours=ModelConfig.refine_neighbours)

    def without_denoiser(self):
        """These sizes with no skeleton denoiser (what weights from before it have)."""
        return dataclasses.replace(self, denoise_hidden=0,
                                   denoise_layers=ModelConfig.denoise_layers)

    def with_view_skr(self):
        """These sizes with a one-view SKR."""
        return dataclasses.replace(self, skr_view=True)

    def to_json(self):
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text):
        values = json.loads(text)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown model config fields {sorted(unknown)}")
        return cls(**values)
