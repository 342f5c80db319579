"""CMU skeleton -> 22 canonical joints: the mapping, the trial list, and one real file."""
import gzip
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import CMU_DIR, needs_cmu
from minretarget.bvh import parse_bvh, read_bvh, resample, world_transforms
from minretarget.conventions import JOINT_INDEX
from minretarget.kinematics import forward_kinematics
from minretarget.skeletons import CMU_BONES, canonical_world
from training.data.cmu import (ANKLE_LIMIT_DEGREES, BROKEN_FLOOR_HEIGHT, BROKEN_TRIALS,
                               LEAD_IN_FRAMES, MIN_SEGMENT_FRAMES, Motion, Trial,
                               broken_ankle_frames, capture_fps, clean_segments,
                               cmu_tpose_joints, floor_height, list_trials, load_motion,
                               local_quaternions, tpose_joints)

WALK = CMU_DIR / "cgspeed" / "02" / "02_01.bvh.gz"

# A small skeleton with the CMU (Daz) joint names, offsets in centimetres like the real one,
# and an eye and a thumb that the mapping must ignore. (name, offset, children, end site)
LEFT_ARM = ("lCollar", (3, 19, -5), [("lShldr", (9, -2, 1), [("lForeArm", (28, -2, 0), [
    ("lHand", (22, 1, 7), [("lThumb1", (1, 0, 3), [], (2, 0, 2))], None)], None)], None)], None)
LEFT_LEG = ("lButtock", (9, 4, 1), [("lThigh", (0, -2, -2), [("lShin", (0, -37, 1), [
    ("lFoot", (-1, -45, -5), [], (1, -4, 12))], None)], None)], None)


def mirror(joint):
    name, offset, children, end = joint
    flip = (lambda v: None if v is None else (-v[0],) + tuple(v[1:]))
    return ("r" + name[1:], flip(offset), [mirror(c) for c in children], flip(end))


SKELETON = ("hip", (0, 0, 0), [
    ("abdomen", (0, 20, -1), [("chest", (0, 12, 0), [
        ("neck", (0, 22, -2), [("head", (0, 7, 1), [("leftEye", (4, 8, 8), [], (1, 0, 0))],
                                None)], None),
        mirror(LEFT_ARM), LEFT_ARM], None)], None),
    mirror(LEFT_LEG), LEFT_LEG], None)


def hierarchy(joint, root=True):
    name, offset, children, end = joint
    channels = ("CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation" if root
                else "CHANNELS 3 Zrotation Xrotation Yrotation")
    lines = [("ROOT " if root else "JOINT ") + name, "{", "OFFSET %g %g %g" % offset, channels]
    for child in children:
        lines += hierarchy(child, root=False)
    if end is not None:
        lines += ["End Site", "{", "OFFSET %g %g %g" % end, "}"]
    return lines + ["}"]


def synthetic_bvh_text(frames=9, seed=0):
    """Random poses (buttocks fixed, as in the CMU files); frame 0 is the zero pose."""
    header = ["HIERARCHY"] + hierarchy(SKELETON)
    names = [line.split()[1] for line in header if line.startswith(("ROOT", "JOINT"))]
    rng = np.random.default_rng(seed)
    values = rng.uniform(-60, 60, (frames, 3 + 3 * len(names)))
    values[:, :3] = rng.uniform(-100, 100, (frames, 3))
    for name in ("lButtock", "rButtock"):
        start = 3 + 3 * names.index(name)
        values[:, start:start + 3] = 0
    values[0] = 0
    lines = header + ["MOTION", f"Frames: {frames}", "Frame Time: 0.0083333"]
    return "\n".join(lines + [" ".join(f"{v:.6f}" for v in row) for row in values]) + "\n"


@pytest.fixture(scope="module")
def synthetic():
    return parse_bvh(synthetic_bvh_text(), scale=0.01)


