"""Foot contacts (minretarget.contacts): the kernel against its NumPy twin, the IK by hand, what
planting does to a walk, switching off, and its place in the stream."""
import numpy as np
import pytest
import twins

from minretarget.contacts import FeetState, FootLock, check_foot_lock, plant_feet
from minretarget.conventions import JOINT_INDEX, NUM_JOINTS
from minretarget.kinematics import forward_kinematics, quaternion_multiply
from minretarget.retargeter import Retargeter
from minretarget.pipeline import PipelineConfig

LEG_JOINTS = [JOINT_INDEX[f"{side}_{name}"] for side in ("left", "right")
              for name in ("hip", "knee", "ankle")]
TOES = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]


def human_tpose():
    """(J, 3) a plausible adult T-pose, metres, facing +Z, left hand to +X, feet on y = 0."""
    place = {"pelvis": (0, 0.95, 0), "left_hip": (0.09, 0.87, 0), "right_hip": (-0.09, 0.87, 0),
             "spine1": (0, 1.05, 0), "left_knee": (0.10, 0.50, 0.01),
             "right_knee": (-0.10, 0.50, 0.01), "spine2": (0, 1.18, 0),
             "left_ankle": (0.10, 0.08, -0.02), "right_ankle": (-0.10, 0.08, -0.02),
             "spine3": (0, 1.25, 0), "left_foot": (0.11, 0.02, 0.11),
             "right_foot": (-0.11, 0.02, 0.11), "neck": (0, 1.48, 0),
             "left_collar": (0.08, 1.40, 0), "right_collar": (-0.08, 1.40, 0),
             "head": (0, 1.60, 0.02), "left_shoulder": (0.18, 1.42, 0),
             "right_shoulder": (-0.18, 1.42, 0), "left_elbow": (0.45, 1.42, 0),
             "right_elbow": (-0.45, 1.42, 0), "left_wrist": (0.70, 1.42, 0),
             "right_wrist": (-0.70, 1.42, 0)}
    return np.array([place[name] for name in JOINT_INDEX], np.float32)


def turn_about_x(degrees):
    half = np.radians(degrees) / 2
    return np.array([np.cos(half), np.sin(half), 0, 0], np.float32)


def stepping(frames=60, seed=0):
    """(T, J, 4), (T, 3): the left leg stands while jitter (5 mm on the root, half a degree
    on every joint) shakes it; the right leg swings fast back and forth, lifted."""
    rng = np.random.default_rng(seed)
    rotations = np.zeros((frames, NUM_JOINTS, 4), np.float32)
    rotations[..., 0] = 1
    rotations[..., 1:] = rng.normal(0, 0.004, (frames, NUM_JOINTS, 3))
    rotations /= np.linalg.norm(rotations, axis=-1, keepdims=True)
    swing = 20 * np.sin(np.arange(frames) * 2 * np.pi / 12)              # degrees, 2.5 Hz
    right_hip, right_knee = JOINT_INDEX["right_hip"], JOINT_INDEX["right_knee"]
    # The standing knee a little bent (slack for the IK: a straight leg cannot reach higher).
    for name, degrees in (("left_hip", -15), ("left_knee", 30), ("left_ankle", -15)):
        rotations[:, JOINT_INDEX[name]] = turn_about_x(degrees)
    for t in range(frames):
        rotations[t, right_hip] = turn_about_x(-60 + swing[t])          # thigh forward, up
        rotations[t, right_knee] = turn_about_x(90)                      # knee bent
    root = np.array([0, 0.95, 0], np.float32) + rng.normal(0, 0.005, (frames, 3))
    return rotations, root.astype(np.float32)


def run_lock(rotations, root, tpose, lock=FootLock(), state=None):
    out, planted = [], []
    for t in range(len(rotations)):
        new, state = plant_feet(rotations[t], root[t], tpose, state, lock)
        out.append(new)
        planted.append(state.feet_planted)
    return np.stack(out), np.stack(planted), state


