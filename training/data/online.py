"""SKR's training frames drawn afresh for every batch, posed and sampled on the training device.

A build (``datasets.skr_samples``) poses a fixed set of frames once, on the CPU: 20,000 of them
take about 3 minutes and 0.5 GB, and a long run on a GPU would see the same clouds over and
over. Here each batch is new: the frames, bodies, turns, shifts and leg
edits are drawn as ``datasets.skr_poses`` draws them (numpy, cheap), and the heavy part, forward
kinematics, linear blend skinning and area-uniform surface sampling of the 13,718-vertex
meshes, runs in torch wherever the model is (``training.kinematics``, the torch twin of the
runtime's). So a session with a GPU trains SKR from a data pack (``pack.py``) alone.
"""
import numpy as np
import torch

from training.kinematics import forward_kinematics, linear_blend_skinning, skinning_transforms

from .datasets import _Frames, skr_poses


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
    corners = vertices[:, faces]                                        # (B, F, 3, 3)
    areas = torch.linalg.cross(corners[:, :, 1] - corners[:, :, 0],
                               corners[:, :, 2] - corners[:, :, 0]).norm(dim=-1)
    face = torch.multinomial(areas, count, replacement=True, generator=generator)  # (B, P)
    r1 = torch.rand(face.shape, generator=generator, device=vertices.device).sqrt()
    r2 = torch.rand(face.shape, generator=generator, device=vertices.device)
    weights = torch.stack([1 - r1, r1 * (1 - r2), r1 * r2], -1)          # uniform in a triangle
    chosen = corners[torch.arange(len(face), device=face.device)[:, None], face]  # (B, P, 3, 3)
    return (weights[..., None] * chosen).sum(-2)


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
        self.frames, self.bodies = _Frames.of(motions), bodies
        self.actor_hip_height, self.config, self.device = actor_hip_height, config, device
        first = bodies[0]
        if any(not (np.array_equal(b.faces, first.faces) and np.array_equal(b.weights,
                                                                          first.weights))
               for b in bodies[1:]):
            raise ValueError("online frames need bodies of one mesh topology and skinning "
                             "weights")

        def tensor(array, dtype=torch.float32):
            return torch.as_tensor(np.asarray(array), dtype=dtype, device=device)
        self.vertices = tensor(np.stack([b.vertices for b in bodies]))   # (B, V, 3)
        self.tpose_joints = tensor(np.stack([b.joints for b in bodies]))  # (B, J, 3)
        self.faces = tensor(first.faces, torch.int64)
        self.weights = tensor(first.weights)

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

    def batch(self, count, points, rng, generator=None):
        """``count`` fresh frames: {'points': (count, P, 3), 'joints': (count, J, 3)}, tensors
        on the device; ``rng`` a numpy Generator for the draws, ``generator`` a torch one on
        the device for the surface points."""
        body, rotations, root = self.poses(count, rng)
        vertices, joints = self.pose(body, rotations, root)
        return {"points": surface_points(vertices, self.faces, points, generator),
                "joints": joints}