def mapped_bvh_positions(bvh):
    """(T, J', 3) BVH world positions of the canonical joints that have a CMU joint, and J'."""
    positions, _ = world_transforms(bvh)
    mapped = [(JOINT_INDEX[name], bvh.names.index(bone)) for name, bone in CMU_BONES.items()
              if bone is not None]
    return positions[:, [b for _, b in mapped]], [j for j, _ in mapped]


def fk_of_mapping(bvh):
    positions, rotations = canonical_world(bvh)
    joints, _ = forward_kinematics(local_quaternions(rotations), positions[:, 0],
                                   tpose_joints(bvh))
    return joints


# ----------------------------------------------------------------------------- mapping

def test_zero_pose_maps_to_identity(synthetic):
    zero = replace(synthetic, values=synthetic.values[:1])
    q = local_quaternions(canonical_world(zero)[1])
    np.testing.assert_allclose(q, np.tile([1, 0, 0, 0], (1, 22, 1)), atol=1e-7)


def test_fk_of_mapped_rotations_reproduces_bvh_positions(synthetic):
    joints = fk_of_mapping(synthetic)
    expected, mapped = mapped_bvh_positions(synthetic)
    np.testing.assert_allclose(joints[:, mapped], expected, atol=1e-5)
    # The joints CMU lacks ride rigidly: the ball of the foot is the foot's End Site.
    positions, rotations = world_transforms(synthetic)
    foot = synthetic.names.index("lFoot")
    ball = positions[:, foot] + rotations[:, foot] @ synthetic.end_sites[foot]
    np.testing.assert_allclose(joints[:, JOINT_INDEX["left_foot"]], ball, atol=1e-5)


def test_missing_joints_get_identity_local_rotations(synthetic):
    q = local_quaternions(canonical_world(synthetic)[1])
    for name in ("spine3", "left_foot", "right_foot"):
        np.testing.assert_allclose(q[:, JOINT_INDEX[name]], np.tile([1, 0, 0, 0], (9, 1)),
                                   atol=1e-6)
    assert (q[..., 0] >= 0).all()


def check_tpose_axes(tpose):
    """Canonical T-pose: +Y up, facing +Z (toes ahead of ankles), left hand toward +X."""
    j = JOINT_INDEX
    assert tpose[j["left_wrist"], 0] > 0.4 and tpose[j["right_wrist"], 0] < -0.4
    assert tpose[j["left_hip"], 0] > 0 > tpose[j["right_hip"], 0]
    for side in ("left", "right"):
        assert tpose[j[f"{side}_foot"], 2] > tpose[j[f"{side}_ankle"], 2] + 0.05
    assert tpose[j["head"], 1] > tpose[j["pelvis"], 1] > tpose[j["left_knee"], 1] > 0
    assert abs(min(tpose[j["left_foot"], 1], tpose[j["right_foot"], 1]) - 0.025) < 1e-6


def test_tpose_axes_and_floor(synthetic):
    check_tpose_axes(tpose_joints(synthetic))


def test_floor_height_finds_a_body_sunk_through_the_floor(synthetic):
    """A T-pose standing on the floor has its balls of the feet at 0.025 m; one frame in a
    hundred sunk 0.8 m (a glitch) does not move the 2nd percentile, all of them sunk does."""
    tpose = tpose_joints(synthetic)
    rotations = np.tile(np.array([1, 0, 0, 0], np.float32), (100, len(tpose), 1))
    root = np.tile(tpose[0], (100, 1))
    standing = Motion("t", rotations, root, 30, "walk", 120.0)
    assert floor_height(standing, tpose) == pytest.approx(0.025, abs=1e-5)
    glitch = root.copy()
    glitch[40, 1] -= 0.8
    assert floor_height(replace(standing, root=glitch), tpose) == pytest.approx(0.025, abs=1e-5)
    sunk = floor_height(replace(standing, root=root - [0, 0.8, 0]), tpose)
    assert sunk == pytest.approx(-0.775, abs=1e-5) and sunk < BROKEN_FLOOR_HEIGHT


