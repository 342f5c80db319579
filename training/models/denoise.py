"""Stage 1d, the skeleton denoiser (minretarget.denoise's torch twin): a GRU over the smoothed
source skeletons, in SMRM's heading frame, that predicts a correction of every joint."""
import torch
from torch import nn

from minretarget.config import ModelConfig
from .smrm import motion_features, turn_vectors


class SkeletonDenoiser(nn.Module):
    def __init__(self, config=ModelConfig()):
        super().__init__()
        j = config.num_joints
        self.config = config
        self.gru = nn.GRU(j * 3 + 3, config.denoise_hidden, config.denoise_layers,
                          batch_first=True)
        self.head = nn.Linear(config.denoise_hidden, j * 3)
        with torch.no_grad():        # start as the identity: no correction
            self.head.weight.zero_()
            self.head.bias.zero_()

    def forward(self, joints, previous_root=None, hidden=None):
        """Denoise a clip (or one frame, T = 1) continuing from ``hidden``.

        Args:
            joints: (B, T, J, 3) smoothed source joints, metres.
            previous_root: (B, 3) the root before the clip's first frame (None: the first
                frame's own, as at a stream's start).
            hidden: (layers, B, H) the GRU's state, or None (zeros) at a stream's start.
        Returns:
            the denoised joints (B, T, J, 3) and the GRU's state after the last frame.
        """
        if previous_root is None:
            previous_root = joints[:, 0, 0, :]
        features, sin_cos = motion_features(joints, previous_root)
        out, hidden = self.gru(features, hidden)
        offsets = self.head(out).view(joints.shape)
        return joints + turn_vectors(offsets, sin_cos), hidden
