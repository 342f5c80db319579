"""Joint refinement (not in the paper): each SKR joint moved by a PointNet on the points around it.

The torch twin of minretarget/refine.py (see its docstring for the layout): per joint, its K
nearest points relative to the joint over ``SCALE``, per-point linear + ReLU layers, a
max-pool, then an MLP on [pooled feature, the skeleton relative to the joint, one-hot of the
joint] to an offset times ``SCALE``. No batch norm, so export copies the layers as they are.
"""
import torch
from torch import nn

from minretarget.config import ModelConfig
from minretarget.refine import MAX_POINTS, SCALE


def _linear_relu_chain(in_width, widths):
    layers = []
    for width in widths:
        layers += [nn.Linear(in_width, width), nn.ReLU()]
        in_width = width
    return nn.Sequential(*layers)


class JointRefiner(nn.Module):
    def __init__(self, config=ModelConfig()):
        super().__init__()
        if not config.refines:
            raise ValueError("the config has no refiner (refine_point_widths is empty)")
        self.neighbours = config.refine_neighbours
        self.point = _linear_relu_chain(3, config.refine_point_widths)
        width = config.refine_point_widths[-1] + 4 * config.num_joints
        self.hidden = _linear_relu_chain(width, config.refine_head_widths)
        self.output = nn.Linear((config.refine_head_widths or (width,))[-1], 3)

    def forward(self, points, joints):
        """points (B, P, 3), joints (B, J, 3) SKR's, metres -> refined joints (B, J, 3)."""
        points = points[:, ::-(-points.shape[1] // MAX_POINTS)]       # thinned as the runtime
        batch, count, _ = points.shape
        joint_count = joints.shape[1]
        k = min(self.neighbours, count)
        # Squared distances from the differences, as the runtime computes them (not cdist's
        # matrix-product shortcut, and ONNX has no cdist), so near-ties rank alike.
        distances = ((joints[:, :, None] - points[:, None]) ** 2).sum(dim=-1)  # (B, J, P)
        nearest = distances.topk(k, dim=2, largest=False).indices             # (B, J, K)
        neighbourhood = torch.gather(points[:, None].expand(batch, joint_count, count, 3), 2,
                                     nearest[..., None].expand(batch, joint_count, k, 3))
        local = (neighbourhood - joints[:, :, None]) / SCALE                  # (B, J, K, 3)
        feature = self.point(local).amax(dim=2)                               # (B, J, C)
        skeleton = (joints[:, None] - joints[:, :, None]).reshape(batch, joint_count, -1)
        one_hot = torch.eye(joint_count, dtype=joints.dtype,
                            device=joints.device).expand(batch, -1, -1)
        head_input = torch.cat([feature, skeleton, one_hot], dim=-1)
        return joints + SCALE * self.output(self.hidden(head_input))