def test_load_motion_drops_the_lead_in_and_resamples(tmp_path):
    path = tmp_path / "mine.bvh"
    path.write_text(synthetic_bvh_text(frames=LEAD_IN_FRAMES + 9))
    bvh = parse_bvh(path.read_text(), scale=0.01)
    motion = load_motion(path)                   # not in the collection: the header's 120 fps
    assert motion.name == "mine" and motion.fps == 30 and motion.source_fps == 120
    assert motion.rotations.shape == (3, 22, 4) and motion.rotations.dtype == np.float32
    assert motion.root.shape == (3, 3) and motion.root.dtype == np.float32
    kept = replace(bvh, values=bvh.values[LEAD_IN_FRAMES::4])          # 3 of the 9 frames
    positions, rotations = canonical_world(kept)
    np.testing.assert_allclose(motion.root, positions[:, 0], atol=1e-6)
    np.testing.assert_allclose(motion.rotations, local_quaternions(rotations), atol=1e-6)
    assert load_motion(path, source_fps=60).rotations.shape[0] == 5   # every other frame


# ----------------------------------------------------------------------------- the collection

def test_list_trials_names_categories_and_splits(tmp_path):
    for rel in ("cgspeed/08/08_01.bvh.gz", "cgspeed/02/02_03.bvh.gz", "cgspeed/05/05_02.bvh.gz",
                "cgspeed/13/13_07.bvh.gz", "aclstm/indian/04.bvh.gz", "aclstm/salsa/01.bvh.gz"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(gzip.compress(b""))
    (tmp_path / "cgspeed" / "CMU-INDEX.md").write_text(
        "Subject #2 (various)\n\n02_03  run/jog\n\n05_02  dance - expressive arms\n\n"
        "08_01  walk\r\n\n13_07  unscrew bottlecap, drink soda\n")
    trials = {t.name: t for t in list_trials(tmp_path)}
    assert sorted(trials) == ["02_03", "05_02", "08_01", "13_07", "indian_04", "salsa_01"]
    assert {n: t.category for n, t in trials.items()} == {
        "02_03": "run", "05_02": "dance", "08_01": "walk", "13_07": "everyday",
        "indian_04": "indian", "salsa_01": "salsa"}
    assert {n for n, t in trials.items() if t.split == "test"} == {"08_01", "indian_04"}
    assert trials["08_01"].subject == "08" and trials["salsa_01"].subject == "salsa"
    assert capture_fps(trials["salsa_01"].path) == 60
    assert capture_fps(trials["indian_04"].path) == capture_fps(trials["02_03"].path) == 120
    assert capture_fps(tmp_path / "elsewhere.bvh") is None


def test_list_trials_leaves_out_broken_captures_unless_asked(tmp_path):
    for rel in ("cgspeed/09/09_10.bvh.gz", "cgspeed/09/09_11.bvh.gz", "cgspeed/07/07_12.bvh.gz"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(gzip.compress(b""))
    (tmp_path / "cgspeed" / "CMU-INDEX.md").write_text("09_10  run\n09_11  run\n07_12  walk\n")
    assert [t.name for t in list_trials(tmp_path)] == ["09_11"]
    assert [t.name for t in list_trials(tmp_path, include_broken=True)] == [
        "07_12", "09_10", "09_11"]


def _turned_ankles(degrees, joint="left_ankle"):
    """(T, J, 4) identity rotations but ``joint``'s, turned by each of ``degrees`` about an
    axis that is neither the foot's length nor across it."""
    axis = np.array([0.6, 0.0, 0.8])
    half = np.radians(np.asarray(degrees, dtype=np.float64)) / 2
    rotations = np.zeros((len(half), 22, 4), np.float32)
    rotations[..., 0] = 1
    rotations[:, JOINT_INDEX[joint], 0] = np.cos(half)
    rotations[:, JOINT_INDEX[joint], 1:] = np.sin(half)[:, None] * axis
    return rotations


def test_broken_ankle_frames_are_those_turned_past_the_limit_on_either_side():
    limit = ANKLE_LIMIT_DEGREES
    for joint in ("left_ankle", "right_ankle"):
        turned = _turned_ankles([0, 45, limit - 1, limit + 1, 179, -(limit + 1)], joint)
        assert broken_ankle_frames(turned).tolist() == [False, False, False, True, True, True]
    # the same rotation with q and -q (w < 0): an angle, not a sign
    flipped = -_turned_ankles([limit + 1, 30])
    assert broken_ankle_frames(flipped).tolist() == [True, False]
    # other joints may turn as far as they like
    assert not broken_ankle_frames(_turned_ankles([170, 179], "left_knee")).any()


def test_clean_segments_cut_the_broken_frames_and_the_short_runs_between_them():
    degrees = np.zeros(160)
    degrees[40:45] = degrees[60] = degrees[100] = 170   # clean runs 0-39, 45-59, 61-99, 101-159
    rotations = _turned_ankles(degrees, "right_ankle")
    root = np.arange(160 * 3, dtype=np.float32).reshape(160, 3)
    motion = Motion("05_06", rotations, root, 30, "dance", 120.0)
    segments = clean_segments(motion)
    assert 60 - 45 < MIN_SEGMENT_FRAMES <= 100 - 61                # 45-59 is too short
    assert [m.name for m in segments] == ["05_06@0", "05_06@61", "05_06@101"]
    for segment, (start, end) in zip(segments, ((0, 40), (61, 100), (101, 160))):
        np.testing.assert_array_equal(segment.rotations, rotations[start:end])
        np.testing.assert_array_equal(segment.root, root[start:end])
        assert (segment.fps, segment.category, segment.source_fps) == (30, "dance", 120.0)
    whole = Motion("08_01", _turned_ankles(np.full(10, 90.0)), root[:10], 30, "walk", 120.0)
    assert clean_segments(whole)[0] is whole and len(clean_segments(whole)) == 1
    assert clean_segments(replace(motion, rotations=_turned_ankles(np.full(120, 170.0)),
                                  root=root)) == []


def test_the_dance_set_names_the_trials_it_cannot_find(tmp_path):
    from training.data.datasets import dance_sequences
    (tmp_path / "cgspeed" / "05").mkdir(parents=True)
    (tmp_path / "cgspeed" / "05" / "05_02.bvh.gz").write_bytes(gzip.compress(b""))
    (tmp_path / "cgspeed" / "CMU-INDEX.md").write_text("05_02  dance\n")
    with pytest.raises(FileNotFoundError, match=r"dance trials \['05_06', .*'salsa_28'\] "
                                                "not found under"):
        dance_sequences(tmp_path)


# ----------------------------------------------------------------------------- real data

needs_walk = needs_cmu(WALK)


@needs_walk
def test_the_broken_trials_are_the_sunken_ones():
    """Each listed trial sinks through the floor; its neighbours (same subject, same session)
    stand on it."""
    trials = {t.name: t for t in list_trials(CMU_DIR, include_broken=True)}
    tpose = cmu_tpose_joints(WALK)
    for name in sorted(BROKEN_TRIALS) + ["01_08", "07_11", "09_11"]:
        height = floor_height(load_motion(trials[name].path), tpose)
        assert (height < BROKEN_FLOOR_HEIGHT) == (name in BROKEN_TRIALS), (name, height)
        assert name in BROKEN_TRIALS or abs(height) < 0.2, (name, height)


def test_cmu_motions_cut_broken_feet_unless_kept(monkeypatch):
    """cmu_motions hands every split's motions through clean_segments, or whole if asked."""
    from training.data import datasets
    broken = np.zeros(100)
    broken[40] = 170
    fake = {"salsa_99": (_turned_ankles(broken), "train"), "08_99": (_turned_ankles([0] * 50),
                                                                      "test")}
    trials = [Trial(name, Path(f"{name}.bvh.gz"), name[:2], "walk", split)
              for name, (_, split) in fake.items()]
    monkeypatch.setattr(datasets, "list_trials", lambda cmu_dir, include_broken: trials)
    monkeypatch.setattr(datasets, "cmu_tpose_joints", lambda path: np.ones((22, 3)))
    monkeypatch.setattr(datasets, "load_motion", lambda path, fps: Motion(
        Path(path).name[:-7], fake[Path(path).name[:-7]][0],
        np.zeros((len(fake[Path(path).name[:-7]][0]), 3), np.float32), fps, "walk", 120.0))
    cut, _ = datasets.cmu_motions("cmu", show_progress=False)
    assert [(m.name, len(m.rotations)) for m in cut["train"]] == [("salsa_99@0", 40),
                                                                   ("salsa_99@41", 59)]
    assert [m.name for m in cut["test"]] == ["08_99"]
    kept, _ = datasets.cmu_motions("cmu", show_progress=False, keep_broken_ankles=True)
    assert [(m.name, len(m.rotations)) for m in kept["train"]] == [("salsa_99", 100)]


@needs_walk
def test_broken_feet_are_where_measured_and_not_in_the_test_split():
    """The measured 05_06 and salsa_01 runs (docs/training_notes.md, "Broken feet in the
    training dances"); no test trial has a broken foot, so the test data is as it was."""
    trials = list_trials(CMU_DIR)
    by_name = {t.name: t for t in trials}
    salsa = np.flatnonzero(broken_ankle_frames(load_motion(by_name["salsa_01"].path).rotations))
    assert (salsa.min(), salsa.max(), len(salsa)) == (356, 448, 93)
    assert broken_ankle_frames(load_motion(by_name["05_06"].path).rotations).sum() == 179
    for trial in (t for t in trials if t.split == "test"):
        assert not broken_ankle_frames(load_motion(trial.path).rotations).any(), trial.name


@needs_walk
def test_the_dance_set_keeps_each_trials_longest_run_without_broken_feet():
    from training.data.datasets import dance_sequences
    held_out = {sequence.trial.name: sequence for sequence in dance_sequences(CMU_DIR)}
    assert (held_out["05_06"].name, held_out["05_06"].frames) == ("05_06@0", 31)
    sequence = held_out["05_06"].build()      # 179 of frames 31-219 past the limit
    assert str(sequence["name"]) == "05_06@0" and len(sequence["source_points"]) == 31
    assert not broken_ankle_frames(sequence["rotations"]).any()
    assert (held_out["05_02"].name, held_out["05_02"].frames) == ("05_02", 279)   # whole


@needs_walk
def test_validation_skips_the_broken_trials_and_keeps_the_others_bodies_and_seeds():
    """Each validation trial keeps its place k in the draw over every trial (its bodies and
    seed: the benchmark figures stored since depend on it); place 9 was the broken 09_10's."""
    from training.data.datasets import validation_sequences
    drawn = {sequence.build.args[1]: sequence.trial.name
             for sequence in validation_sequences(CMU_DIR)}
    assert drawn == {0: "09_06", 1: "06_05", 2: "06_11", 3: "06_12", 4: "09_12", 5: "06_03",
                     6: "09_11", 7: "06_07", 8: "09_03", 10: "06_04", 11: "09_08",
                     12: "06_09"}


@needs_walk
def test_the_dance_set_is_training_motion_on_validation_bodies():
    from training.data.datasets import DANCE_TRIALS, VALIDATION_SUBJECTS, dance_sequences
    held_out = dance_sequences(CMU_DIR)
    assert [sequence.trial.name for sequence in held_out] == list(DANCE_TRIALS)
    assert [sequence.build.args[1] for sequence in held_out] == list(range(len(DANCE_TRIALS)))
    assert sum(sequence.frames for sequence in held_out) == 6954
    for trial in (sequence.trial for sequence in held_out):
        assert trial.split == "train" and trial.subject not in VALIDATION_SUBJECTS
        assert trial.category in ("dance", "salsa", "martial") and trial.name not in BROKEN_TRIALS


@needs_walk
def test_the_motion_set_is_every_other_training_category_on_validation_bodies():
    from training.data.datasets import (DANCE_TRIALS, MOTION_CATEGORIES_LEFT_OUT,
                                        VALIDATION_SUBJECTS, motion_sequences)
    held_out = motion_sequences(CMU_DIR)
    trials = [sequence.trial for sequence in held_out]
    assert [sequence.build.args[1] for sequence in held_out] == list(range(len(trials)))
    assert (len(trials), sum(sequence.frames for sequence in held_out)) == (28, 4883)
    assert [t.name for t in trials] == [s.trial.name for s in motion_sequences(CMU_DIR)]
    counts = {}
    for trial in trials:
        assert trial.split == "train" and trial.subject not in VALIDATION_SUBJECTS
        assert trial.category not in MOTION_CATEGORIES_LEFT_OUT and trial.name not in BROKEN_TRIALS
        assert trial.name not in DANCE_TRIALS
        counts[trial.category] = counts.get(trial.category, 0) + 1
    assert max(counts.values()) == 4 and {"walk", "sit", "climb", "jump"} <= set(counts)
    assert len({t.name for t in trials}) == len(trials)


@needs_walk
def test_the_more_dances_set_is_every_other_training_dance_on_validation_bodies():
    from training.data.cmu import list_trials
    from training.data.datasets import DANCE_TRIALS, VALIDATION_SUBJECTS, more_dance_sequences
    held_out = more_dance_sequences(CMU_DIR)
    names = {sequence.trial.name for sequence in held_out}
    assert (len(held_out), sum(sequence.frames for sequence in held_out)) == (39, 8267)
    assert [sequence.build.args[1] for sequence in held_out] == list(range(len(held_out)))
    assert max(sequence.frames for sequence in held_out) == 240
    # every training dance trial is in exactly one of the two dance sets
    dances = {t.name for t in list_trials(CMU_DIR) if t.split == "train"
              and t.subject not in VALIDATION_SUBJECTS and t.category in ("dance", "salsa",
                                                                          "martial")}
    assert names | set(DANCE_TRIALS) == dances and not names & set(DANCE_TRIALS)
    assert not names & BROKEN_TRIALS and len(names) == len(held_out)


@needs_walk
def test_real_walk_maps_exactly_and_walks_forward():
    motion = load_motion(WALK)
    assert motion.category == "walk" and motion.source_fps == 120
    bvh = read_bvh(WALK, scale=0.01)
    check_tpose_axes(tpose_joints(bvh))
    np.testing.assert_array_equal(tpose_joints(bvh), cmu_tpose_joints(WALK))
    bvh = resample(replace(bvh, values=bvh.values[LEAD_IN_FRAMES:]), fps=30, source_fps=120)
    joints, rotations = forward_kinematics(motion.rotations, motion.root, cmu_tpose_joints(WALK))
    expected, mapped = mapped_bvh_positions(bvh)
    assert np.abs(joints[:, mapped] - expected).max() < 1e-3                 # metres
    # The actor walks the way the pelvis faces, feet near the floor.
    velocity = np.diff(motion.root[:, [0, 2]], axis=0)
    facing = rotations[:-1, 0][:, [0, 2], 2]                     # pelvis +Z, horizontal part
    cosine = np.sum(velocity * facing, axis=1) / np.linalg.norm(velocity, axis=1) \
        / np.linalg.norm(facing, axis=1)
    assert np.median(cosine) > 0.9
    feet = joints[:, [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]], 1]
    assert feet.min(axis=1).max() < 0.15 and feet.min() > -0.02
