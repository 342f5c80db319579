"""Dataset build: a tiny build on synthetic motions; contents, ground truth and determinism.

Needs anny (the 12 bodies of a tiny build take about 10 s once anny's model cache exists).
"""
import dataclasses
import json
import sys

import numpy as np
import pytest

pytest.importorskip("anny")

from minretarget.conventions import JOINT_INDEX, NUM_JOINTS  # noqa: E402
from minretarget.kinematics import forward_kinematics, quaternion_to_matrix  # noqa: E402
from training.data import bodies  # noqa: E402
from training.data.cmu import Motion  # noqa: E402
from training.data.datasets import (DATASETS, BuildConfig, Frames, augment,  # noqa: E402
                                     build, crossed_legs, crossings_over_time,
                                     seated_legs)

ACTOR_HIP_HEIGHT = 0.9
TINY = BuildConfig(seed=3, bodies=2, frames=12, points=64, skin_samples=6, skin_points=32,
                   clip_stride=10)


def _walk(name, frames, phase=0.0):
    """A synthetic motion: legs and arms swinging about x, root walking along +Z at hip height."""
    t = np.arange(frames) / 30.0
    angles = np.zeros((frames, NUM_JOINTS))
    for joint, sign in ((1, 1), (2, -1), (16, -1), (17, 1)):     # hips and shoulders
        angles[:, joint] = sign * 0.4 * np.sin(2 * np.pi * t + phase)
    angles[:, 4] = angles[:, 5] = 0.3                              # knees
    rotations = np.zeros((frames, NUM_JOINTS, 4), np.float32)
    rotations[..., 0], rotations[..., 1] = np.cos(angles / 2), np.sin(angles / 2)
    root = np.stack([np.zeros(frames), np.full(frames, ACTOR_HIP_HEIGHT), 1.2 * t], axis=1)
    return Motion(name=name, rotations=rotations, root=root.astype(np.float32), fps=30,
                  category="walk", source_fps=30)


MOTIONS = {"train": [_walk("train_a", 50), _walk("train_b", 40, 1.0)],
           "val": [_walk("val_a", 45, 2.0)],
           "test": [_walk("test_b", 20, 0.5), _walk("test_a", 35, 1.5)]}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("bodies")


@pytest.fixture(scope="module")
def built(tmp_path_factory, cache):
    out = tmp_path_factory.mktemp("data")
    summary = build(MOTIONS, ACTOR_HIP_HEIGHT, out, TINY, cache_dir=cache, show_progress=False)
    return out, summary


def _load(path):
    with np.load(path, allow_pickle=False) as data:
        return dict(data)


def _body(summary, split, index, cache):
    name = summary["bodies"][split][index]
    return bodies.get_body(summary["phenotypes"][name], name, cache)


def test_files_and_shapes(built):
    out, summary = built
    skr = _load(out / "skr_train.npz")
    assert skr["points"].shape == (12, 64, 3) and skr["points"].dtype == np.float32
    assert skr["joints"].shape == (12, NUM_JOINTS, 3) and skr["body"].shape == (12,)
    assert _load(out / "skr_val.npz")["points"].shape == (1, 64, 3)
    skin = _load(out / "skin_train.npz")
    assert skin["tpose_points"].shape == skin["posed_points"].shape == (6, 32, 3)
    assert skin["weights"].shape == (6, 32, NUM_JOINTS) and skin["weights"].dtype == np.float16
    smrm = _load(out / "smrm_train.npz")
    # Windows of 30 frames every 10 inside each trial: 50 frames -> 3, 40 frames -> 2.
    assert smrm["joints"].shape == (5, 30, NUM_JOINTS, 3)
    assert smrm["rotations"].shape == (5, 30, NUM_JOINTS, 4)
    assert smrm["bodies_tpose_joints"].shape == (2, NUM_JOINTS, 3)
    assert _load(out / "smrm_val.npz")["joints"].shape == (2, 30, NUM_JOINTS, 3)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["counts"]["test_sequences"] == 2 and manifest["counts"]["test_frames"] == 55
    assert sorted(p.name for p in (out / "test").iterdir()) == ["test_a.npz", "test_b.npz"]
    assert summary["total_bytes"] == sum(p.stat().st_size for p in out.rglob("*.npz"))


