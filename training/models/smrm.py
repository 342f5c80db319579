"""SMRM, skeletal motion retargeting (after Villegas et al. 2018), and its motion discriminator.

Per frame t, with source joints x_t (J, 3) and the target's T-pose skeleton s (J, 3):
    1. heading: H_t, the turn about +Y from +Z to the way the source faces at t (from its hips
       and shoulders); the network works in this body-aligned frame, so it never has to learn
       that a motion turned about the vertical is the same motion
    2. features: H_t^T (x_t - x_t[0]) (J*3) and the root velocity H_t^T (x_t[0] - x_{t-1}[0]) (3)
    3. encoder GRU (layers x H) over the features
    4. decoder GRU (layers x H) over [encoder output, s - s[0]] (the T-pose relative to its root)
    5. heads: (J, 4) unit quaternions, the root's relative to H_t, and a root offset d_t (3);
       with ``smrm_analytic_prior`` each is instead a correction applied after the analytic
       rotation of x_t onto s (training.analytic), in the joint's own frame; with the config's
       ``rest_pose``, onto s as the rest-pose model turns it (minretarget.rest_pose), from the
       mean source bone lengths so far
    6. root rotation H_t q_0; root r_t = k_t * x_t[0] + H_t d_t, with k_t = leg length of s /
       the mean source leg length over the frames seen so far (the Mixamo-style scaling of the
       source root, corrected by the network; see minretarget.smrm for why the mean)
    7. FK of the quaternions on s with root r_t gives the retargeted joints (J, 3)
The recurrent state (both GRUs' hidden states, the previous source root, the mean source bone
lengths and the frame count) is explicit, so a stream can be fed one frame at a time and gives the same result as
the whole sequence at once.
"""
from typing import NamedTuple

import torch
from torch import nn

from minretarget.config import ModelConfig
from minretarget.rest_pose import NUM_BONES, NUM_FEATURES
from minretarget.smrm import LEG_BONES
from training.analytic import analytic_rotations
from training.kinematics import forward_kinematics, normalize_quaternions, quaternion_multiply
from training.models.rest_pose import torch_bone_lengths, torch_prior_reference


class MotionState(NamedTuple):
    encoder_hidden: torch.Tensor   # (layers, B, H)
    decoder_hidden: torch.Tensor   # (layers, B, H)
    previous_root: torch.Tensor    # (B, 3) source root of the last frame seen, metres
    source_bone_lengths: torch.Tensor  # (B, bones) mean source bone lengths over the frames
    frames_seen: torch.Tensor      # (B,) frames seen so far


def leg_length(joints):
    """(..., J, 3) -> (...,) mean hip-knee-ankle chain length (minretarget.kinematics twin)."""
    total = 0.0
    for hip, knee, ankle in ((1, 4, 7), (2, 5, 8)):
        total = total + (joints[..., knee, :] - joints[..., hip, :]).norm(dim=-1)
        total = total + (joints[..., ankle, :] - joints[..., knee, :]).norm(dim=-1)
    return total / 2


def heading(joints, eps=1e-8):
    """(..., J, 3) -> (..., 2) (sin, cos) of the turn about +Y taking +Z to the facing direction.

    Facing = across x up, with across = (left hip - right hip) + (left shoulder - right
    shoulder): in the T-pose, across is +X and the body faces +Z.
    """
    across = joints[..., 1, :] - joints[..., 2, :] + joints[..., 16, :] - joints[..., 17, :]
    facing = torch.stack([-across[..., 2], across[..., 0]], dim=-1)   # (sin, cos) unnormalised
    return facing / facing.norm(dim=-1, keepdim=True).clamp_min(eps)


def turn_vectors(vectors, sin_cos, inverse=False):
    """Rotate (..., K, 3) vectors about +Y by the heading (..., 2) (or its inverse)."""
    sin, cos = sin_cos[..., None, 0], sin_cos[..., None, 1]
    sin = -sin if inverse else sin
    x, y, z = vectors.unbind(-1)
    return torch.stack([cos * x + sin * z, y, cos * z - sin * x], dim=-1)


def turn_quaternions(quaternions, sin_cos):
    """(..., 4) q -> h q: the rotation q followed by the heading turn h (..., 2) about +Y."""
    half = torch.atan2(sin_cos[..., 0], sin_cos[..., 1]) / 2            # stable at a half turn
    hw, hy = torch.cos(half), torch.sin(half)
    w, x, y, z = quaternions.unbind(-1)
    return torch.stack([hw * w - hy * y, hw * x + hy * z, hw * y + hy * w, hw * z - hy * x], -1)


def motion_features(joints, previous_root):
    """joints (B, T, J, 3), previous_root (B, 3) -> (B, T, J*3 + 3) encoder input, each frame
    turned into its own heading frame, and the headings (B, T, 2)."""
    sin_cos = heading(joints)                                          # (B, T, 2)
    root = joints[:, :, 0, :]                                          # (B, T, 3)
    local = turn_vectors(joints - root[:, :, None, :], sin_cos, inverse=True)
    velocity = root - torch.cat([previous_root[:, None, :], root[:, :-1, :]], dim=1)
    velocity = turn_vectors(velocity[:, :, None, :], sin_cos, inverse=True)
    return torch.cat([local.flatten(2), velocity[:, :, 0, :]], dim=-1), sin_cos


