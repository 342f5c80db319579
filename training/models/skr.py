"""SKR, the skeleton regressor: PointNet from a point cloud (B, P, 3) to 22 joints (B, J, 3).

Layout (widths from ModelConfig; paper sizes in brackets):
    centre the points on their centroid (translation invariance; added back at the end)
    3x3 input transform (an STN PointNet) applied to the points
    1x1 conv 3 -> w0 [64], then the w0 x w0 feature transform (a second STN)
    1x1 convs w0 -> w1 [128] -> w2 [1024], max-pool over points
    MLP w2 -> h0 [512] -> h1 [256] (dropout 0.3) -> J*3
Every hidden layer is linear + batch norm + ReLU; export folds the batch norm into the linear.
"""
import torch
from torch import nn

from minretarget.config import ModelConfig


class PointLayers(nn.Module):
    """Shared per-point linear layers with batch norm and ReLU: (B, C, P) -> (B, w[-1], P)."""

    def __init__(self, in_width, widths):
        super().__init__()
        self.layers = nn.ModuleList()
        for width in widths:
            self.layers.append(nn.Sequential(nn.Conv1d(in_width, width, 1),
                                             nn.BatchNorm1d(width), nn.ReLU()))
            in_width = width

    def forward(self, x):
        for layer in self.layers:
            x = layer(x)
        return x


class Head(nn.Module):
    """MLP on a global feature: hidden linear + batch norm + ReLU layers, then a linear output."""

    def __init__(self, in_width, widths, out_width, dropout=0.0):
        super().__init__()
        hidden = []
        for width in widths:
            hidden += [nn.Linear(in_width, width), nn.BatchNorm1d(width), nn.ReLU()]
            in_width = width
        if dropout:
            hidden.append(nn.Dropout(dropout))
        self.hidden = nn.Sequential(*hidden)
        self.output = nn.Linear(in_width, out_width)

    def forward(self, x):
        return self.output(self.hidden(x))


class TransformNet(nn.Module):
    """STN: a small PointNet predicting a k x k transform of its input, (B, k, P) -> (B, k, k)."""

    def __init__(self, k, config):
        super().__init__()
        self.k = k
        self.points = PointLayers(k, config.skr_point_widths)
        self.head = Head(config.skr_point_widths[-1], config.skr_head_widths, k * k)
        # Start at the identity transform: the output adds to the identity matrix.
        nn.init.zeros_(self.head.output.weight)
        nn.init.zeros_(self.head.output.bias)

    def forward(self, x):
        feature = self.points(x).amax(dim=2)                           # (B, w2, P) -> (B, w2)
        transform = self.head(feature).view(-1, self.k, self.k)
        return transform + torch.eye(self.k, dtype=x.dtype, device=x.device)


class SkeletonRegressor(nn.Module):
    def __init__(self, config=ModelConfig()):
        super().__init__()
        w0 = config.skr_point_widths[0]
        self.num_joints = config.num_joints
        self.input_transform = TransformNet(3, config)
        self.feature_transform = TransformNet(w0, config)
        self.first = PointLayers(3, config.skr_point_widths[:1])
        self.rest = PointLayers(w0, config.skr_point_widths[1:])
        self.head = Head(config.skr_point_widths[-1], config.skr_head_widths,
                         config.num_joints * 3, dropout=0.3)

    def forward(self, points):
        """points (B, P, 3) metres, any P -> joints (B, J, 3) metres."""
        centroid = points.mean(dim=1, keepdim=True)                    # (B, 1, 3)
        x = (points - centroid).transpose(1, 2)                        # (B, 3, P)
        x = torch.bmm(self.input_transform(x).transpose(1, 2), x)     # x^T A, kept as (B, 3, P)
        x = self.first(x)                                              # (B, w0, P)
        x = torch.bmm(self.feature_transform(x).transpose(1, 2), x)
        feature = self.rest(x).amax(dim=2)                             # (B, w2)
        offsets = self.head(feature).view(-1, self.num_joints, 3)
        return offsets + centroid