def test_training_samples_scale_the_root_by_hip_height(built, cache):
    out, summary = built
    skr = _load(out / "skr_train.npz")
    for n in range(len(skr["body"])):
        body = _body(summary, "train", skr["body"][n], cache)
        # The synthetic actor's pelvis stays at its hip height: the body's does too.
        assert abs(skr["joints"][n, 0, 1] - body.hip_height) < 1e-5
        # Bone lengths are the body's.
        np.testing.assert_allclose(np.linalg.norm(skr["joints"][n, 4] - skr["joints"][n, 1]),
                                   np.linalg.norm(body.joints[4] - body.joints[1]), rtol=1e-4)
        # Points lie around the body: within its reach of the pelvis.
        assert np.linalg.norm(skr["points"][n] - skr["joints"][n, 0], axis=1).max() < body.height


def test_sequences_are_whole_trials_posed_frame_after_frame(built, cache):
    out, summary = built
    for split in ("train", "val"):
        data = _load(out / f"sequences_{split}.npz")
        motions = MOTIONS[split]
        np.testing.assert_array_equal(data["starts"], np.cumsum([0] + [len(m.rotations)
                                                                     for m in motions]))
        assert data["points"].shape == (data["starts"][-1], 64, 3)
        for s, motion in enumerate(motions):
            body = _body(summary, split, data["body"][s], cache)
            frames = slice(data["starts"][s], data["starts"][s + 1])
            root = motion.root * (body.hip_height / ACTOR_HIP_HEIGHT)
            joints, _ = forward_kinematics(motion.rotations, root.astype(np.float32),
                                           body.joints)
            np.testing.assert_allclose(data["joints"][frames], joints, atol=1e-5)
            reach = np.linalg.norm(data["points"][frames] - joints[:, :1], axis=-1).max()
            assert reach < body.height


def test_skin_points_correspond(built, cache):
    out, summary = built
    skin = _load(out / "skin_train.npz")
    np.testing.assert_allclose(skin["weights"].astype(np.float32).sum(-1), 1.0, atol=5e-3)
    for n in range(len(skin["body"])):
        body = _body(summary, "train", skin["body"][n], cache)
        np.testing.assert_array_equal(skin["tpose_joints"][n], body.joints)
        joints, rotations = forward_kinematics(skin["rotations"][n], skin["root"][n], body.joints)
        np.testing.assert_allclose(skin["joints"][n], joints, atol=1e-5)
        # LBS of the T-pose points with their interpolated weights lands near the posed points
        # (LBS of interpolated weights vs interpolation of LBS: equal up to a few mm).
        transforms = np.concatenate([rotations, (joints - np.einsum(
            "jab,jb->ja", rotations, body.joints))[..., None]], axis=-1)       # (J, 3, 4)
        blended = np.einsum("qj,jab->qab", skin["weights"][n].astype(np.float32), transforms)
        posed = np.einsum("qab,qb->qa", blended[..., :3], skin["tpose_points"][n]) + blended[..., 3]
        assert np.linalg.norm(posed - skin["posed_points"][n], axis=1).max() < 0.02


def test_smrm_clips_are_fk_of_their_rotations(built):
    out, _ = built
    smrm = _load(out / "smrm_train.npz")
    joints, _ = forward_kinematics(smrm["rotations"], smrm["root"], smrm["tpose_joints"][:, None])
    np.testing.assert_allclose(smrm["joints"], joints, atol=1e-5)
    np.testing.assert_array_equal(smrm["tpose_joints"],
                                  smrm["bodies_tpose_joints"][smrm["body"]])


def test_test_sequences_are_mixamo_ground_truth(built, cache):
    out, summary = built
    targets, sources = bodies.benchmark_bodies(cache)
    for i, name in enumerate(["test_a", "test_b"]):                # sorted by name, cycled
        seq = _load(out / "test" / f"{name}.npz")
        source, target = sources[0], targets[i]
        assert str(seq["source_body"]) == source.name and str(seq["target_body"]) == target.name
        assert str(seq["name"]) == name and str(seq["category"]) == "walk"
        motion = next(m for m in MOTIONS["test"] if m.name == name)
        frames = len(motion.rotations)
        assert seq["source_points"].shape == (frames, 64, 3)
        assert seq["target_points"].shape == (frames, len(target.vertices), 3)
        np.testing.assert_array_equal(seq["rotations"], motion.rotations)
        np.testing.assert_allclose(seq["target_root"],
                                   seq["source_root"] * target.hip_height / source.hip_height,
                                   rtol=1e-5)
        np.testing.assert_allclose(seq["source_root"],
                                   motion.root * source.hip_height / ACTOR_HIP_HEIGHT, rtol=1e-5)
        vertices, joints = bodies.pose_body(target, motion.rotations, seq["target_root"])
        np.testing.assert_allclose(seq["target_points"], vertices, atol=1e-5)
        np.testing.assert_allclose(seq["target_joints"], joints, atol=1e-5)
        source_joints = forward_kinematics(motion.rotations, seq["source_root"], source.joints)[0]
        np.testing.assert_allclose(seq["source_joints"], source_joints, atol=1e-5)
        np.testing.assert_array_equal(seq["target_tpose_points"], target.vertices)
        np.testing.assert_array_equal(seq["target_faces"], target.faces)
        np.testing.assert_array_equal(seq["target_weights"], target.weights)
        # Fresh clouds every frame, on the source body (near its posed joints).
        assert not np.array_equal(seq["source_points"][0], seq["source_points"][1])
        reach = np.linalg.norm(seq["source_points"] - seq["source_joints"][:, :1], axis=-1)
        assert reach.max() < source.height