def feet_state(**fields):
    """A FeetState of zeros (no foot planted), with ``fields`` set."""
    feet = np.zeros((2, 3), np.float32)
    return FeetState(feet, feet, feet, np.zeros(2, bool))._replace(**fields)


def toes_of(rotations, root, tpose):
    return forward_kinematics(rotations, root, tpose)[0][:, TOES]


def test_kernel_matches_the_twin():
    tpose = human_tpose()
    rotations, root = stepping()
    for lock in (FootLock(), FootLock(0.3, 0.6, 4.0, 0.02, 0.05, 0.8, 0.1)):
        out, planted, _ = run_lock(rotations, root, tpose, lock)
        twin, twin_planted = twins.plant_feet(rotations, root, tpose, lock)
        np.testing.assert_array_equal(planted, twin_planted)
        # Quaternions q and -q are one rotation: compare the poses they make.
        np.testing.assert_allclose(forward_kinematics(out, root, tpose)[0],
                                   twins_fk(twin, root, tpose), atol=2e-5)


def test_a_foot_that_lifts_and_plants_again_does_not_jump():
    """The standing foot kicks for two frames (its toe faster than the lift speed), then
    stands again while its offset is still easing back: it plants with that offset, so the
    toe goes on from where it was shown; the kernel and the twin agree all along."""
    tpose = human_tpose()
    rotations, root = stepping()
    hip = JOINT_INDEX["left_hip"]
    for t in (30, 31):
        rotations[t, hip] = quaternion_multiply(turn_about_x(-40), rotations[t, hip])
    lock = FootLock(max_offset=0.03, release_decay=0.8, anchor_follow=0.0)
    out, planted, _ = run_lock(rotations, root, tpose, lock)
    replant = 30 + int(np.argmax(planted[30:, 0]))
    assert planted[29, 0] and not planted[30, 0] and replant > 31       # lifted, then back
    offset = toes_of(out, root, tpose)[:, 0] - toes_of(rotations, root, tpose)[:, 0]
    before = np.linalg.norm(offset[replant - 1])
    assert before > 0.003                                # still easing back when it plants
    assert np.linalg.norm(offset[replant] - offset[replant - 1]) < 0.1 * before
    twin, twin_planted = twins.plant_feet(rotations, root, tpose, lock)
    np.testing.assert_array_equal(planted, twin_planted)
    np.testing.assert_allclose(forward_kinematics(out, root, tpose)[0],
                               twins_fk(twin, root, tpose), atol=2e-5)


def twins_fk(rotations, root, tpose):
    return np.stack([twins.forward_kinematics(r, p, tpose)[0] for r, p in zip(rotations, root)])


def test_a_standing_foot_stays_put_and_a_swinging_one_is_left_alone():
    tpose = human_tpose()
    rotations, root = stepping()
    # A 5 cm leash: longer than SMRM's toe drifts here, so the anchor stays where it planted.
    out, planted, _ = run_lock(rotations, root, tpose, FootLock(max_offset=0.05,
                                                                anchor_follow=0.0))
    assert planted[5:, 0].all()                 # the standing (left) foot, once speed is known
    assert not planted[:, 1].any()              # the swinging right foot, fast and lifted
    before, after = toes_of(rotations, root, tpose), toes_of(out, root, tpose)
    # Planted, anchor fixed: the left toe does not move over the ground at all (SMRM's moved
    # 1.7 cm a frame on average), and its height is SMRM's: the lock holds a foot on the
    # ground, not up.
    assert np.abs(np.diff(after[5:, 0][:, [0, 2]], axis=0)).max() < 1e-4
    np.testing.assert_allclose(after[:, 0, 1], before[:, 0, 1], atol=1e-5)
    assert np.abs(np.diff(before[5:, 0, 1])).max() > 0.002   # SMRM's toe height did move
    step_before = np.linalg.norm(np.diff(before[5:, 0][:, [0, 2]], axis=0), axis=-1).mean()
    assert step_before > 0.005
    # With the defaults the toe is dragged on the 1 cm leash: it moves, much less than SMRM's.
    def mean_step(lock):
        out, _, _ = run_lock(rotations, root, tpose, lock)
        return np.linalg.norm(np.diff(toes_of(out, root, tpose)[5:, 0][:, [0, 2]], axis=0),
                              axis=-1).mean()
    assert 0 < mean_step(FootLock()) < 0.5 * step_before
    # And on a leash long enough not to pull, the anchor's creep alone moves the toe.
    assert mean_step(FootLock(max_offset=0.05, anchor_follow=0.05)) > 1e-4
    # Only the legs' hip, knee and ankle rotations change; they stay unit quaternions.
    others = [j for j in range(NUM_JOINTS) if j not in LEG_JOINTS]
    np.testing.assert_array_equal(out[:, others], rotations[:, others])
    np.testing.assert_array_equal(out[:, LEG_JOINTS[3:]], rotations[:, LEG_JOINTS[3:]])
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1, atol=1e-6)


