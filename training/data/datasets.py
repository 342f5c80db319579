"""Training, validation and test data: motions played on anny bodies, saved as ``.npz`` files.

Every file is written by ``np.savez`` (to a temporary name, then renamed) and is read with
``np.load(path, allow_pickle=False)``. Lengths are metres, rotations are canonical local
quaternions (w, x, y, z), frames are 30 fps (``minretarget.conventions``). ``body`` arrays index
the body names of ``manifest.json``'s ``bodies[split]``.

``skr_{train,val}.npz``: static frames for the skeleton regressor.
    points (N, P, 3) float32: an area-uniform sample of the posed mesh, in random order.
    joints (N, J, 3) float32: the posed joints.    body (N,) int32.
``skr_tpose_{train,val}.npz``: the same arrays for bodies standing in T-pose (half of the
clouds are subsets of the mesh vertices), because retargeting targets come in T-pose.
``skin_{train,val}.npz``: T-pose and posed surface points in correspondence, for the skinning
field.
    tpose_points (N, Q, 3) float32, posed_points (N, Q, 3) float32: the same surface points
    (triangle, barycentric coordinates drawn once per sample) on the T-pose and posed mesh.
    weights (N, Q, J) float16: the mesh's skinning weights interpolated at those points.
    rotations (N, J, 4) float32, root (N, 3) float32, tpose_joints (N, J, 3) float32,
    joints (N, J, 3) float32 (posed), body (N,) int32.
``smrm_{train,val}.npz``: skeleton clips of C frames (``clip_frames``, 30) for motion
retargeting.
    joints (N, C, J, 3) float32, rotations (N, C, J, 4) float32, root (N, C, 3) float32,
    tpose_joints (N, J, 3) float32 (the clip's body), body (N,) int32, and
    bodies_tpose_joints (B, J, 3) float32: every body of the split, to draw other targets from.
``sequences_{train,val}.npz``: whole trials as clouds, frame after frame, for the skeleton
denoiser (it learns how SKR's error moves over time): each trial of the split on a random
body of the split, not augmented (as the test sequences are).
    points (N, P, 3) float32: the trials' frames one after another, a fresh sample each.
    joints (N, J, 3) float32.    starts (S + 1,) int64: trial s is frames starts[s]:starts[s+1].
    body (S,) int32.
``test/<sequence>.npz``: one whole test trial (the DESIGN.md benchmark), source -> target.
    source_points (T, P, 3) float32: a fresh sample and order every frame.
    source_joints (T, J, 3), source_root (T, 3), source_tpose_joints (J, 3) float32.
    rotations (T, J, 4) float32: the motion's local rotations, shared by source and target.
    target_tpose_points (V, 3) float32 (the target mesh's vertices), target_faces (F, 3) int32,
    target_tpose_joints (J, 3) float32, target_weights (V, J) float32.
    target_joints (T, J, 3), target_root (T, 3), target_points (T, V, 3) float32: the ground
    truth as Mixamo makes it: the same local rotations on the target, the root translation
    scaled by the ratio of hip heights (target / source).
    name, category, source_body, target_body: str; fps: int.
    Everything stays float32, target_points included (about 2.7 of the default build's 3.7 GB):
    float16 would round points a few metres from the origin by 2-4 mm, as much as the MEDL
    metric measures (about 1 mm).
    Source and target of the i-th trial (sorted by name): source ``i // 4 % 4``, target
    ``i % 4`` of the fixed test bodies, so 16 trials cover every pair.

Training samples: a random training body plays a random motion frame or clip; the motion's
root translation is scaled by (body hip height / actor hip height) so the feet stay on the
ground, then turned by a random heading about +Y (root rotation and root translation) and
shifted by a random horizontal translation.
"""
import dataclasses
import functools
import json
import os
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from minretarget.conventions import (FORWARD_AXIS, FPS, JOINT_INDEX, LEFT_AXIS, NUM_JOINTS,
                                     UP_AXIS)
from minretarget.kinematics import forward_kinematics, quaternion_multiply, quaternion_slerp
from minretarget.sampling import points_from_barycentric, sample_point_clouds, sample_surface

from .bodies import (benchmark_bodies, body_from_seed, pose_body, posed_clouds,
                     sampled_body_seeds)
from .cmu import (BROKEN_TRIALS, MIN_SEGMENT_FRAMES, Trial, broken_ankle_frames,
                  clean_segments, cmu_tpose_joints, list_trials, load_motion, trial_of)

# Training subjects held out for validation (basketball and running; about 3,000 frames).
VALIDATION_SUBJECTS = frozenset({"06", "09"})
# Frames posed at once: bounds memory to about CHUNK x V x 12 float32 (~170 MB at 256).
CHUNK = 256


# Config fields added after builds were made, with the value that builds the data as before.
# (Builds before the broken captures and the broken feet were found had them: include_broken
# and keep_broken_ankles True.)
ADDED_CONFIG_FIELDS = {"category_power": 1.0, "seated_fraction": 0.0, "crossed_fraction": 0.0,
                       "include_broken": True, "keep_broken_ankles": True}