def test_builds_are_deterministic(built, cache, tmp_path):
    out, _ = built
    build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path / "again", TINY, cache_dir=cache,
          show_progress=False)
    for path in sorted(out.rglob("*.npz")):
        first, second = _load(path), _load(tmp_path / "again" / path.relative_to(out))
        assert first.keys() == second.keys()
        for key in first:
            assert first[key].dtype == second[key].dtype
            assert first[key].tobytes() == second[key].tobytes(), (path.name, key)
    other = build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path / "other",
                  BuildConfig(**{**TINY.__dict__, "seed": 4}), cache_dir=cache,
                  show_progress=False)
    assert other["counts"] == json.loads((out / "manifest.json").read_text())["counts"]
    assert not np.array_equal(_load(out / "skr_train.npz")["points"],
                              _load(tmp_path / "other" / "skr_train.npz")["points"])


def test_only_smrm_with_longer_clips(built, cache, tmp_path):
    out, _ = built
    config = BuildConfig(**{**TINY.__dict__, "clip_frames": 40})
    summary = build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path, config, cache_dir=cache,
                    show_progress=False, datasets=("smrm",))
    assert sorted(p.name for p in tmp_path.rglob("*.npz")) == ["smrm_train.npz", "smrm_val.npz"]
    # 40-frame windows every 10: 50 frames -> 2, 40 -> 1; validation's 45 frames -> 1.
    long = _load(tmp_path / "smrm_train.npz")
    assert long["joints"].shape == (3, 40, NUM_JOINTS, 3)
    assert summary["counts"]["smrm_train"] == 3 and "skr_train" not in summary["counts"]
    joints, _ = forward_kinematics(long["rotations"], long["root"], long["tpose_joints"][:, None])
    np.testing.assert_allclose(long["joints"], joints, atol=1e-5)
    # Targets are drawn from every training body, as in the full build.
    np.testing.assert_array_equal(long["bodies_tpose_joints"],
                                  _load(out / "smrm_train.npz")["bodies_tpose_joints"])
    with pytest.raises(ValueError, match="unknown datasets"):
        build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path, config, cache_dir=cache,
              show_progress=False, datasets=("smrm", "clips"))
    # Another partial build into the same folder adds to its manifest.
    build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path, config, cache_dir=cache, show_progress=False,
          datasets=("sequences",))
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["counts"]["smrm_train"] == 3 and manifest["counts"]["sequences_train"] == 90
    assert set(manifest["files"]) == {p.name for p in tmp_path.glob("*.npz")}
    with pytest.raises(ValueError, match="another build config"):
        build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path, BuildConfig(**{**config.__dict__, "seed": 4}),
              cache_dir=cache, show_progress=False, datasets=("sequences",))


def test_category_power_weighs_the_skr_frames_by_category():
    """Shares of the draw by category: as the frames come (power 1), alike (0), or in
    proportion to the square roots of their frame counts (0.5); frames within one alike;
    finite at powers whose plain powers of the counts would overflow."""
    run = dataclasses.replace(_walk("run", 100), category="run")
    frames = Frames.of([_walk("a", 200), run, _walk("b", 100)])              # 300 walk, 100 run
    walking = np.r_[np.ones(200, bool), np.zeros(100, bool), np.ones(100, bool)]
    for power, walk_share in ((1.0, 0.75), (0.0, 0.5), (0.5, np.sqrt(3) / (np.sqrt(3) + 1)),
                              (400.0, 1.0), (-400.0, 0.0)):
        weights = frames.category_weights(power)
        assert weights.shape == (400,) and abs(weights.sum() - 1) < 1e-12
        np.testing.assert_allclose(weights[walking], walk_share / 300, atol=1e-15)
        np.testing.assert_allclose(weights[~walking], (1 - walk_share) / 100, atol=1e-15)
    with pytest.raises(ValueError, match="category_power must be finite, got nan"):
        BuildConfig(category_power=float("nan"))