@pytest.mark.parametrize("rest_knee", [(0.09, 0.50, 0.0), (0.13, 0.50, 0.0),
                                       (0.10, 0.50, 0.01)])
def test_ik_by_hand_the_knee_flexes_forward_about_its_hinge(rest_knee):
    """Identity pose, a vertical release offset set by hand (the lock itself makes only
    horizontal ones; a rise is what makes the knee flex), the left ankle's goal 10 cm above
    it: the ankle rises 10 cm, the foot keeps its orientation
    (toe - ankle unchanged), the right leg is untouched, and the knee goes forward (+Z), not
    sideways: for an exactly straight leg (no bend plane at all), a knee kinked 4 cm sideways
    at rest (its bend plane is the wrong one) and a slightly bent one."""
    tpose = human_tpose()
    knee, ankle, toe = (JOINT_INDEX[f"left_{name}"] for name in ("knee", "ankle", "foot"))
    tpose[knee] = rest_knee
    tpose[ankle] = (0.09, 0.08, 0.0)
    tpose[toe] = tpose[ankle] + (0.01, -0.06, 0.13)
    identity = np.zeros((NUM_JOINTS, 4), np.float32)
    identity[:, 0] = 1
    root = tpose[0]
    # Lifted (no foot plants: their filtered tracks were a metre off, so they move fast), the
    # left offset eases back by half.
    state = feet_state(toe_filtered=tpose[TOES] + 1.0,
                       foot_offset=np.array([[0, 0.2, 0], [0, 0, 0]], np.float32))
    out, state = plant_feet(identity, root, tpose, state, FootLock(release_decay=0.5))
    assert not state.feet_planted.any()
    joints = forward_kinematics(out, root, tpose)[0]
    np.testing.assert_allclose(joints[ankle], tpose[ankle] + [0, 0.1, 0], atol=1e-5)
    np.testing.assert_allclose(joints[toe] - joints[ankle], tpose[toe] - tpose[ankle], atol=1e-5)
    moved = joints[knee] - tpose[knee]
    assert moved[2] > 0.1 and abs(moved[0]) < 0.01, moved
    np.testing.assert_array_equal(out[LEG_JOINTS[3:]], identity[LEG_JOINTS[3:]])   # right leg


