"""The body model the runtime's source fit tracks (``minretarget.fit``).

A linear shape space in the canonical T-pose, made from sampled anny training bodies (never
validation or test bodies):

1. Q surface points are drawn once, area-uniform, on the mean training body's mesh, as
   (triangle, barycentric coordinates); every body shares anny's faces, so the same points
   exist on every body and are linear in its vertices.
2. Each body's T-pose is the vector [Q surface points, 22 joints]; PCA over the bodies gives
   a mean and K components, scaled so that a body's coefficients are about N(0, 1).
3. The points' normals are the mean body's; their skinning weights the barycentric blend of
   their triangle's vertex weights (anny's are the same for every body), kept sparse: the
   B largest per point.

    python -m training.body_model --out minretarget/data/body_model.npz

The file is a flat ``.npz`` (no pickle) holding ``minretarget.fit.BodyModel``'s fields and
``metadata`` (JSON: how it was made, the variance the K components keep).
"""
import argparse
import json
import time

import numpy as np

from minretarget.atomic import atomic_write
from minretarget.fit import BodyModel
from minretarget.formats.glb import top_weights, vertex_normals
from minretarget.sampling import points_from_barycentric, sample_surface

from .data.bodies import body_from_seed, sampled_body_seeds

DEFAULT_BODIES = 400
DEFAULT_POINTS = 1536
DEFAULT_COMPONENTS = 16
BONES_PER_POINT = 6            # anny's blended weights touch at most 6 joints per point


def sparse_weights(weights, count):
    """(Q, J) rows summing to 1 -> the ``count`` largest per row as (Q, count) joint indices
    and weights (``glb.top_weights``); ValueError if a row had more non-zero weights."""
    if (np.count_nonzero(weights > 0, axis=1) > count).any():
        raise ValueError(f"a point has more than {count} non-zero skinning weights")
    return top_weights(weights, count)


def build_body_model(bodies, points=DEFAULT_POINTS, components=DEFAULT_COMPONENTS, seed=0):
    """A ``BodyModel``'s arrays (dict) from a list of ``Body`` (the module docstring), and
    the fraction of the bodies' variance the K components keep."""
    mean_vertices = np.mean([body.vertices for body in bodies], axis=0)
    faces, weights = bodies[0].faces, bodies[0].weights
    face_index, barycentric = sample_surface(mean_vertices, faces, points,
                                             np.random.default_rng(seed))
    vectors = np.stack([np.concatenate([                                     # (N, Q + J, 3)
        points_from_barycentric(body.vertices, faces, face_index, barycentric),
        body.joints]).astype(np.float64) for body in bodies])
    mean = vectors.mean(axis=0)
    centred = (vectors - mean).reshape(len(bodies), -1)                     # (N, (Q + J) * 3)
    _, singular, rows = np.linalg.svd(centred, full_matrices=False)
    scale = singular[:components] / np.sqrt(len(bodies) - 1)                # coefficient std
    basis = (rows[:components] * scale[:, None]).reshape((components,) + mean.shape)
    kept = float(np.sum(singular[:components] ** 2) / np.sum(singular ** 2))
    corners = faces[face_index]                                             # (Q, 3)
    normals = np.einsum("qc,qca->qa", barycentric, vertex_normals(mean_vertices, faces)[corners])
    point_weights = np.einsum("qc,qcj->qj", barycentric, weights[corners])
    bone_index, bone_weight = sparse_weights(point_weights, BONES_PER_POINT)
    arrays = BodyModel(points=mean[:points], points_basis=basis[:, :points],
                       normals=normals / np.linalg.norm(normals, axis=1, keepdims=True),
                       joints=mean[points:], joints_basis=basis[:, points:],
                       bone_index=bone_index, bone_weight=bone_weight)._asdict()
    return arrays, kept


def save_body_model(path, arrays, metadata):
    """Write a body model ``.npz`` atomically: floats as float32, indices as int32."""
    with atomic_write(path) as file:
        np.savez(file, metadata=np.array(json.dumps(metadata)), **{
            key: np.ascontiguousarray(value, np.int32 if key == "bone_index" else np.float32)
            for key, value in arrays.items()})


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--bodies", type=int, default=DEFAULT_BODIES)
    parser.add_argument("--points", type=int, default=DEFAULT_POINTS)
    parser.add_argument("--components", type=int, default=DEFAULT_COMPONENTS)
    args = parser.parse_args(argv)
    started = time.perf_counter()
    bodies = [body_from_seed(seed) for seed in sampled_body_seeds(args.bodies, "train")]
    arrays, kept = build_body_model(bodies, args.points, args.components)
    metadata = {"bodies": args.bodies, "split": "train", "points": args.points,
                "components": args.components, "variance_kept": kept}
    save_body_model(args.out, arrays, metadata)
    print(f"{args.out}: {args.bodies} training bodies, {args.points} points, "
          f"{args.components} components keeping {kept:.6f} of the variance "
          f"({time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