def test_category_power_changes_the_skr_frames_alone(built, cache, tmp_path):
    """Another power draws other SKR frames (training and validation) and leaves the other
    datasets as they were; a folder built before the field existed takes partial builds with
    the default power, refuses another, and says which field differs."""
    out, _ = built
    stripped = json.loads((out / "manifest.json").read_text())
    assert stripped["config"]["category_power"] == 1.0
    del stripped["config"]["category_power"]
    old = tmp_path / "old"
    old.mkdir()
    (old / "manifest.json").write_text(json.dumps(stripped))
    balanced = BuildConfig(**{**TINY.__dict__, "category_power": 0.0})
    with pytest.raises(ValueError, match=r"differs in \['category_power'\]"):
        build(MOTIONS, ACTOR_HIP_HEIGHT, old, balanced, cache_dir=cache, show_progress=False,
              datasets=("skr",))
    build(MOTIONS, ACTOR_HIP_HEIGHT, old, TINY, cache_dir=cache, show_progress=False,
          datasets=("skr",))
    for split in ("train", "val"):
        assert _load(old / f"skr_{split}.npz")["points"].tobytes() == \
            _load(out / f"skr_{split}.npz")["points"].tobytes()
    # MOTIONS are all walks: give one training trial its own category.
    motions = dict(MOTIONS, train=[MOTIONS["train"][0],
                                   dataclasses.replace(MOTIONS["train"][1], category="run")])
    plain, other = tmp_path / "plain", tmp_path / "other"
    for folder, config in ((plain, TINY), (other, balanced)):
        build(motions, ACTOR_HIP_HEIGHT, folder, config, cache_dir=cache, show_progress=False,
              datasets=("skr", "smrm"))
    assert _load(plain / "skr_train.npz")["joints"].tobytes() != \
        _load(other / "skr_train.npz")["joints"].tobytes()
    for key, value in _load(plain / "smrm_train.npz").items():
        np.testing.assert_array_equal(_load(other / "smrm_train.npz")[key], value, err_msg=key)


def _straight_legged_tpose():
    """(J, 3) a T-pose whose legs hang straight down from the hips (bones along -Y) onto
    level soles, the other joints anywhere: bend angles then read off directly."""
    joints = np.random.default_rng(0).normal(0.0, 0.1, (NUM_JOINTS, 3)) + (0.0, 1.2, 0.0)
    joints[0] = (0.0, 1.0, 0.0)
    for side, x in (("left", 0.1), ("right", -0.1)):
        for name, height in (("hip", 0.9), ("knee", 0.5), ("ankle", 0.1)):
            joints[JOINT_INDEX[f"{side}_{name}"]] = (x, height, 0.0)
        joints[JOINT_INDEX[f"{side}_foot"]] = (x, 0.1, 0.12)         # the sole level
    return joints.astype(np.float32)


def leg_joints():
    """The legs' joints (left hip, knee, ankle, then the right's) and every other joint."""
    legs = [JOINT_INDEX[f"{side}_{name}"] for side in ("left", "right")
            for name in ("hip", "knee", "ankle")]
    return legs, np.setdiff1d(np.arange(NUM_JOINTS), legs)


def test_seated_legs_bend_hips_and_knees_forward_and_keep_the_rest():
    """From any pose: the thighs swing forward 25 to 135 degrees from straight down (flexion
    40 to 120, spread and twist aside), each knee bends 40 to 140 degrees (the angle between
    thigh and shank, a hinge about the thigh's left axis), the soles stay within 40 degrees
    of the shank's right angle; every other joint's rotation is untouched."""
    rng = np.random.default_rng(1)
    rotations = rng.normal(size=(500, NUM_JOINTS, 4)).astype(np.float32)
    rotations /= np.linalg.norm(rotations, axis=-1, keepdims=True)
    rotations[:, 0] = (1.0, 0.0, 0.0, 0.0)           # an upright pelvis: angles in its frame
    seated = seated_legs(rotations, np.random.default_rng(2))
    legs, others = leg_joints()
    np.testing.assert_array_equal(seated[:, others], rotations[:, others])
    np.testing.assert_allclose(np.linalg.norm(seated, axis=-1), 1.0, atol=1e-6)
    joints = forward_kinematics(seated, np.zeros((500, 3), np.float32),
                                _straight_legged_tpose())[0]
    for side in ("left", "right"):
        hip, knee, ankle, foot = (joints[:, JOINT_INDEX[f"{side}_{name}"]]
                                  for name in ("hip", "knee", "ankle", "foot"))
        thigh, shank, sole = knee - hip, ankle - knee, foot - ankle
        swing = np.degrees(np.arctan2(thigh[:, 2], -thigh[:, 1]))
        assert swing.min() > 25 and swing.max() < 135
        cosine = (thigh * shank).sum(-1) / np.linalg.norm(thigh, axis=-1) / np.linalg.norm(
            shank, axis=-1)
        bend = np.degrees(np.arccos(np.clip(cosine, -1, 1)))
        assert bend.min() > 39.9 and bend.max() < 140.1
        assert bend.max() - bend.min() > 80                            # spread over the range
        cosine = (shank * sole).sum(-1) / np.linalg.norm(shank, axis=-1) / np.linalg.norm(
            sole, axis=-1)
        ankle_angle = np.degrees(np.arccos(np.clip(cosine, -1, 1)))
        assert np.abs(ankle_angle - 90).max() < 40.1


