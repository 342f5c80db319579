"""A data pack: everything a build needs from the CMU motions and the anny bodies, in one file.

A GPU machine lent to a session gets the repository and nothing beside it (64 MiB in all): no
``../shared/data/cmu``, no anny and no body cache. A pack carries the training and validation
motions and bodies there, so that ``python -m training.data build --pack FILE`` makes the same
datasets (bar the test split) without them:

    python -m training.data pack --cmu ../shared/data/cmu --out data/pack.npz [--bodies 120]

Contents (``np.savez_compressed``, loaded without pickle):
    motion_rotations (N, J, 4) float32, motion_root (N, 3) float32: every frame of the
        training and validation motions at 30 fps (the trials' runs without broken feet,
        ``cmu.clean_segments``, unless packed with them), one after another, exactly as loaded;
    motion_starts (M + 1,) int64 each motion's first frame, then N; motion_names,
        motion_categories, motion_splits (M,) str ('train' or 'val'); motion_source_fps (M,)
        float64 the capture rates they were resampled from;
    actor_hip_height () float64 metres; include_broken () bool (``cmu.BROKEN_TRIALS`` kept);
    keep_broken_ankles () bool (frames with broken feet kept, ``cmu.broken_ankle_frames``;
        a pack without the key, from before it existed, kept them);
    body_names, body_splits (B,) str; phenotype_labels (K,) str, body_phenotypes (B, K)
        float64; body_joints (B, J, 3) float32 T-pose joints, exact;
    body_vertices (B, V, 3) float32 T-pose vertices;
    faces (F, 3) int32, skin_weights (V, J) float32: one copy, every anny body has the same
        mesh topology and skinning weights (checked when packing).
Everything is stored exactly, so on one machine a build from a pack is the build from the CMU
folder and the body cache, array for array (float16 vertices would halve the bodies' 20 MB,
but they move 5 % of a cloud's points to other triangles). With 120 training bodies (and 15
validation ones) it is 36.4 MB (34.7 MiB).
"""
import dataclasses
import hashlib
import io
from pathlib import Path

import numpy as np

from minretarget.atomic import atomic_write
from minretarget.formats.npz import load_npz
from minretarget.conventions import FPS

from .bodies import Body, check_one_mesh
from .cmu import Motion, clean_segments
from .datasets import BuildConfig, check_broken, cmu_motions, sampled_bodies

SPLITS = ("train", "val")
KEYS = ("motion_rotations", "motion_root", "motion_starts", "motion_names", "motion_categories",
        "motion_source_fps", "motion_splits", "actor_hip_height", "include_broken",
        "body_names", "body_splits", "phenotype_labels", "body_phenotypes", "body_joints",
        "body_vertices", "faces", "skin_weights")


def pack_arrays(motions, actor_hip_height, bodies, include_broken, keep_broken_ankles=False):
    """The pack's arrays (module docstring) of ``motions`` {'train', 'val': [Motion]} and
    ``bodies`` {'train', 'val': [Body]}. ValueError if the bodies differ in faces or skinning
    weights."""
    empty = [f"{split} {kind}" for split in SPLITS for kind, given in
             (("motions", motions), ("bodies", bodies)) if not given[split]]
    if empty:
        raise ValueError(f"a pack needs motions and bodies of both splits; no {empty}")
    trials = [(split, motion) for split in SPLITS for motion in motions[split]]
    every = [body for split in SPLITS for body in bodies[split]]
    slow = sorted(m.name for _, m in trials if m.fps != FPS)
    if slow:
        raise ValueError(f"motions {slow} are not at {FPS} fps")
    check_broken({split: motions[split] for split in SPLITS}, include_broken, keep_broken_ankles)
    check_one_mesh(every)
    first = every[0]
    labels = sorted(first.phenotype)
    return {
        "motion_rotations": np.concatenate([m.rotations for _, m in trials]).astype(np.float32),
        "motion_root": np.concatenate([m.root for _, m in trials]).astype(np.float32),
        "motion_starts": np.cumsum([0] + [len(m.rotations) for _, m in trials]),
        "motion_names": np.array([m.name for _, m in trials]),
        "motion_categories": np.array([m.category for _, m in trials]),
        "motion_source_fps": np.array([m.source_fps for _, m in trials], dtype=np.float64),
        "motion_splits": np.array([split for split, _ in trials]),
        "actor_hip_height": np.float64(actor_hip_height),
        "include_broken": np.bool_(include_broken),
        "keep_broken_ankles": np.bool_(keep_broken_ankles),
        "body_names": np.array([body.name for body in every]),
        "body_splits": np.array([split for split in SPLITS for _ in bodies[split]]),
        "phenotype_labels": np.array(labels),
        "body_phenotypes": np.array([[body.phenotype[k] for k in labels] for body in every]),
        "body_joints": np.stack([body.joints for body in every]).astype(np.float32),
        "body_vertices": np.stack([body.vertices for body in every]).astype(np.float32),
        "faces": first.faces.astype(np.int32), "skin_weights": first.weights.astype(np.float32),
    }


