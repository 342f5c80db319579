"""Stage 1d, the skeleton denoiser (minretarget.denoise's torch twin): a GRU over the smoothed
source skeletons, in SMRM's heading frame, that predicts a correction of every joint. It trains
on one view (``forward``); the runtime runs it on the skeleton and on its mirror image and
averages (``mirror_averaged``)."""
import torch
from torch import nn

from minretarget.config import ModelConfig
from minretarget.conventions import LEFT_AXIS, MIRROR
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

    def mirror_averaged(self, joints, previous_root=None, hidden=None):
        """``forward`` on the clip and on its mirror image (x -> -x, left and right joints
        swapped), each with its own GRU state, the second mirrored back and averaged: what
        the runtime runs (``minretarget.denoise``).

        Args: as ``forward``, but ``hidden`` (2, layers, B, H), the two views' states.
        Returns: the denoised joints (B, T, J, 3) and the states after the last frame
            (2, layers, B, H).
        """
        plain, hidden_plain = self(joints, previous_root, None if hidden is None else hidden[0])
        other, hidden_other = self(mirror_image(joints),
                                   None if previous_root is None else mirror_image(previous_root,
                                                                                   joints=False),
                                   None if hidden is None else hidden[1])
        return (plain + mirror_image(other)) / 2, torch.stack([hidden_plain, hidden_other])


def mirror_image(x, joints=True):
    """(..., J, 3) joints (or, with ``joints=False``, (..., 3) points) of the mirror image:
    x -> -x, and left and right joints swapped."""
    flip = torch.ones(3, dtype=x.dtype, device=x.device)
    flip[LEFT_AXIS] = -1.0
    return (x[..., list(MIRROR), :] if joints else x) * flip