def test_lifting_eases_back_by_the_decay():
    tpose = human_tpose()
    rotations, root = stepping(30)
    lock = FootLock()
    out, planted, state = run_lock(rotations[:20], root[:20], tpose, lock)
    assert state.feet_planted[0] and np.linalg.norm(state.foot_offset[0]) > 1e-3
    offset = state.foot_offset[0].copy()
    restless = FootLock(plant_speed=1e-6, lift_speed=1e-6, release_decay=0.6)  # every toe lifts
    for t in range(20, 24):                   # no foot plants: the offsets shrink
        new, state = plant_feet(rotations[t], root[t], tpose, state, restless)
        assert not state.feet_planted.any()
        offset = restless.release_decay * offset
        np.testing.assert_allclose(state.foot_offset[0], offset, atol=1e-6)
    # And once the offsets are gone, a lifted foot leaves SMRM's rotations exactly as they were.
    state = state._replace(foot_offset=np.zeros((2, 3), np.float32))
    new, _ = plant_feet(rotations[25], root[25], tpose, state, restless)
    np.testing.assert_array_equal(new, rotations[25])


@pytest.mark.parametrize("bad", [
    (0, 2, 12, 0.05, 0.2, 0.5, 0.1), (3, 2, 12, 0.05, 0.2, 0.5, 0.1),
    (2, 2, 12, 0.05, 0.2, 1.0, 0.1), (2, 2, np.inf, 0.05, 0.2, 0.5, 0.1),
    (2, 2, 12, 0.05, 0.2, 0.5, -0.1), (2, 2, 12, "x", 0.2, 0.5, 0.1),
    (2, 2, 12, 0.05, 0.2, 0.5), (1.0,), "fast"])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError, match="foot_lock"):
        check_foot_lock(bad)


def test_the_retargeter_plants_feet_and_resumes_exactly(tiny_weights, tiny_stream):
    """In the stream: with the lock off the rotations are SMRM's alone; a state saved mid-way
    and set on another retargeter continues with the same frames, foot contacts included."""
    target, frames, _ = tiny_stream
    plain = Retargeter(tiny_weights, PipelineConfig(foot_lock=None), warn=False)
    locked = Retargeter(tiny_weights, PipelineConfig(foot_lock=FootLock(5.0, 5.0, 12.0, 1.0,
                                                                     1.0, 0.5)), warn=False)
    for retargeter in (plain, locked):
        retargeter.set_target(target)
    plain_frames = [plain.step(points) for points in frames]
    locked_frames = [locked.step(points) for points in frames]
    feet = locked.state.stages["foot_lock"]
    assert any(feet.feet_planted) or np.abs(feet.foot_offset).max() > 0
    # FK runs once, before the lock, which places the legs it bends again: the frame's joints
    # and vertices are those of FK and LBS on its final rotations.
    for frame in locked_frames:
        vertices, joints = locked.pose(frame.rotations, frame.root)
        np.testing.assert_allclose(frame.joints, joints, atol=1e-6)
        np.testing.assert_allclose(frame.vertices, vertices, atol=1e-6)
    assert max(np.abs(a.rotations - b.rotations).max()
               for a, b in zip(plain_frames, locked_frames)) > 1e-4
    # Resume from the middle.
    middle = len(frames) // 2
    locked.reset()
    for points in frames[:middle]:
        locked.step(points)
    other = Retargeter(tiny_weights, PipelineConfig(foot_lock=locked.config.foot_lock), warn=False)
    other.set_target(target)
    other.state = locked.state
    for points, expected in zip(frames[middle:], locked_frames[middle:]):
        np.testing.assert_array_equal(other.step(points).vertices, expected.vertices)


def test_bad_state_is_refused_naming_the_field():
    tpose = human_tpose()
    rotations, root = stepping(2)
    state = feet_state()
    for field, value in (("toe_anchor", np.zeros((3, 3))), ("foot_offset", np.full((2, 3), np.nan)),
                         ("feet_planted", np.zeros(2))):
        with pytest.raises(ValueError, match=f"foot_lock.{field}"):
            plant_feet(rotations[0], root[0], tpose, state._replace(**{field: value}))
    with pytest.raises(ValueError, match="FeetState"):
        plant_feet(rotations[0], root[0], tpose, tuple(state))
    with pytest.raises(ValueError, match="needs a FootLock"):
        plant_feet(rotations[0], root[0], tpose, state, None)
