"""SKR's training frames drawn afresh for every batch, posed and sampled on the training device.

A build (``datasets.skr_samples``) poses a fixed set of frames once, on the CPU: 20,000 of them
take about 3 minutes and 0.5 GB, and a long run on a GPU would see the same clouds over and
over. Here each batch is new: the frames, bodies, turns, shifts and leg
edits are drawn as ``datasets.skr_poses`` draws them (numpy, cheap), and the heavy part, forward
kinematics, linear blend skinning and area-uniform surface sampling of the 13,718-vertex
meshes, runs in torch wherever the model is (``training.kinematics``, the torch twin of the
runtime's). So a session with a GPU trains SKR from a data pack (``pack.py``) and the small
T-pose build made from it (``skr_tpose``).
"""
import numpy as np
import torch

from training.kinematics import forward_kinematics, linear_blend_skinning, skinning_transforms

from .bodies import check_one_mesh
from .datasets import Frames, skr_poses


def surface_points(vertices, faces, count, generator=None):
    """Area-uniform points on meshes, fresh for each.

    Args:
        vertices: (B, V, 3) posed mesh vertices, metres.
        faces: (F, 3) int64 triangles.
        count: P, points per mesh.
        generator: a torch.Generator on ``vertices``' device, or None.
    Returns:
        (B, P, 3) points, metres, in random order.
    """
    first, second, third = (vertices[:, faces[:, k]] for k in range(3))  # (B, F, 3) each
    areas = torch.linalg.cross(second - first, third - first).norm(dim=-1)  # twice the areas
    face = torch.multinomial(areas, count, replacement=True, generator=generator)  # (B, P)
    r1 = torch.rand(face.shape, generator=generator, device=vertices.device).sqrt()
    r2 = torch.rand(face.shape, generator=generator, device=vertices.device)
    weights = torch.stack([1 - r1, r1 * (1 - r2), r1 * r2], -1)          # uniform in a triangle
    batch = torch.arange(len(face), device=face.device)[:, None, None]
    corners = vertices[batch, faces[face]]                               # (B, P, 3, 3)
    return (weights[..., None] * corners).sum(-2)


class OnlineFrames:
    """A split's motions and bodies, ready to pose on ``device``.

    Args:
        motions: [``cmu.Motion``] of one split; bodies: [``bodies.Body``] sharing one mesh
            topology and skinning weights (a pack's, ``pack.load_pack``).
        actor_hip_height: the motions' actor's pelvis height, metres.
        config: a ``datasets.BuildConfig`` (max_shift, category_power, seated_fraction,
            crossed_fraction are used).
        device: torch device of the batches.
    """

    def __init__(self, motions, bodies, actor_hip_height, config, device):
        check_one_mesh(bodies)
        self.frames, self.bodies = Frames.of(motions), bodies
        self.actor_hip_height, self.config, self.device = actor_hip_height, config, device

        def tensor(array, dtype=torch.float32):
            return torch.as_tensor(array, dtype=dtype, device=device)
        self.vertices = tensor(np.stack([b.vertices for b in bodies]))   # (B, V, 3)
        self.tpose_joints = tensor(np.stack([b.joints for b in bodies]))  # (B, J, 3)
        self.faces = tensor(bodies[0].faces, torch.int64)
        self.weights = tensor(bodies[0].weights)

    def poses(self, count, rng):
        """``datasets.skr_poses``' draws: (count,) bodies, (count, J, 4) rotations, (count, 3)
        roots (numpy)."""
        config = self.config
        return skr_poses(self.frames, self.bodies, count, self.actor_hip_height, rng,
                         config.max_shift, config.category_power, config.seated_fraction,
                         config.crossed_fraction)

    def pose(self, body, rotations, root):
        """Pose the bodies: (N,) body indices, (N, J, 4) rotations, (N, 3) roots (numpy) ->
        vertices (N, V, 3) and joints (N, J, 3), tensors on the device, metres."""
        body = torch.as_tensor(body, dtype=torch.int64, device=self.device)
        rotations = torch.as_tensor(rotations, dtype=torch.float32, device=self.device)
        root = torch.as_tensor(root, dtype=torch.float32, device=self.device)
        tpose = self.tpose_joints[body]
        joints, global_rotations = forward_kinematics(rotations, root, tpose)
        transforms = skinning_transforms(joints, global_rotations, tpose)
        return linear_blend_skinning(self.vertices[body], self.weights, transforms), joints

    def clouds(self, body, rotations, root, points, generator=None, chunk=64):
        """The posed bodies (``pose``' arguments) seen as fresh P-point clouds, ``chunk`` at a
        time (to bound memory): {'points': (N, P, 3), 'joints': (N, J, 3)}, tensors on the
        device; ``generator`` a torch Generator on the device for the surface points."""
        parts = []
        for start in range(0, len(body), chunk):
            part = slice(start, start + chunk)
            vertices, joints = self.pose(body[part], rotations[part], root[part])
            parts.append((surface_points(vertices, self.faces, points, generator), joints))
        return {"points": torch.cat([points for points, _ in parts]),
                "joints": torch.cat([joints for _, joints in parts])}

    def batch(self, count, points, rng, generator=None):
        """``count`` fresh frames (``poses`` drawn with the numpy Generator ``rng``, then
        ``clouds``)."""
        return self.clouds(*self.poses(count, rng), points, generator)