def test_crossed_legs_swing_one_foot_past_the_other_and_keep_the_rest():
    """From the T-pose: in each pose one leg (both sides drawn) swings in so that its toe
    passes the standing toe's side (by at least 1 cm), in front of it or behind (both drawn),
    with the knee bent at most 60 degrees; the standing leg and every other joint stay."""
    count = 400
    rotations = np.zeros((count, NUM_JOINTS, 4), np.float32)
    rotations[..., 0] = 1.0
    crossed = crossed_legs(rotations, np.random.default_rng(5))
    np.testing.assert_allclose(np.linalg.norm(crossed, axis=-1), 1.0, atol=1e-6)
    hips = [JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]]
    moved = (crossed[:, hips] != rotations[:, hips]).any(-1)                   # (N, 2)
    assert (moved.sum(1) == 1).all() and 0.35 < moved[:, 0].mean() < 0.65
    left = moved[:, 0]
    legs, others = leg_joints()
    np.testing.assert_array_equal(crossed[:, others], rotations[:, others])
    joints = forward_kinematics(crossed, np.zeros((count, 3), np.float32),
                                _straight_legged_tpose())[0]
    toe = {side: joints[:, JOINT_INDEX[f"{side}_foot"]] for side in ("left", "right")}
    swinging = np.where(left[:, None], toe["left"], toe["right"])
    standing = np.where(left[:, None], toe["right"], toe["left"])
    # The T-pose's left is +X: a crossing left toe lies right of (below) the right toe's x.
    past = np.where(left, standing[:, 0] - swinging[:, 0], swinging[:, 0] - standing[:, 0])
    assert past.min() > 0.01 and np.median(past) > 0.15
    in_front = swinging[:, 2] > standing[:, 2]
    assert 0.35 < in_front.mean() < 0.65
    for side, chosen in (("left", left), ("right", ~left)):
        hip, knee, ankle = (joints[chosen, JOINT_INDEX[f"{side}_{name}"]]
                            for name in ("hip", "knee", "ankle"))
        thigh, shank = knee - hip, ankle - knee
        cosine = (thigh * shank).sum(-1) / np.linalg.norm(thigh, axis=-1) / np.linalg.norm(
            shank, axis=-1)
        assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 60.1


def test_crossings_over_time_blend_a_crossed_leg_in_and_out_smoothly():
    """A standing motion (the T-pose, 300 frames): the crossing weight rises and falls by at
    most 1/ramp's smoothstep a frame; at weight 0 the pose is the motion's; at weight 1 one
    leg's toe is past the other's side; in each frame one leg at most and no other joint
    moves; the leg turns smoothly (no frame's rotation jumps); quaternions stay unit."""
    frames = 300
    rotations = np.zeros((frames, NUM_JOINTS, 4), np.float32)
    rotations[..., 0] = 1.0
    crossed, weight = crossings_over_time(rotations, np.random.default_rng(4))
    assert weight.min() == 0 and weight.max() == 1
    assert np.abs(np.diff(weight)).max() < 0.25           # smoothstep over 8 frames: < 0.2
    assert (weight > 0).sum() > 60 and (weight == 0).sum() > 60    # both, over and over
    np.testing.assert_array_equal(crossed[weight == 0], rotations[weight == 0])
    np.testing.assert_allclose(np.linalg.norm(crossed, axis=-1), 1.0, atol=1e-6)
    legs, others = leg_joints()
    np.testing.assert_array_equal(crossed[:, others], rotations[:, others])
    kept = [(crossed[:, side] == rotations[:, side]).all((1, 2))
            for side in (legs[:3], legs[3:])]
    assert (kept[0] | kept[1]).all() and not (kept[0] & kept[1]).all()
    joints = forward_kinematics(crossed, np.zeros((frames, 3), np.float32),
                                _straight_legged_tpose())[0]
    toes = joints[:, [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]]
    apart = toes[:, 0, 0] - toes[:, 1, 0]          # the T-pose's left is +X: > 0 uncrossed
    assert (apart[weight == 0] > 0).all() and (apart[weight == 1] < 0).all()
    assert np.linalg.norm(np.diff(toes, axis=0), axis=-1).max() < 0.15     # metres a frame


