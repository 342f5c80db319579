"""The whole retargeting pipeline in torch: the reference the runtime's Retargeter must match.

Mirrors minretarget.Retargeter step for step (inference only, eval mode, no gradients), as
``Retargeter(weights, RUNTIME_CONFIG)`` runs it: SKR (and the refiner), the denoiser (if the
config has them), SMRM, FK, LBS. The parity tests (tests/test_parity.py, benchmarks/parity.py)
and the engine comparison of benchmarks/speed.py pair the two through ``RUNTIME_CONFIG``.
"""
import torch
from torch import nn

from minretarget.config import ModelConfig
from minretarget.pipeline import PipelineConfig
from training.kinematics import linear_blend_skinning, skinning_transforms, forward_kinematics
from .denoise import SkeletonDenoiser
from .refine import JointRefiner
from .skin import SkinningField
from .skr import SkeletonRegressor
from .smrm import MotionRetargeter

# The runtime's pipeline that computes what ReferenceRetargeter does: SMRM's output as it comes
# (no smoothing, foot lock, mirrored target or facing check). ``allow_untrained``: trained
# weights' denoiser learned smoothed skeletons (``minretarget.pipeline.check_pipeline``), and
# the reference feeds it unsmoothed ones.
RUNTIME_CONFIG = PipelineConfig(smoothing=None, foot_lock=None, mirror_target=False,
                                facing_check=False, allow_untrained=True)


class ReferenceRetargeter(nn.Module):
    def __init__(self, config=ModelConfig()):
        super().__init__()
        self.config = config
        self.skr = SkeletonRegressor(config)
        self.smrm = MotionRetargeter(config)
        self.skin = SkinningField(config)
        self.refine = JointRefiner(config) if config.refines else None
        self.denoise = SkeletonDenoiser(config) if config.denoises else None
        self.target_points = self.tpose_joints = self.skin_weights = self.state = None
        # The target's leg length that scales the root (the runtime's ``Target.leg_length``,
        # which reads a mesh's from its surface), or None: its skeleton's.
        self.leg_length = None

    @torch.no_grad()
    def set_target(self, points):
        """points (V, 3) target in T-pose, metres: computes its skeleton and skinning weights."""
        self.target_points = torch.as_tensor(points, dtype=torch.float32)
        self.tpose_joints = self.skeleton(self.target_points[None])[0]        # (J, 3)
        self.skin_weights = self.skin(self.target_points[None], self.tpose_joints[None])[0]
        self.leg_length = self.state = None

    @torch.no_grad()
    def step(self, points):
        """points (P, 3) one source frame -> dict of vertices (V, 3), joints (J, 3),
        rotations (J, 4), root (3,), source_joints (J, 3)."""
        out, self.state = self.forward(torch.as_tensor(points, dtype=torch.float32), self.state)
        return out

    def skeleton(self, points):
        """points (B, P, 3) -> SKR's joints (B, J, 3), refined if the config has a refiner."""
        joints = self.skr(points)
        return joints if self.refine is None else self.refine(points, joints)

    def forward(self, points, state):
        """One frame as a pure function (what ``step`` runs, and what ONNX export traces):
        points (P, 3), the state before it (None at a stream's start) -> (dict as ``step``
        returns, the state after it: SMRM's MotionState, and the denoiser's GRU state and
        last input root, or None without a denoiser)."""
        source_joints = self.skeleton(points[None])                      # (1, J, 3)
        smrm_state, denoise_state = (None, None) if state is None else state
        if self.denoise is not None:
            hidden, previous_root = (None, None) if denoise_state is None else denoise_state
            raw_root = source_joints[:, 0]
            denoised, hidden = self.denoise.mirror_averaged(source_joints[:, None],
                                                            previous_root, hidden)
            source_joints, denoise_state = denoised[:, 0], (hidden, raw_root)
        rotations, root, joints, smrm_state = self.smrm(
            source_joints[:, None], self.tpose_joints[None], smrm_state,
            None if self.leg_length is None else self.leg_length[None])
        state = (smrm_state, denoise_state)
        rotations, root, joints = rotations[0, 0], root[0, 0], joints[0, 0]
        _, global_rotations = forward_kinematics(rotations, root, self.tpose_joints)
        transforms = skinning_transforms(joints, global_rotations, self.tpose_joints)
        vertices = linear_blend_skinning(self.target_points, self.skin_weights, transforms)
        return dict(vertices=vertices, joints=joints, rotations=rotations, root=root,
                    source_joints=source_joints[0]), state