class MotionRetargeter(nn.Module):
    def __init__(self, config=ModelConfig(), dropout=0.2):
        super().__init__()
        j, h, layers = config.num_joints, config.smrm_hidden, config.smrm_layers
        self.config = config
        dropout = dropout if layers > 1 else 0.0
        self.encoder = nn.GRU(j * 3 + 3, h, layers, batch_first=True, dropout=dropout)
        self.decoder = nn.GRU(h + j * 3, h, layers, batch_first=True, dropout=dropout)
        self.rotation_head = nn.Linear(h, j * 4)
        self.root_head = nn.Linear(h, 3)
        # Start near the identity pose (with the analytic prior: exactly the analytic
        # retargeting) and no root correction.
        with torch.no_grad():
            self.rotation_head.weight.mul_(0.1)
            self.root_head.weight.mul_(0.1)
            self.root_head.bias.zero_()
        self.reset_rotation_head()
        if config.rest_pose:         # fitted, not trained (training.rest_pose)
            self.register_buffer("rest_directions", torch.zeros(NUM_FEATURES, 3 * NUM_BONES))

    def reset_rotation_head(self):
        """Identity rotations out (zero weights with the analytic prior): what a network
        trained without the prior needs before it learns corrections to it."""
        with torch.no_grad():
            if self.config.smrm_analytic_prior:
                self.rotation_head.weight.zero_()
            self.rotation_head.bias.copy_(
                torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(self.config.num_joints))

    def initial_state(self, first_joints):
        """first_joints (B, J, 3): the stream's first source frame -> the state before it."""
        b, c = first_joints.shape[0], self.config
        zeros = first_joints.new_zeros((c.smrm_layers, b, c.smrm_hidden))
        return MotionState(zeros, zeros.clone(), first_joints[:, 0, :].clone(),
                           first_joints.new_zeros((b, NUM_BONES)), first_joints.new_zeros(b))

    def forward(self, source_joints, target_tpose, state=None, target_leg_length=None):
        """Retarget a clip (or one frame, T = 1) continuing from ``state``.

        Args:
            source_joints: (B, T, J, 3) source joint positions, metres.
            target_tpose: (B, J, 3) target T-pose joints, metres.
            state: MotionState from the previous call, or None to start a stream.
            target_leg_length: (B,) the targets' leg lengths that scale the root, metres
                (the runtime's ``Target.leg_length``), or None: ``target_tpose``'s.
        Returns:
            rotations (B, T, J, 4) unit quaternions, root (B, T, 3), joints (B, T, J, 3)
            (FK on the target skeleton), and the MotionState after the last frame.
        """
        b, t, j, _ = source_joints.shape
        if state is None:
            state = self.initial_state(source_joints[:, 0])
        features, sin_cos = motion_features(source_joints, state.previous_root)
        encoded, encoder_hidden = self.encoder(features, state.encoder_hidden)
        skeleton = (target_tpose - target_tpose[:, :1, :]).flatten(1)    # (B, J*3)
        decoder_input = torch.cat([encoded, skeleton[:, None, :].expand(b, t, -1)], dim=-1)
        decoded, decoder_hidden = self.decoder(decoder_input, state.decoder_hidden)
        rotations = normalize_quaternions(self.rotation_head(decoded).view(b, t, j, 4))
        # The mean source bone lengths so far (B, T, bones).
        frames = state.frames_seen[:, None] + torch.arange(1, t + 1, device=source_joints.device)
        lengths = ((state.frames_seen[:, None] * state.source_bone_lengths)[:, None]
                   + torch_bone_lengths(source_joints).cumsum(dim=1)) / frames[..., None]
        if self.config.smrm_analytic_prior:
            reference = target_tpose[:, None]
            if self.config.rest_pose:
                reference = torch_prior_reference(self.rest_directions, reference, lengths)
            prior = analytic_rotations(source_joints, reference)
            rotations = quaternion_multiply(prior, rotations)
        else:
            rotations = torch.cat([turn_quaternions(rotations[:, :, :1], sin_cos[:, :, None]),
                                   rotations[:, :, 1:]], dim=2)

        # The source root scaled by the mean leg lengths (the same chains as leg_length's),
        # plus the offset.
        legs = lengths[..., list(LEG_BONES)].sum(-1) / 2                 # (B, T)
        if target_leg_length is None:
            target_leg_length = leg_length(target_tpose)
        scale = target_leg_length[:, None] / legs.clamp_min(1e-6)          # (B, T)
        offset = turn_vectors(self.root_head(decoded)[:, :, None, :], sin_cos)[:, :, 0, :]
        root = scale[..., None] * source_joints[:, :, 0, :] + offset
        joints, _ = forward_kinematics(rotations, root, target_tpose[:, None])
        new_state = MotionState(encoder_hidden, decoder_hidden, source_joints[:, -1, 0, :],
                                lengths[:, -1], frames[:, -1].to(legs.dtype))
        return rotations, root, joints, new_state


class MotionDiscriminator(nn.Module):
    """Scores how real a skeleton motion looks, from windows of its frames (training only).

    Input: the motion's encoder features (B, T, J*3 + 3) (root-relative joints and root
    velocity in the heading frame, see ``motion_features``) divided by the skeleton's leg length, so bodies of
    every size are judged on the same footing. Output: (B, T') logits, one per window.
    """

    def __init__(self, config=ModelConfig(), width=256):
        super().__init__()
        c = config.num_joints * 3 + 3
        self.layers = nn.Sequential(
            nn.Conv1d(c, width, 4, stride=2, padding=1), nn.LeakyReLU(0.2),
            nn.Conv1d(width, width, 4, stride=2, padding=1), nn.LeakyReLU(0.2),
            nn.Conv1d(width, 1, 3, padding=1))

    def forward(self, features, scale):
        """features (B, T, J*3 + 3), scale (B,) metres -> (B, T') logits."""
        x = (features / scale[:, None, None]).transpose(1, 2)           # (B, C, T)
        return self.layers(x)[:, 0, :]
