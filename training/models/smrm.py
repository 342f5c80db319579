"""SMRM, skeletal motion retargeting (after Villegas et al. 2018), and its motion discriminator.

Per frame t, with source joints x_t (J, 3) and the target's T-pose skeleton s (J, 3):
    1. features: joints relative to the root (J*3) and root velocity x_t[0] - x_{t-1}[0] (3)
    2. encoder GRU (layers x H) over the features
    3. decoder GRU (layers x H) over [encoder output, s - s[0]] (the T-pose relative to its root)
    4. heads: (J, 4) unit quaternions, and a root offset d_t (3)
    5. root: r_t = k_t * x_t[0] + d_t with k_t = leg length of s / running mean of the source's
       leg length (the Mixamo-style scaling of the source root, corrected by the network)
    6. FK of the quaternions on s with root r_t gives the retargeted joints (J, 3)
The recurrent state (both GRUs' hidden states, the previous source root, the running leg
length) is explicit, so a stream can be fed one frame at a time and gives the same result as
the whole sequence at once.
"""
from typing import NamedTuple

import torch
from torch import nn

from minretarget.config import ModelConfig
from training.kinematics import forward_kinematics, normalize_quaternions


class MotionState(NamedTuple):
    encoder_hidden: torch.Tensor   # (layers, B, H)
    decoder_hidden: torch.Tensor   # (layers, B, H)
    previous_root: torch.Tensor    # (B, 3) source root of the last frame seen, metres
    leg_length_sum: torch.Tensor   # (B,) sum of the source leg lengths seen, metres
    frames_seen: torch.Tensor      # (B,) frames seen so far


def leg_length(joints):
    """(..., J, 3) -> (...,) mean hip-knee-ankle chain length (minretarget.kinematics twin)."""
    total = 0.0
    for hip, knee, ankle in ((1, 4, 7), (2, 5, 8)):
        total = total + (joints[..., knee, :] - joints[..., hip, :]).norm(dim=-1)
        total = total + (joints[..., ankle, :] - joints[..., knee, :]).norm(dim=-1)
    return total / 2


def motion_features(joints, previous_root):
    """joints (B, T, J, 3), previous_root (B, 3) -> (B, T, J*3 + 3) encoder input."""
    root = joints[:, :, 0, :]                                          # (B, T, 3)
    local = (joints - root[:, :, None, :]).flatten(2)                  # (B, T, J*3)
    velocity = root - torch.cat([previous_root[:, None, :], root[:, :-1, :]], dim=1)
    return torch.cat([local, velocity], dim=-1)


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
        # Start near the identity pose and no root correction.
        with torch.no_grad():
            self.rotation_head.weight.mul_(0.1)
            self.rotation_head.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(j))
            self.root_head.weight.mul_(0.1)
            self.root_head.bias.zero_()

    def initial_state(self, first_joints):
        """first_joints (B, J, 3): the stream's first source frame -> the state before it."""
        b, c = first_joints.shape[0], self.config
        zeros = first_joints.new_zeros((c.smrm_layers, b, c.smrm_hidden))
        return MotionState(zeros, zeros.clone(), first_joints[:, 0, :].clone(),
                           first_joints.new_zeros(b), first_joints.new_zeros(b))

    def forward(self, source_joints, target_tpose, state=None):
        """Retarget a clip (or one frame, T = 1) continuing from ``state``.

        Args:
            source_joints: (B, T, J, 3) source joint positions, metres.
            target_tpose: (B, J, 3) target T-pose joints, metres.
            state: MotionState from the previous call, or None to start a stream.
        Returns:
            rotations (B, T, J, 4) unit quaternions, root (B, T, 3), joints (B, T, J, 3)
            (FK on the target skeleton), and the MotionState after the last frame.
        """
        b, t, j, _ = source_joints.shape
        if state is None:
            state = self.initial_state(source_joints[:, 0])
        features = motion_features(source_joints, state.previous_root)
        encoded, encoder_hidden = self.encoder(features, state.encoder_hidden)
        skeleton = (target_tpose - target_tpose[:, :1, :]).flatten(1)    # (B, J*3)
        decoder_input = torch.cat([encoded, skeleton[:, None, :].expand(b, t, -1)], dim=-1)
        decoded, decoder_hidden = self.decoder(decoder_input, state.decoder_hidden)
        rotations = normalize_quaternions(self.rotation_head(decoded).view(b, t, j, 4))

        # Running mean of the source's leg length, then the scaled source root plus the offset.
        leg_sum = state.leg_length_sum[:, None] + leg_length(source_joints).cumsum(dim=1)
        frames = state.frames_seen[:, None] + torch.arange(1, t + 1, device=leg_sum.device)
        scale = leg_length(target_tpose)[:, None] / (leg_sum / frames)  # (B, T)
        root = scale[..., None] * source_joints[:, :, 0, :] + self.root_head(decoded)
        joints, _ = forward_kinematics(rotations, root, target_tpose[:, None])
        new_state = MotionState(encoder_hidden, decoder_hidden, source_joints[:, -1, 0, :],
                                leg_sum[:, -1], frames[:, -1].to(leg_sum.dtype))
        return rotations, root, joints, new_state


class MotionDiscriminator(nn.Module):
    """Scores how real a skeleton motion looks, from windows of its frames (training only).

    Input: the motion's encoder features (B, T, J*3 + 3) (root-relative joints and root
    velocity, see ``motion_features``) divided by the skeleton's leg length, so bodies of
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