def test_seated_fraction_bends_the_skr_frames_knees(built, cache, tmp_path):
    """seated_fraction 1: every SKR frame's knee bends more than any of the plain build's
    walking frames' (at most 30 degrees, the body's rest bend in); out of [0, 1] refused."""
    out, _ = built
    folder = tmp_path / "seated"
    build(MOTIONS, ACTOR_HIP_HEIGHT, folder, BuildConfig(**{**TINY.__dict__,
                                                            "seated_fraction": 1.0}),
          cache_dir=cache, show_progress=False, datasets=("skr",))

    def knee_bend(joints):
        hip, knee, ankle = (joints[:, JOINT_INDEX[f"left_{name}"]]
                            for name in ("hip", "knee", "ankle"))
        thigh, shank = knee - hip, ankle - knee
        cosine = (thigh * shank).sum(-1) / np.linalg.norm(thigh, axis=-1) / np.linalg.norm(
            shank, axis=-1)
        return np.degrees(np.arccos(np.clip(cosine, -1, 1)))

    for split in ("train", "val"):
        plain = knee_bend(_load(out / f"skr_{split}.npz")["joints"])
        assert knee_bend(_load(folder / f"skr_{split}.npz")["joints"]).min() > plain.max() + 5
    with pytest.raises(ValueError, match=r"seated_fraction must be in \[0, 1\], got 1.5"):
        BuildConfig(seated_fraction=1.5)
    with pytest.raises(ValueError, match=r"crossed_fraction must be in \[0, 1\], got -0.1"):
        BuildConfig(crossed_fraction=-0.1)


@pytest.mark.parametrize("text, message", [("nan", "must be finite, got nan"),
                                           ("0.5x", "not a number: '0.5x'")])
def test_build_command_refuses_a_bad_category_power(tmp_path, capsys, text, message):
    from training.data.__main__ import main
    with pytest.raises(SystemExit) as exit_info:
        main(["build", "--cmu", str(tmp_path), "--out", str(tmp_path / "out"),
              "--category-power", text])
    assert exit_info.value.code == 2
    assert f"--category-power: {message}" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_augment_turns_about_y_and_shifts():
    rng = np.random.default_rng(0)
    rotations = rng.normal(size=(4, NUM_JOINTS, 4)).astype(np.float32)
    rotations /= np.linalg.norm(rotations, axis=-1, keepdims=True)
    root = rng.normal(size=(4, 3)).astype(np.float32)
    heading, shift = rng.uniform(0, 6, 4), rng.normal(size=(4, 2))
    turned, moved = augment(rotations, root, heading, shift)
    np.testing.assert_array_equal(turned[:, 1:], rotations[:, 1:])
    c, s = np.cos(heading), np.sin(heading)
    turn = np.zeros((4, 3, 3))
    turn[:, 0, 0], turn[:, 0, 2], turn[:, 1, 1], turn[:, 2, 0], turn[:, 2, 2] = c, s, 1, -s, c
    np.testing.assert_allclose(quaternion_to_matrix(turned[:, 0]),
                               turn @ quaternion_to_matrix(rotations[:, 0]), atol=1e-5)
    expected = np.einsum("nab,nb->na", turn, root) + np.insert(shift, 1, 0.0, axis=1)
    np.testing.assert_allclose(moved, expected, atol=1e-5)


def test_broken_captures_need_include_broken_and_old_builds_count_as_having_them(tmp_path):
    """Motions holding a broken capture are refused unless the config says so; a partial build
    into a folder made before the field existed (whose data kept them) is refused by default
    and accepted with include_broken=True."""
    broken = {**MOTIONS, "train": MOTIONS["train"] + [_walk("07_12", 30)]}
    with pytest.raises(ValueError, match=r"broken captures \['07_12'\]"):
        build(broken, ACTOR_HIP_HEIGHT, tmp_path / "a", TINY, show_progress=False)
    old_config = {k: v for k, v in dataclasses.asdict(TINY).items()
                  if k not in ("include_broken", "seated_fraction", "keep_broken_ankles")}
    (tmp_path / "manifest.json").write_text(json.dumps({"config": old_config}))
    with pytest.raises(ValueError, match=r"differs in \['include_broken', 'keep_broken_ankles'\]"):
        build(MOTIONS, ACTOR_HIP_HEIGHT, tmp_path, TINY, show_progress=False,
              datasets=("skin",))
    kept = BuildConfig(**{**TINY.__dict__, "include_broken": True})
    with pytest.raises(ValueError, match="another build config") as refused:
        build(broken, ACTOR_HIP_HEIGHT, tmp_path, BuildConfig(**{**kept.__dict__, "seed": 9}),
              show_progress=False, datasets=("skin",))
    assert "include_broken" not in str(refused.value).split("differs in")[1]


