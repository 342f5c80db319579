"""SKIN, the skinning-weight field: per target point, weights over the J joints.

Input per point: its offsets to the J T-pose joints (J*3, metres). MLP through the widths of
ModelConfig.skin_widths [256, 256] with ReLU, then J logits and a softmax, so the weights
are non-negative and sum to one. Computed once per target; LBS then poses the points.
"""
import torch
from torch import nn

from minretarget.config import ModelConfig


def joint_offsets(points, tpose_joints):
    """points (B, V, 3), tpose_joints (B, J, 3) -> (B, V, J*3) offsets point - joint, metres."""
    return (points[:, :, None, :] - tpose_joints[:, None, :, :]).flatten(2)


class SkinningField(nn.Module):
    def __init__(self, config=ModelConfig()):
        super().__init__()
        layers, width = [], config.num_joints * 3
        for hidden in config.skin_widths:
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        self.hidden = nn.Sequential(*layers)
        self.output = nn.Linear(width, config.num_joints)

    def forward(self, points, tpose_joints):
        """points (B, V, 3), tpose_joints (B, J, 3) metres -> skinning weights (B, V, J)."""
        logits = self.output(self.hidden(joint_offsets(points, tpose_joints)))
        return torch.softmax(logits, dim=-1)