def write_pack(path, arrays):
    """Write a pack's arrays compressed, to a temporary name renamed to ``path``."""
    with atomic_write(path) as file:
        np.savez_compressed(file, **arrays)


def make_pack(cmu_dir, path, bodies=BuildConfig.bodies, include_broken=False, cache_dir=None,
              show_progress=True, keep_broken_ankles=False):
    """Load the CMU trials and the first ``bodies`` training bodies (and the validation bodies
    a build of that many uses) and write them to ``path``. Returns the arrays."""
    motions, actor_hip_height = cmu_motions(cmu_dir, show_progress, include_broken,
                                            keep_broken_ankles)
    chosen = sampled_bodies(BuildConfig(bodies=bodies), cache_dir)
    arrays = pack_arrays(motions, actor_hip_height, chosen, include_broken, keep_broken_ankles)
    write_pack(path, arrays)
    return arrays


@dataclasses.dataclass(frozen=True)
class Pack:
    """A loaded pack: motions and bodies as a build takes them (``datasets.build``)."""
    motions: dict            # {'train', 'val', 'test': [Motion]}; 'test' is always empty
    actor_hip_height: float
    bodies: dict             # {'train', 'val': [Body]}
    include_broken: bool
    sha256: str              # of the file: weights trained on it record it
    keep_broken_ankles: bool = True


def without_broken_ankles(pack):
    """``pack`` with its motions cut around broken feet (``cmu.clean_segments``), as a build
    from the CMU folder cuts them: a pack made before the cut existed, or with
    --keep-broken-ankles, holds them."""
    if not pack.keep_broken_ankles:
        return pack
    motions = {split: [run for motion in pack.motions[split] for run in clean_segments(motion)]
               for split in pack.motions}
    return dataclasses.replace(pack, motions=motions, keep_broken_ankles=False)


def load_pack(path):
    """Read a pack written by ``write_pack``. ValueError names the file if it is not one."""
    path = Path(path)
    try:
        contents = path.read_bytes()          # read once: hashed, then unpacked
    except OSError as error:
        raise ValueError(f"{path}: cannot read the pack ({error})") from None
    digest = hashlib.sha256(contents).hexdigest()
    arrays = load_npz(io.BytesIO(contents), name=path)
    missing = sorted(set(KEYS) - set(arrays))
    if missing:
        raise ValueError(f"{path}: not a data pack, missing {missing}")
    splits = set(arrays["motion_splits"].tolist()) | set(arrays["body_splits"].tolist())
    if splits != set(SPLITS):
        raise ValueError(f"{path}: a pack holds the splits {SPLITS}, this one {sorted(splits)}")
    starts = arrays["motion_starts"]
    motions = {"train": [], "val": [], "test": []}
    for i, (name, category, source_fps, split) in enumerate(zip(
            arrays["motion_names"].tolist(), arrays["motion_categories"].tolist(),
            arrays["motion_source_fps"].tolist(), arrays["motion_splits"].tolist())):
        frames = slice(starts[i], starts[i + 1])
        motions[split].append(Motion(name=name, rotations=arrays["motion_rotations"][frames],
                                     root=arrays["motion_root"][frames], fps=FPS,
                                     category=category, source_fps=source_fps))
    labels = arrays["phenotype_labels"].tolist()
    bodies = {split: [] for split in SPLITS}
    for i, (name, split) in enumerate(zip(arrays["body_names"].tolist(),
                                          arrays["body_splits"].tolist())):
        phenotype = dict(zip(labels, arrays["body_phenotypes"][i].tolist()))
        bodies[split].append(Body(name=name, phenotype=phenotype,
                                  vertices=arrays["body_vertices"][i], faces=arrays["faces"],
                                  joints=arrays["body_joints"][i], weights=arrays["skin_weights"]))
    return Pack(motions, float(arrays["actor_hip_height"]), bodies,
                bool(arrays["include_broken"]), digest,
                bool(arrays.get("keep_broken_ankles", True)))