def test_motions_with_broken_feet_are_refused_unless_kept(tmp_path):
    """A frame whose ankle turns past cmu.ANKLE_LIMIT_DEGREES is refused unless the config
    keeps such frames; a segment of a broken capture is still a broken capture."""
    rotations = MOTIONS["train"][0].rotations.copy()
    rotations[7, JOINT_INDEX["left_ankle"]] = [np.cos(1.4), np.sin(1.4), 0, 0]   # 160 degrees
    twisted = dataclasses.replace(MOTIONS["train"][0], name="salsa_01", rotations=rotations)
    with pytest.raises(ValueError, match=r"feet turn further than an ankle can .*"
                                         r"\{'salsa_01': 1\}.*keep_broken_ankles=True"):
        build({**MOTIONS, "train": [twisted]}, ACTOR_HIP_HEIGHT, tmp_path / "a", TINY,
              show_progress=False)
    with pytest.raises(ValueError, match=r"broken captures \['07_12@45'\]"):
        build({**MOTIONS, "train": [_walk("07_12@45", 30)]}, ACTOR_HIP_HEIGHT, tmp_path / "b",
              TINY, show_progress=False)
    kept = BuildConfig(**{**TINY.__dict__, "keep_broken_ankles": True})
    summary = build({**MOTIONS, "train": [twisted]}, ACTOR_HIP_HEIGHT, tmp_path / "c", kept,
                    show_progress=False, datasets=("smrm",))
    assert summary["trials"]["train"] == ["salsa_01"]


# ----------------------------------------------------------------------------- data packs

def _tiny_pack(built, cache, path):
    """The tiny build's motions (train and val) and bodies, packed into ``path``."""
    from training.data.pack import pack_arrays, write_pack
    _, summary = built
    chosen = {split: [_body(summary, split, i, cache)
                      for i in range(len(summary["bodies"][split]))] for split in ("train", "val")}
    write_pack(path, pack_arrays(MOTIONS, ACTOR_HIP_HEIGHT, chosen, include_broken=False))
    return chosen


def test_a_build_from_a_pack_is_the_build_from_the_motions_and_cache_without_anny(
        built, cache, tmp_path, monkeypatch):
    from training.data.pack import load_pack
    out, _ = built
    chosen = _tiny_pack(built, cache, tmp_path / "pack.npz")
    monkeypatch.setitem(sys.modules, "anny", None)      # importing anny now fails
    pack = load_pack(tmp_path / "pack.npz")
    assert pack.actor_hip_height == ACTOR_HIP_HEIGHT and not pack.include_broken
    assert not pack.keep_broken_ankles
    assert [m.name for m in pack.motions["train"]] == ["train_a", "train_b"]
    assert pack.motions["test"] == []
    assert [b.name for b in pack.bodies["val"]] == [b.name for b in chosen["val"]]
    assert pack.bodies["train"][1].phenotype == chosen["train"][1].phenotype
    kinds = tuple(kind for kind in DATASETS if kind != "test")
    summary = build(pack.motions, pack.actor_hip_height, tmp_path / "again", TINY,
                    show_progress=False, datasets=kinds, bodies=pack.bodies)
    assert summary["bodies"] == json.loads((out / "manifest.json").read_text())["bodies"]
    compared = sorted(out.glob("*.npz"))
    assert len(compared) == 2 * len(kinds)
    for path in compared:
        first, second = _load(path), _load(tmp_path / "again" / path.name)
        assert first.keys() == second.keys()
        for key in first:
            assert first[key].tobytes() == second[key].tobytes(), (path.name, key)