@dataclasses.dataclass(frozen=True)
class BuildConfig:
    """Sizes of a build. Validation gets a tenth of each training count (bodies: an eighth).

    The defaults take about 21 minutes on a 2-core machine and write 5.0 GB (0.7 GB of
    training and validation data, 1.3 GB of whole trials for the denoiser, about 10 minutes
    of the time, and 3.0 GB of test sequences).
    """
    seed: int = 0
    bodies: int = 120            # training bodies (the paper: 120)
    frames: int = 20_000         # SKR training frames (the paper: ~65,000)
    tpose_frames: int = 2_000    # SKR training frames of bodies in T-pose (targets come so)
    points: int = 2048           # P, points of a source cloud (SKR frames and test frames)
    skin_samples: int = 2_000    # SKIN training samples
    skin_points: int = 1024      # Q, surface points per SKIN sample
    clip_stride: int = 10        # frames between the starts of consecutive SMRM clips
    clip_frames: int = 30        # frames of an SMRM clip (the paper: 30)
    max_shift: float = 1.0       # horizontal shift augmentation: uniform in +-max_shift, metres
    # SKR frames (training and validation): each motion category's share of them is
    # proportional to its frame count to this power (1: every frame alike, as the motions
    # come, each drawn once before any twice; otherwise drawn with replacement; 0: every
    # category alike). README, Data and licences, says why.
    category_power: float = 1.0
    # SKR frames (training and validation) whose legs are bent as if seated or crouched
    # (``seated_legs``): the training motion has almost no sitting (577 of 53,326 frames).
    seated_fraction: float = 0.0
    # SKR frames (training and validation) with one leg crossed over the other
    # (``crossed_legs``): dancers cross their feet, and SKR then reads them swapped.
    crossed_fraction: float = 0.0
    # Keep the broken captures (``cmu.BROKEN_TRIALS``: bodies sink through the floor), as the
    # data of the shipped weights did; ``build`` refuses motions that contradict it.
    include_broken: bool = False
    # Keep the frames whose feet turn further from the shin than an ankle can
    # (``cmu.broken_ankle_frames``), as the data of the shipped weights did; otherwise the
    # motions are cut around them (``cmu.clean_segments``) and ``build`` refuses any left.
    keep_broken_ankles: bool = False

    def __post_init__(self):
        if not np.isfinite(self.category_power):
            raise ValueError(f"category_power must be finite, got {self.category_power}")
        for name in ("seated_fraction", "crossed_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")

    @property
    def val_bodies(self):
        return max(2, self.bodies // 8)


# ----------------------------------------------------------------------------- augmentation

def _about(axis, angles):
    """(...,) angles about the world axis 0, 1 or 2 (x, y, z), radians -> (..., 4) float32
    quaternions (w, x, y, z)."""
    half = np.asarray(angles, dtype=np.float64) / 2
    quaternions = np.zeros(half.shape + (4,), np.float32)
    quaternions[..., 0] = np.cos(half)
    quaternions[..., 1 + axis] = np.sin(half)
    return quaternions


def heading_quaternions(angles):
    """(...,) angles about +Y, radians -> (..., 4) float32 quaternions (w, x, y, z)."""
    return _about(UP_AXIS, angles)


def augment(rotations, root, heading, shift):
    """Turn a motion about +Y through the world origin, then shift it horizontally.

    Args:
        rotations: (..., J, 4) float32 local quaternions.
        root: (..., 3) float32 pelvis positions, metres.
        heading: (...,) angles about +Y, radians.
        shift: (..., 2) horizontal (x, z) translations, metres.
    Returns:
        rotations (..., J, 4) float32 (only the root's changes), root (..., 3) float32.
    """
    turn = heading_quaternions(heading)
    rotations = np.array(rotations, dtype=np.float32)
    rotations[..., 0, :] = quaternion_multiply(turn, rotations[..., 0, :])
    cos, sin = np.cos(heading), np.sin(heading)
    x, y, z = np.moveaxis(np.asarray(root, dtype=np.float64), -1, 0)
    root = np.stack([cos * x + sin * z + shift[..., 0], y, -sin * x + cos * z + shift[..., 1]], -1)
    return rotations, root.astype(np.float32)


# ----------------------------------------------------------------------------- motions

@dataclasses.dataclass(frozen=True)
class Frames:
    """Every frame of a split's motions, stacked: rotations (N, J, 4), root (N, 3)."""
    rotations: np.ndarray
    root: np.ndarray
    starts: np.ndarray           # (trials + 1,) first frame of each trial, then N
    categories: tuple            # (trials,) each trial's motion category

    @staticmethod
    def of(motions):
        lengths = [len(m.rotations) for m in motions]
        return Frames(np.concatenate([m.rotations for m in motions]).astype(np.float32),
                       np.concatenate([m.root for m in motions]).astype(np.float32),
                       np.concatenate([[0], np.cumsum(lengths)]),
                       tuple(m.category for m in motions))

    def category_weights(self, power):
        """(N,) probabilities of drawing each frame so that a category's share is
        proportional to its frame count to ``power``; frames within a category alike."""
        category = np.repeat(np.array(self.categories), np.diff(self.starts))
        _, index, counts = np.unique(category, return_inverse=True, return_counts=True)
        log_share = power * np.log(counts)           # in logs: no overflow at large |power|
        share = np.exp(log_share - log_share.max())
        weights = (share / share.sum() / counts)[index]
        return weights / weights.sum()

    def clip_starts(self, stride, length):
        """First frames of every ``length``-frame window at ``stride`` inside one trial."""
        return np.concatenate([np.arange(a, b - length + 1, stride)
                               for a, b in zip(self.starts[:-1], self.starts[1:])] + [[]]
                              ).astype(np.int64)


def cmu_motions(cmu_dir, show_progress=True, include_broken=False, keep_broken_ankles=False):
    """Load every CMU trial at 30 fps (the broken ones, ``cmu.BROKEN_TRIALS``, only if
    ``include_broken``), split for training, validation and test; unless
    ``keep_broken_ankles``, each cut into the runs of frames between its broken feet
    (``cmu.clean_segments``: no test trial has any).

    Returns:
        motions: {'train', 'val', 'test'}: lists of ``cmu.Motion``; 'test' is DESIGN.md's test
            split, 'val' the training subjects in ``VALIDATION_SUBJECTS``.
        actor_hip_height: the CMU actor's T-pose pelvis height above the floor, metres.
    """
    trials = list_trials(cmu_dir, include_broken)
    if not trials:
        raise FileNotFoundError(f"no CMU trial (*.bvh.gz) under {cmu_dir}")
    motions = {"train": [], "val": [], "test": []}
    for trial in tqdm(trials, desc="loading CMU", unit="trial", disable=not show_progress):
        split = ("test" if trial.split == "test" else
                 "val" if trial.subject in VALIDATION_SUBJECTS else "train")
        motion = load_motion(trial.path, fps=FPS)
        motions[split].extend([motion] if keep_broken_ankles else clean_segments(motion))
    return motions, float(cmu_tpose_joints(trials[0].path)[0, 1])


def _draw_frames(total, count, rng):
    """``count`` frame indices, without repeats until every frame has been drawn once."""
    rounds = -(-count // total)
    return np.concatenate([rng.permutation(total) for _ in range(rounds)])[:count]


def seated_legs(rotations, rng):
    """Both legs of each pose bent as if seated or crouched; the rest of the pose kept.

    Per leg: the hip flexed forward within 15 degrees of an angle of 40 to 120 the two legs
    share, spread outward -5 to 25 and twisted +-15 about the thigh; the knee flexed 40 to
    140; the ankle turned to keep the sole near level (within +-40 degrees). Local rotations
    are turns from the T-pose, whose left axis is +X, up +Y and forward +Z, so a flexion is a
    turn about the parent's +X whatever the body's heading.

    Args:
        rotations: (N, J, 4) float32 local quaternions (w, x, y, z).
        rng: numpy Generator.
    Returns:
        (N, J, 4) float32.
    """
    rotations = np.array(rotations, dtype=np.float32)
    count = len(rotations)
    hip_base = rng.uniform(np.radians(40), np.radians(120), count)
    for side, outward in (("left", 1.0), ("right", -1.0)):
        hip = hip_base + rng.uniform(-np.radians(15), np.radians(15), count)
        spread = outward * rng.uniform(-np.radians(5), np.radians(25), count)
        twist = rng.uniform(-np.radians(15), np.radians(15), count)
        knee = rng.uniform(np.radians(40), np.radians(140), count)
        ankle = np.clip(hip - knee, -np.radians(40), np.radians(40))
        _set_leg(rotations, slice(None), side, spread, hip, twist, knee, ankle)
    return rotations


def crossed_legs(rotations, rng):
    """One leg of each pose (left or right, alike) swung across the other, in front of it or
    behind; the rest of the pose kept. Dancers cross a foot over and back while the other
    stands, and SKR, which has seen few such poses, reads the feet back on their own sides.

    The crossing leg: the hip turned in toward the other leg by 30 to 50 degrees and flexed
    15 to 45 forward (the foot crosses in front) or extended 10 to 30 backward (behind), half
    the poses each, twisted +-15 about the thigh; the knee flexed 0 to 60; the ankle turned
    to keep the sole near level (within +-30 degrees). Axes as in ``seated_legs``.

    Args:
        rotations: (N, J, 4) float32 local quaternions (w, x, y, z).
        rng: numpy Generator.
    Returns:
        (N, J, 4) float32.
    """
    rotations = np.array(rotations, dtype=np.float32)
    left, *angles = _crossing(len(rotations), rng)
    for side, chosen in (("left", left), ("right", ~left)):
        _set_leg(rotations, chosen, side, *(angle[chosen] for angle in angles))
    return rotations


def _crossing(count, rng):
    """``count`` crossings as ``crossed_legs`` draws them: whether the left leg crosses (N,)
    bool, and its spread, hip flexion, twist, knee and ankle angles (N,) each, radians."""
    left = rng.random(count) < 0.5
    in_front = rng.random(count) < 0.5
    inward = np.where(left, -1.0, 1.0) * rng.uniform(np.radians(30), np.radians(50), count)
    hip = np.where(in_front, rng.uniform(np.radians(15), np.radians(45), count),
                   -rng.uniform(np.radians(10), np.radians(30), count))
    twist = rng.uniform(-np.radians(15), np.radians(15), count)
    knee = rng.uniform(0.0, np.radians(60), count)
    ankle = np.clip(hip - knee, -np.radians(30), np.radians(30))
    return left, inward, hip, twist, knee, ankle


def crossings_over_time(rotations, rng, gap=(20, 40), hold=(15, 45), ramp=8):
    """A motion (T, J, 4) with one leg crossed over the other now and then, as a dancer crosses a
    foot over and back: after a gap of ``gap`` frames (uniform in [low, high)), a crossing
    drawn as ``crossed_legs`` draws one is blended in over ``ramp`` frames (slerp,
    smoothstep), held ``hold`` frames (likewise) and blended out over ``ramp``; the other
    leg and the rest of the pose keep the motion. Returns the rotations (T, J, 4) float32
    and each frame's weight of the crossing (T,) float32 (0: the motion's own legs)."""
    rotations = np.array(rotations, dtype=np.float32)
    frames = len(rotations)
    weight = np.zeros(frames, np.float32)
    rise = np.arange(1, ramp + 1) / (ramp + 1)
    rise = rise * rise * (3 - 2 * rise)                              # smoothstep
    start = int(rng.integers(*gap))
    while start < frames:
        held = int(rng.integers(*hold))
        window = np.concatenate([rise, np.ones(held), rise[::-1]])[:frames - start]
        span = slice(start, start + len(window))
        left, *angles = _crossing(1, rng)
        side = "left" if left[0] else "right"
        crossed = rotations[span].copy()
        _set_leg(crossed, slice(None), side, *(np.repeat(a, len(window)) for a in angles))
        for joint in (f"{side}_hip", f"{side}_knee", f"{side}_ankle"):
            j = JOINT_INDEX[joint]
            rotations[span, j] = quaternion_slerp(rotations[span, j], crossed[:, j], window)
        weight[span] = window
        start += len(window) + int(rng.integers(*gap))
    rotations *= np.where(rotations[..., :1] < 0, -1, 1).astype(np.float32)      # w >= 0
    return rotations, weight


def _set_leg(rotations, rows, side, spread, flexion, twist, knee, ankle):
    """Write one leg's local rotations into ``rotations[rows]`` (N, J, 4): the hip twisted
    about the thigh, flexed forward about the left axis, then turned about the forward axis
    by ``spread`` (outward for positive on the left leg); knee and ankle flexed about the
    left axis. Angles in radians, one per row."""
    rotations[rows, JOINT_INDEX[f"{side}_hip"]] = quaternion_multiply(
        _about(FORWARD_AXIS, spread),
        quaternion_multiply(_about(LEFT_AXIS, -flexion), _about(UP_AXIS, twist)))
    rotations[rows, JOINT_INDEX[f"{side}_knee"]] = _about(LEFT_AXIS, knee)
    rotations[rows, JOINT_INDEX[f"{side}_ankle"]] = _about(LEFT_AXIS, ankle)


def _augmentation(rng, shape, max_shift):
    return rng.uniform(0, 2 * np.pi, shape), rng.uniform(-max_shift, max_shift, shape + (2,))


def _chunks(indices):
    for start in range(0, len(indices), CHUNK):
        yield indices[start:start + CHUNK]


# ----------------------------------------------------------------------------- datasets

def skr_samples(frames, bodies, count, points, actor_hip_height, rng, max_shift,
                category_power=1.0, seated_fraction=0.0, crossed_fraction=0.0, progress=None):
    """Static frames: random body, random frame (categories weighted by
    ``BuildConfig.category_power``; a ``seated_fraction`` of them with ``seated_legs``, then
    a ``crossed_fraction`` with ``crossed_legs``), augmented; see the module docstring."""
    body, rotations, root = skr_poses(frames, bodies, count, actor_hip_height, rng, max_shift,
                                      category_power, seated_fraction, crossed_fraction)
    out = {"points": np.empty((count, points, 3), np.float32),
           "joints": np.empty((count, NUM_JOINTS, 3), np.float32), "body": body}
    for b, model in enumerate(bodies):
        for chunk in _chunks(np.flatnonzero(body == b)):
            out["points"][chunk], out["joints"][chunk] = posed_clouds(
                model, rotations[chunk], root[chunk], points, rng)
            if progress is not None:
                progress.update(len(chunk))
    return out


def skr_poses(frames, bodies, count, actor_hip_height, rng, max_shift, category_power=1.0,
              seated_fraction=0.0, crossed_fraction=0.0):
    """The draws of ``skr_samples``, before posing: (count,) int32 bodies, (count, J, 4)
    float32 rotations and (count, 3) float32 roots (the actor's scaled to each body's hips,
    turned and shifted)."""
    if category_power == 1.0:
        frame = _draw_frames(len(frames.root), count, rng)
    else:
        frame = rng.choice(len(frames.root), count, p=frames.category_weights(category_power))
    body = rng.integers(len(bodies), size=count).astype(np.int32)
    heading, shift = _augmentation(rng, (count,), max_shift)
    drawn = frames.rotations[frame]
    if seated_fraction > 0.0:       # no draws otherwise: default builds stay as they were
        seated = np.flatnonzero(rng.random(count) < seated_fraction)
        drawn[seated] = seated_legs(drawn[seated], rng)
    if crossed_fraction > 0.0:
        crossed = np.flatnonzero(rng.random(count) < crossed_fraction)
        drawn[crossed] = crossed_legs(drawn[crossed], rng)
    scale = np.array([model.hip_height for model in bodies])[body] / actor_hip_height
    rotations, root = augment(drawn, frames.root[frame] * scale[:, None].astype(np.float32),
                              heading, shift)
    return body, rotations, root


def skr_tpose_samples(bodies, count, points, rng, max_shift, progress=None):
    """Bodies standing in T-pose, as retargeting targets come: SKR must find their skeletons.

    Half the clouds are random subsets of the mesh vertices (a target is often given as its
    mesh), half are area-uniform samples; heading and horizontal shift are augmented like the
    motion frames. Same arrays as ``skr_samples``.
    """
    body = rng.integers(len(bodies), size=count).astype(np.int32)
    heading, shift = _augmentation(rng, (count,), max_shift)
    identity = np.zeros((count, NUM_JOINTS, 4), np.float32)
    identity[..., 0] = 1
    out = {"points": np.empty((count, points, 3), np.float32),
           "joints": np.empty((count, NUM_JOINTS, 3), np.float32), "body": body}
    for b, model in enumerate(bodies):
        chunk = np.flatnonzero(body == b)
        if not len(chunk):
            continue
        pelvis = np.broadcast_to(model.joints[0], (len(chunk), 3))
        rotations, root = augment(identity[chunk], pelvis, heading[chunk], shift[chunk])
        vertices, joints = pose_body(model, rotations, root)
        sampled = sample_point_clouds(vertices, model.faces, points, rng)
        for i, n in enumerate(chunk):
            use_vertices = rng.random() < 0.5 and len(model.vertices) >= points
            out["points"][n] = (vertices[i][rng.choice(len(model.vertices), points, replace=False)]
                                if use_vertices else sampled[i])
        out["joints"][chunk] = joints
        if progress is not None:
            progress.update(len(chunk))
    return out


def skin_samples(frames, bodies, count, points, actor_hip_height, rng, max_shift, progress=None):
    """T-pose and posed surface points in correspondence; see the module docstring."""
    frame = _draw_frames(len(frames.root), count, rng)
    body = rng.integers(len(bodies), size=count).astype(np.int32)
    heading, shift = _augmentation(rng, (count,), max_shift)
    out = {name: np.empty((count, points, 3), np.float32)
           for name in ("tpose_points", "posed_points")}
    out.update(weights=np.empty((count, points, NUM_JOINTS), np.float16),
               rotations=np.empty((count, NUM_JOINTS, 4), np.float32),
               root=np.empty((count, 3), np.float32),
               tpose_joints=np.empty((count, NUM_JOINTS, 3), np.float32),
               joints=np.empty((count, NUM_JOINTS, 3), np.float32), body=body)
    for b, model in enumerate(bodies):
        scale = model.hip_height / actor_hip_height
        for chunk in _chunks(np.flatnonzero(body == b)):
            rotations, root = augment(frames.rotations[frame[chunk]],
                                      frames.root[frame[chunk]] * scale,
                                      heading[chunk], shift[chunk])
            vertices, joints = pose_body(model, rotations, root)
            for i, n in enumerate(chunk):
                face, barycentric = sample_surface(model.vertices, model.faces, points, rng)
                out["tpose_points"][n] = points_from_barycentric(model.vertices, model.faces,
                                                                 face, barycentric)
                out["posed_points"][n] = points_from_barycentric(vertices[i], model.faces,
                                                                 face, barycentric)
                corners = model.weights[model.faces[face]]                # (Q, 3, J)
                out["weights"][n] = np.einsum("qcj,qc->qj", corners, barycentric)
            out["rotations"][chunk], out["root"][chunk] = rotations, root
            out["tpose_joints"][chunk], out["joints"][chunk] = model.joints, joints
            if progress is not None:
                progress.update(len(chunk))
    return out


def smrm_clips(frames, bodies, stride, length, actor_hip_height, rng, max_shift,
               progress=None):
    """Every ``length``-frame window (at ``stride``) once, each on a random body, augmented."""
    starts = frames.clip_starts(stride, length)
    count = len(starts)
    body = rng.integers(len(bodies), size=count).astype(np.int32)
    heading, shift = _augmentation(rng, (count,), max_shift)
    window = starts[:, None] + np.arange(length)                        # (N, length)
    scale = np.array([m.hip_height / actor_hip_height for m in bodies], np.float32)[body]
    rotations, root = augment(frames.rotations[window],
                              frames.root[window] * scale[:, None, None],
                              heading[:, None], shift[:, None])
    tpose_joints = np.stack([m.joints for m in bodies])[body]           # (N, J, 3)
    joints, _ = forward_kinematics(rotations, root, tpose_joints[:, None])
    if progress is not None:
        progress.update(count)
    return {"joints": joints, "rotations": rotations, "root": root,
            "tpose_joints": tpose_joints, "body": body,
            "bodies_tpose_joints": np.stack([m.joints for m in bodies])}


def trial_sequences(frames, bodies, points, actor_hip_height, rng, progress=None):
    """Every trial of ``frames`` played whole on a random body; see the module docstring."""
    count = int(frames.starts[-1])
    body = rng.integers(len(bodies), size=len(frames.starts) - 1).astype(np.int32)
    out = {"points": np.empty((count, points, 3), np.float32),
           "joints": np.empty((count, NUM_JOINTS, 3), np.float32),
           "starts": frames.starts.astype(np.int64), "body": body}
    for trial, model in enumerate(bodies[b] for b in body):
        scale = model.hip_height / actor_hip_height
        for chunk in _chunks(np.arange(frames.starts[trial], frames.starts[trial + 1])):
            out["points"][chunk], out["joints"][chunk] = posed_clouds(
                model, frames.rotations[chunk], frames.root[chunk] * scale, points, rng)
            if progress is not None:
                progress.update(len(chunk))
    return out


def benchmark_sequence(motion, source, target, points, actor_hip_height, rng, progress=None):
    """One benchmark sequence: ``motion`` on ``source`` (clouds) and on ``target`` (ground
    truth, Mixamo style); see the module docstring."""
    rotations = np.asarray(motion.rotations, np.float32)
    frames = len(rotations)
    source_root = (motion.root * (source.hip_height / actor_hip_height)).astype(np.float32)
    target_root = (motion.root * (target.hip_height / actor_hip_height)).astype(np.float32)
    out = {"source_points": np.empty((frames, points, 3), np.float32),
           "source_joints": np.empty((frames, NUM_JOINTS, 3), np.float32),
           "target_points": np.empty((frames,) + target.vertices.shape, np.float32),
           "target_joints": np.empty((frames, NUM_JOINTS, 3), np.float32)}
    for chunk in _chunks(np.arange(frames)):
        out["source_points"][chunk], out["source_joints"][chunk] = posed_clouds(
            source, rotations[chunk], source_root[chunk], points, rng)
        out["target_points"][chunk], out["target_joints"][chunk] = pose_body(
            target, rotations[chunk], target_root[chunk])
        if progress is not None:
            progress.update(len(chunk))
    out.update(source_root=source_root, source_tpose_joints=source.joints, rotations=rotations,
               target_root=target_root, target_tpose_points=target.vertices,
               target_faces=target.faces, target_tpose_joints=target.joints,
               target_weights=target.weights, name=np.array(motion.name),
               category=np.array(motion.category), source_body=np.array(source.name),
               target_body=np.array(target.name), fps=np.array(FPS))
    return out


def validation_sequences(cmu_dir, trials=12, max_frames=240, points=2048):
    """Benchmark sequences from validation motion, never the test split: ``trials`` trials of
    the held-out training subjects (VALIDATION_SUBJECTS; not the broken ``cmu.BROKEN_TRIALS``,
    whose place the next trial drawn takes), at most ``max_frames`` frames each, on held-out
    validation bodies (source and target differ), sampled as the test benchmark is. Returns
    ``HeldOutSequence``s: ``build()`` makes the sequence (seconds of work, so a caller with a
    cache can skip it); the same every time (fixed seeds)."""
    # drawn from every trial, broken ones then skipped: the others keep their bodies and seeds
    chosen = [t for t in list_trials(cmu_dir, include_broken=True)
              if t.subject in VALIDATION_SUBJECTS]
    order = np.random.default_rng(0).permutation(len(chosen))
    kept = [(k, chosen[i]) for k, i in enumerate(order) if chosen[i].name not in BROKEN_TRIALS]
    return _on_validation_bodies(kept[:trials], max_frames, points, seed=0)


# Dance and martial-arts trials of the training split (16 of its 55 dance, salsa and martial
# trials; at most 600 frames each, then each trial's longest run without broken feet: 6,954
# frames): the validation subjects have no such motion, where the test set's feet slide most.
# SKR and the rest trained on these motions, on other bodies, so they show how a change
# carries to held-out bodies, not to new motion. Four of them hold broken feet in their first
# 600 frames (``cmu.broken_ankle_frames``): 05_06 keeps its first 31 of 220 frames, 05_08
# frames 40-178, 05_18 the first 322 of 456 and salsa_01 the first 356 of 600 (until the
# ninth session the set kept them whole: 7,561 frames).
DANCE_TRIALS = ("05_02", "05_06", "05_08", "05_12", "05_14", "05_18", "martial_03",
                "martial_06", "martial_08", "salsa_01", "salsa_12", "salsa_16", "salsa_20",
                "salsa_21", "salsa_25", "salsa_28")


def dance_sequences(cmu_dir, max_frames=600, points=2048):
    """Benchmark sequences of ``DANCE_TRIALS`` on held-out validation bodies, as
    ``validation_sequences`` makes them (its seeds offset), as ``HeldOutSequence``s."""
    return _on_validation_bodies(list(enumerate(_dance_trials(cmu_dir))), max_frames, points,
                                 seed=1)


def _dance_trials(cmu_dir):
    """The ``Trial``s of ``DANCE_TRIALS``, in that order (FileNotFoundError if any is missing)."""
    trials = {t.name: t for t in list_trials(cmu_dir)}
    missing = [name for name in DANCE_TRIALS if name not in trials]
    if missing:
        raise FileNotFoundError(f"dance trials {missing} not found under {cmu_dir}")
    return [trials[name] for name in DANCE_TRIALS]


# Every other motion category of the training split (walks, runs, jumps, climbs, everyday,
# sports, fights, sitting...), up to four trials of each drawn with a fixed seed, at most 240
# frames each: a selection set for what the dances and validation's two subjects rarely show
# (legs crossing, say), on held-out bodies; SKR and the rest trained on these motions, on
# other bodies, as with the dances.
MOTION_CATEGORIES_LEFT_OUT = frozenset({"dance", "salsa", "martial"})     # the dances' own


def motion_sequences(cmu_dir, per_category=4, max_frames=240, points=2048):
    """Benchmark sequences of ``per_category`` trials of each motion category of the training
    split but the dances' (``MOTION_CATEGORIES_LEFT_OUT``), not of the validation subjects,
    drawn with a fixed seed (broken trials skipped), on held-out validation bodies, as
    ``validation_sequences`` makes them (its seeds offset), as ``HeldOutSequence``s."""
    by_category = {}
    for trial in list_trials(cmu_dir):
        if (trial.split == "train" and trial.subject not in VALIDATION_SUBJECTS
                and trial.category not in MOTION_CATEGORIES_LEFT_OUT):
            by_category.setdefault(trial.category, []).append(trial)
    rng = np.random.default_rng(2)
    chosen = []
    for category in sorted(by_category):
        trials = by_category[category]
        chosen += [trials[i] for i in sorted(rng.permutation(len(trials))[:per_category])]
    return _on_validation_bodies(list(enumerate(chosen)), max_frames, points, seed=2)


# Every dance, salsa and martial-arts trial of the training split that ``DANCE_TRIALS`` leaves
# out (39), at most 240 frames each: a wider selection set of dance motion. The test split's
# crossed legs rose in its Indian dances under a change no selection set moved (docs/
# source_fit.md); the training split has no Indian dance, so this is the most dance it holds,
# every such trial, fixed before any run on it.
def more_dance_sequences(cmu_dir, max_frames=240, points=2048):
    """Benchmark sequences of every training-split dance, salsa and martial trial not in
    ``DANCE_TRIALS`` (broken captures skipped), in ``list_trials`` order, on held-out validation
    bodies, as ``validation_sequences`` makes them (its seeds offset), as ``HeldOutSequence``s."""
    trials = [t for t in list_trials(cmu_dir)
              if t.split == "train" and t.subject not in VALIDATION_SUBJECTS
              and t.category in MOTION_CATEGORIES_LEFT_OUT and t.name not in DANCE_TRIALS]
    return _on_validation_bodies(list(enumerate(trials)), max_frames, points, seed=4)


# The dance trials again (at most 240 frames each), a leg crossed over the other every second
# or so (``crossings_over_time``, from the pose augmentation SKR trained with): a selection
# set for legs that cross, which the test split's dances show and the other selection sets
# barely do (the training split has no Indian dance).
def crossed_sequences(cmu_dir, max_frames=240, points=2048):
    """``DANCE_TRIALS`` with ``crossings_over_time``, on held-out validation bodies, as
    ``validation_sequences`` makes them (its seeds offset), as ``HeldOutSequence``s named
    "<trial>+crossed". Trial k's crossings are drawn from the seed (3, k), the same seed as
    its clouds' sampling: harmless, and kept so that the set stays the one measured."""
    def crossed(motion, k):
        rotations, _ = crossings_over_time(motion.rotations, np.random.default_rng([3, k]))
        return dataclasses.replace(motion, rotations=rotations, name=f"{motion.name}+crossed")

    return _on_validation_bodies(list(enumerate(_dance_trials(cmu_dir))), max_frames, points,
                                 seed=3, vary=crossed)


class HeldOutSequence(NamedTuple):
    """One sequence of ``validation_sequences``, ``dance_sequences``, ``motion_sequences`` or
    ``crossed_sequences``, known before it is built: a caller can check names and lengths
    (against a saved run, say) at once."""
    trial: Trial
    name: str            # the sequence's: the trial's, or "<trial>@<first frame>" for a run;
                         # "+crossed" after it in ``crossed_sequences``
    frames: int
    build: object        # () -> the sequence's dict, as ``benchmark_sequence`` makes it


def _on_validation_bodies(numbered_trials, max_frames, points, seed, vary=None):
    """(k, Trial) pairs -> ``HeldOutSequence``s, trial k's benchmark sequence (its first
    ``max_frames`` frames at most, then the longest run of them without broken feet,
    ``cmu.clean_segments``, then ``vary(motion, k)`` if given) with validation bodies 2k and
    2k + 1 (mod 15) as source and target and its randomness seeded (seed, k)."""
    actor_hip_height = float(cmu_tpose_joints(numbered_trials[0][1].path)[0, 1])
    bodies = [body_from_seed(s) for s in sampled_body_seeds(15, "val")]

    def motion_of(trial):
        motion = load_motion(trial.path, fps=FPS)
        motion = dataclasses.replace(motion, rotations=motion.rotations[:max_frames],
                                     root=motion.root[:max_frames])
        motion = max(clean_segments(motion), key=lambda run: len(run.rotations), default=None)
        if motion is None:
            raise ValueError(f"trial {trial.name}: no {MIN_SEGMENT_FRAMES} frames in a row "
                             f"without broken feet in its first {max_frames}")
        return motion

    def build(motion, k):
        return benchmark_sequence(motion, bodies[2 * k % 15], bodies[(2 * k + 1) % 15],
                                  points, actor_hip_height, np.random.default_rng([seed, k]))

    held_out = []
    for k, trial in numbered_trials:
        motion = motion_of(trial)
        if vary is not None:
            motion = vary(motion, k)
        held_out.append(HeldOutSequence(trial, motion.name, len(motion.rotations),
                                        functools.partial(build, motion, k)))
    return held_out


# ----------------------------------------------------------------------------- build

def save_npz(path, arrays):
    """Write arrays with ``np.savez`` to a temporary name, then rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "wb") as file:
        np.savez(file, **arrays)
    os.replace(temporary, path)


DATASETS = ("skr", "skin", "smrm", "skr_tpose", "test", "sequences")


def check_broken(motions, include_broken, keep_broken_ankles=False):
    """ValueError if ``motions`` ({split: [Motion]}) hold a broken capture
    (``cmu.BROKEN_TRIALS``) and ``include_broken`` is False, or a frame with a broken foot
    (``cmu.broken_ankle_frames``) and ``keep_broken_ankles`` is False."""
    broken = sorted(m.name for split in motions.values() for m in split
                    if trial_of(m.name) in BROKEN_TRIALS)
    if broken and not include_broken:
        raise ValueError(f"the motions hold broken captures {broken} (cmu.BROKEN_TRIALS); "
                         "leave them out or build with include_broken=True")
    if keep_broken_ankles:
        return
    feet = {m.name: int(broken_ankle_frames(m.rotations).sum())
            for split in motions.values() for m in split}
    feet = {name: count for name, count in feet.items() if count}
    if feet:
        raise ValueError(f"the motions hold frames whose feet turn further than an ankle can "
                         f"(cmu.broken_ankle_frames; frames per motion: {feet}); cut them out "
                         "(cmu.clean_segments, as cmu_motions does) or build with "
                         "keep_broken_ankles=True")


def sampled_bodies(config, cache_dir=None):
    """{'train', 'val': [Body]}: the ``config.bodies`` and ``config.val_bodies`` sampled bodies
    a build uses (from the cache, else made with anny)."""
    return {split: [body_from_seed(seed, cache_dir) for seed in sampled_body_seeds(count, split)]
            for split, count in (("train", config.bodies), ("val", config.val_bodies))}


def first_bodies(bodies, config):
    """The first ``config.bodies`` and ``config.val_bodies`` of given bodies {'train', 'val':
    [Body]} (a data pack's); ValueError if there are fewer."""
    for split, count in (("train", config.bodies), ("val", config.val_bodies)):
        if len(bodies[split]) < count:
            raise ValueError(f"the build needs {count} {split} bodies, given "
                             f"{len(bodies[split])}")
    return {"train": bodies["train"][:config.bodies], "val": bodies["val"][:config.val_bodies]}


def build(motions, actor_hip_height, out_dir, config=BuildConfig(), cache_dir=None,
          show_progress=True, datasets=DATASETS, bodies=None):
    """Build the datasets into ``out_dir``, deterministically from ``config.seed``.

    Args:
        motions: {'train': [...], 'val': [...], 'test': [...]} lists of motions, each with
            ``name``, ``category``, ``rotations`` (T, J, 4) and ``root`` (T, 3) (metres, the
            actor's pelvis, +Y up, feet on the ground at y = 0) at 30 fps.
        actor_hip_height: the motions' actor's T-pose pelvis height above the floor, metres.
        out_dir: output folder.
        config: a ``BuildConfig``.
        cache_dir: body cache folder (None: ``bodies.default_cache_dir()``).
        show_progress: draw a tqdm progress bar.
        datasets: the kinds to build, of ``DATASETS`` (e.g. ("smrm",) for longer clips alone;
            each kind draws from its own random stream, so it comes out as in a full build).
            Built into a folder that holds a build already, they are added to its
            manifest, which must record the same config.
        bodies: None to make the sampled bodies (from the cache, else with anny), or
            {'train', 'val': [Body]} holding at least ``config.bodies`` and
            ``config.val_bodies`` of them, whose first ones are taken (a data pack's,
            ``pack.load_pack``); the test split's bodies always come from the cache.
    Returns:
        a summary dict: counts, file sizes (bytes), seconds; also saved as manifest.json.
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    previous = out_dir / "manifest.json"
    partial = set(datasets) != set(DATASETS) and previous.is_file()
    old = json.loads(previous.read_text()) if partial else {}
    # A manifest from before a config field existed was built as ADDED_CONFIG_FIELDS says.
    recorded = {**ADDED_CONFIG_FIELDS, **old["config"]} if "config" in old else {}
    check_broken(motions, config.include_broken, config.keep_broken_ankles)
    wanted = dataclasses.asdict(config)
    if partial and recorded != wanted:
        differing = sorted(k for k, v in wanted.items() if recorded.get(k) != v)
        raise ValueError(f"{previous} records another build config ({old.get('config')}; "
                         f"differs in {differing}); build these datasets with it, or into "
                         "another folder")
    # Each dataset has its own random stream, so changing one size leaves the others alone.
    streams = {name: np.random.default_rng([config.seed, k]) for k, name in enumerate(
        ("skr_train", "skr_val", "skin_train", "skin_val", "smrm_train", "smrm_val", "test",
         "skr_tpose_train", "skr_tpose_val", "sequences_train", "sequences_val"))}
    bodies = (sampled_bodies(config, cache_dir) if bodies is None
              else first_bodies(bodies, config))
    unknown = sorted(set(datasets) - set(DATASETS))
    if unknown:
        raise ValueError(f"unknown datasets {unknown}; known: {DATASETS}")
    targets, sources = benchmark_bodies(cache_dir) if "test" in datasets else ((), ())
    frames = {split: Frames.of(motions[split]) for split in ("train", "val")}
    counts = {"skr_train": config.frames, "skr_val": max(1, config.frames // 10),
              "skr_tpose_train": config.tpose_frames,
              "skr_tpose_val": max(1, config.tpose_frames // 10),
              "skin_train": config.skin_samples, "skin_val": max(1, config.skin_samples // 10),
              "smrm_train": len(frames["train"].clip_starts(config.clip_stride,
                                                                config.clip_frames)),
              "smrm_val": len(frames["val"].clip_starts(config.clip_stride,
                                                            config.clip_frames)),
              "test_frames": sum(len(m.rotations) for m in motions["test"]),
              **{f"sequences_{s}": int(frames[s].starts[-1]) for s in frames}}
    counts = {name: count for name, count in counts.items()
              if name.rsplit("_", 1)[0] in datasets}
    files = {}
    with tqdm(total=sum(counts.values()), unit="sample", disable=not show_progress,
              desc="building") as progress:
        for split in ("train", "val"):
            common = dict(frames=frames[split], bodies=bodies[split],
                          actor_hip_height=actor_hip_height, max_shift=config.max_shift,
                          progress=progress)
            for kind, make, sizes in (
                    ("skr", skr_samples, dict(count=counts.get(f"skr_{split}"),
                                              points=config.points,
                                              category_power=config.category_power,
                                              seated_fraction=config.seated_fraction,
                                              crossed_fraction=config.crossed_fraction)),
                    ("skin", skin_samples, dict(count=counts.get(f"skin_{split}"),
                                                points=config.skin_points)),
                    ("smrm", smrm_clips, dict(stride=config.clip_stride,
                                                length=config.clip_frames)),
                    ("skr_tpose", lambda frames, actor_hip_height, **rest:
                     skr_tpose_samples(**rest),
                     dict(count=counts.get(f"skr_tpose_{split}"), points=config.points)),
                    ("sequences", lambda frames, bodies, actor_hip_height, rng, progress,
                     max_shift, points: trial_sequences(frames, bodies, points,
                                                        actor_hip_height, rng, progress),
                     dict(points=config.points))):
                if kind not in datasets:
                    continue
                name = f"{kind}_{split}"
                progress.set_postfix_str(name)
                path = out_dir / f"{name}.npz"
                save_npz(path, make(rng=streams[name], **common, **sizes))
                files[path.name] = path.stat().st_size
        pairs = []
        test_motions = motions["test"] if "test" in datasets else []
        for i, motion in enumerate(sorted(test_motions, key=lambda m: m.name)):
            # Cycle through the 16 (source, target) pairs: target fastest.
            source, target = sources[(i // len(targets)) % len(sources)], targets[i % len(targets)]
            progress.set_postfix_str(f"test {motion.name}")
            path = out_dir / "test" / f"{motion.name}.npz"
            save_npz(path, benchmark_sequence(motion, source, target, config.points,
                                         actor_hip_height, streams["test"], progress))
            files[f"test/{path.name}"] = path.stat().st_size
            pairs.append({"sequence": motion.name, "category": motion.category,
                          "frames": len(motion.rotations), "source": source.name,
                          "target": target.name})
    summary = {
        "config": dataclasses.asdict(config), "actor_hip_height": actor_hip_height,
        "counts": {**counts, **({"test_sequences": len(pairs)} if "test" in datasets else {}),
                   "bodies_train": len(bodies["train"]), "bodies_val": len(bodies["val"]),
                   **{f"motion_frames_{s}": int(frames[s].starts[-1]) for s in frames},
                   **{f"trials_{s}": len(motions[s]) for s in motions}},
        "bodies": {split: [b.name for b in bodies[split]] for split in bodies},
        "phenotypes": {b.name: b.phenotype for b in (*bodies["train"], *bodies["val"],
                                                     *targets, *sources)},
        "trials": {split: sorted(m.name for m in motions[split]) for split in motions},
        "test_pairs": pairs,
        "files": files, "total_bytes": sum(files.values()),
        "seconds": round(time.perf_counter() - start, 1),
    }
    if partial:                                      # a partial build adds to the manifest
        summary = {**old, **summary, **{key: {**old.get(key, {}), **summary[key]}
                                        for key in ("counts", "files", "phenotypes")}}
        summary["test_pairs"] = pairs if "test" in datasets else old.get("test_pairs", [])
        summary["total_bytes"] = sum(summary["files"].values())
    temporary = out_dir / ".manifest.json.tmp"
    temporary.write_text(json.dumps(summary, indent=1))
    os.replace(temporary, out_dir / "manifest.json")
    return summary