def test_build_command_from_a_pack_and_its_refusals(built, cache, tmp_path, capsys):
    from training.data.__main__ import main
    _tiny_pack(built, cache, tmp_path / "pack.npz")
    common = ["build", "--pack", str(tmp_path / "pack.npz"), "--bodies", "2", "--frames", "12",
              "--points", "64", "--seed", "3"]
    main(common + ["--out", str(tmp_path / "out"), "--only", "skr"])
    np.testing.assert_array_equal(_load(tmp_path / "out" / "skr_train.npz")["points"],
                                  _load(built[0] / "skr_train.npz")["points"])
    for extra, message in (
            (["--only", "test"], "holds no test split; build it with --cmu"),
            (["--include-broken"], "was packed without the broken captures"),
            (["--keep-broken-ankles"], "was packed without the broken feet"),
            (["--bodies", "3"], "--bodies 3: the build needs 3 train bodies, given 2 by "
                                ".*pack.npz")):
        with pytest.raises(SystemExit, match=message):
            main(common + ["--out", str(tmp_path / "refused")] + extra)
    assert not (tmp_path / "refused").exists()
    truncated = (tmp_path / "pack.npz").read_bytes()[:1000]
    (tmp_path / "truncated.npz").write_bytes(truncated)
    with pytest.raises(SystemExit, match="truncated.npz: not a readable .npz"):
        main(["build", "--pack", str(tmp_path / "truncated.npz"), "--out", str(tmp_path / "x")])
    np.savez(tmp_path / "other.npz", points=np.zeros(3))
    with pytest.raises(SystemExit, match=r"other.npz: not a data pack, missing \['actor_hip"):
        main(["build", "--pack", str(tmp_path / "other.npz"), "--out", str(tmp_path / "x")])


def test_a_pack_from_before_the_ankle_check_counts_as_keeping_broken_feet(built, cache,
                                                                           tmp_path):
    from training.data.pack import load_pack, without_broken_ankles, write_pack
    _tiny_pack(built, cache, tmp_path / "pack.npz")
    with np.load(tmp_path / "pack.npz", allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files if key != "keep_broken_ankles"}
    write_pack(tmp_path / "old.npz", arrays)
    assert load_pack(tmp_path / "old.npz").keep_broken_ankles
    assert not load_pack(tmp_path / "pack.npz").keep_broken_ankles
    # such a pack is cut when used, as a build from the CMU folder cuts: train_a (frames 0-49)
    # broken at frame 45 keeps its frames 0-44; 46-49 are too few to keep
    arrays["motion_rotations"][45, JOINT_INDEX["right_ankle"]] = [np.cos(1.4), 0, np.sin(1.4), 0]
    write_pack(tmp_path / "broken.npz", arrays)
    cut = without_broken_ankles(load_pack(tmp_path / "broken.npz"))
    assert not cut.keep_broken_ankles
    assert [(m.name, len(m.rotations)) for m in cut.motions["train"]] == [
        ("train_a@0", 45), ("train_b", 40)]
    np.testing.assert_array_equal(cut.motions["train"][0].rotations,
                                  arrays["motion_rotations"][:45])


def test_a_pack_holds_one_mesh_topology(built, cache):
    from training.data.pack import pack_arrays
    _, summary = built
    first, second = (_body(summary, "train", i, cache) for i in range(2))
    other = dataclasses.replace(second, weights=np.roll(second.weights, 1, axis=1))
    with pytest.raises(ValueError, match=f"body {second.name} has other faces or skinning "
                                         f"weights than {first.name}"):
        pack_arrays(MOTIONS, ACTOR_HIP_HEIGHT, {"train": [first, other], "val": [first]}, False)
    with pytest.raises(ValueError, match=r"no \['val bodies'\]"):
        pack_arrays(MOTIONS, ACTOR_HIP_HEIGHT, {"train": [first], "val": []}, False)
    broken = {**MOTIONS, "train": MOTIONS["train"] + [_walk("07_12", 30)]}
    with pytest.raises(ValueError, match=r"broken captures \['07_12'\].*include_broken=True"):
        pack_arrays(broken, ACTOR_HIP_HEIGHT, {"train": [first], "val": [first]}, False)


@pytest.mark.parametrize("option, value, message", [
    ("--crossed-fraction", "3", "must be in [0, 1], got 3"),
    ("--seated-fraction", "-0.5", "must be in [0, 1], got -0.5"),
    ("--clip-frames", "1", "must be at least 2, got 1"),
    ("--bodies", "0", "must be at least 1, got 0"),
    ("--skin-points", "0", "must be at least 1, got 0"),
    ("--seed", "-1", "must be at least 0, got -1"),
    ("--frames", "many", "not an integer: 'many'")])
def test_build_options_are_checked_by_name(option, value, message, tmp_path, capsys):
    from training.data.__main__ import main
    with pytest.raises(SystemExit):
        main(["build", "--cmu", str(tmp_path), "--out", str(tmp_path / "x"), option, value])
    assert f"argument {option}: {message}" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
