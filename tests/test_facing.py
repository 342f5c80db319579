"""The facing check (minretarget.facing) on hand-made skeletons, and in the Retargeter."""
import numpy as np
import pytest

from conftest import facing
from minretarget.conventions import NUM_JOINTS
from minretarget.facing import CONFIRM, TRIGGER, check_facing, half_turned
from minretarget.heading import heading_angles, heading_features, wrapped
from minretarget.pipeline import PipelineConfig
from minretarget.retargeter import Retargeter
from minretarget.stages import Reading


def cloud(*shape, seed=0):
    """Random float32 points of ``shape``, the same every run."""
    return np.random.default_rng(seed).normal(size=shape).astype(np.float32)


def test_heading_angles_are_the_turn_from_plus_z_as_smrm_sees_it():
    angles = np.array([0.0, 0.5, np.pi / 2, -2.0, 3.0])
    skeletons = np.stack([facing(a, seed) for seed, a in enumerate(angles)])
    np.testing.assert_allclose(wrapped(heading_angles(skeletons) - angles), 0.0, atol=1e-6)
    for joints in skeletons:                                 # SMRM's heading, as an angle
        _, sin, cos = heading_features(joints, joints[0])
        assert heading_angles(joints) == pytest.approx(np.arctan2(sin, cos), abs=1e-6)


def test_half_turned_is_a_half_turn_about_the_vertical_through_the_centre():
    points = cloud(50, 3)
    centre = np.array([0.4, 9.0, -1.0], np.float32)
    turned = half_turned(points, centre)
    np.testing.assert_allclose(turned[:, 1], points[:, 1])                 # heights kept
    np.testing.assert_allclose(turned[:, [0, 2]] + points[:, [0, 2]],      # through the centre
                               np.broadcast_to(2 * centre[[0, 2]], (50, 2)), atol=1e-6)
    np.testing.assert_allclose(half_turned(turned, centre), points, atol=1e-6)
    # A proper rotation: its skeleton's heading turns by pi.
    joints = facing(0.3)
    assert abs(wrapped(heading_angles(half_turned(joints, centre)) - 0.3 - np.pi)) < 1e-6


class Finder:
    """A skeleton finder that answers ``answer`` and counts its calls."""
    def __init__(self, answer):
        self.answer, self.clouds = answer, []

    def __call__(self, clouds):
        self.clouds.append(clouds)
        return self.answer[None]


def test_a_reading_facing_near_the_reference_or_with_none_stands():
    points = cloud(200, 3)
    finder = Finder(facing(0.0))
    reading = facing(np.pi)                                   # backwards
    for reference, away_frames in ((np.nan, 0), (np.pi - TRIGGER + 0.01, 3)):
        joints, new_reference, away = check_facing(reading, points, reference, away_frames,
                                                   finder)
        np.testing.assert_array_equal(joints, reading)
        assert (wrapped(new_reference - np.pi), away) == (pytest.approx(0.0, abs=1e-6), 0)
    assert finder.clouds == []                               # no second reading either time


def test_a_reading_facing_away_is_read_again_half_turned():
    points = cloud(200, 3)
    centre = points.mean(axis=0)
    reading = facing(0.2 + np.pi - 0.3)
    # The finder sees the half-turned cloud; its skeleton there faces 0.1 + pi, which turned
    # back faces 0.1: within the trigger of the reference 0.2.
    finder = Finder(facing(0.1 + np.pi, seed=1))
    joints, reference, away = check_facing(reading, points, 0.2, 2, finder)
    [clouds] = finder.clouds
    np.testing.assert_allclose(clouds[0], half_turned(points, centre), atol=1e-6)
    np.testing.assert_allclose(joints, half_turned(finder.answer, centre), atol=1e-6)
    assert (reference, away) == (pytest.approx(0.1, abs=1e-5), 0)


@pytest.mark.parametrize("second_heading, nearer", [(0.2 - 2.0, "second"), (0.2 + 2.9, "first")])
def test_when_both_readings_face_away_the_reference_waits(second_heading, nearer):
    """The nearer reading is used, the reference kept, until CONFIRM frames in a row."""
    points = cloud(200, 3)
    centre = points.mean(axis=0)
    reading = facing(0.2 + 2.5)                              # 2.5 away from the reference 0.2
    finder = Finder(facing(second_heading + np.pi, seed=1))  # turned back: second_heading
    expected = half_turned(finder.answer, centre) if nearer == "second" else reading
    for away_frames in range(CONFIRM):
        joints, reference, away = check_facing(reading, points, 0.2, away_frames, finder)
        np.testing.assert_allclose(joints, expected, atol=1e-6)
        if away_frames + 1 < CONFIRM:
            assert (reference, away) == (0.2, away_frames + 1)
        else:                          # confirmed: the first reading's heading, count reset
            assert (reference, away) == (pytest.approx(0.2 + 2.5, abs=1e-5), 0)


class ScriptedReading(Reading):
    """SKR's stage answering from a script: [(cloud, joints)]; each read appends its
    ``mirrored`` flag to ``calls``."""
    def __init__(self, answers, calls, mirrored):
        self.answers, self.calls, self.mirrored = answers, calls, mirrored

    def read(self, points):
        self.calls.append(self.mirrored)

        def one(cloud):
            [answer] = [a for c, a in self.answers if np.allclose(c, cloud, atol=1e-6)]
            return answer
        return np.stack([one(c) for c in points]) if points.ndim == 3 else one(points)


class ScriptedRetargeter(Retargeter):
    """SKR replaced by a script: ``readings`` (frame t's cloud -> facing(readings[t], seed=t))
    and ``seconds`` (frame t's cloud half turned -> facing(seconds[t] + pi, seed=100 + t),
    which turned back faces seconds[t]); records the mirrored flags it is called with."""
    def __init__(self, weights, clouds, readings, seconds, **options):
        super().__init__(weights, PipelineConfig(smoothing=None, denoise=False, **options),
                         warn=False)
        self.answers = [(c, facing(h, seed=t)) for t, (c, h) in enumerate(zip(clouds, readings))]
        self.answers += [(half_turned(c, c.mean(axis=0)), facing(h + np.pi, seed=100 + t))
                         for t, (c, h) in enumerate(zip(clouds, seconds))]
        self.mirrored = []

    def _reader(self, mirrored):
        return ScriptedReading(self.answers, self.mirrored, mirrored)


def scripted(tiny_weights, target, frames, **options):
    """A ScriptedRetargeter whose frame 0 faces 0 and frames 1.. face pi, their second
    readings pi - 0.5 (both away from 0: the second is nearer), on ``target``."""
    clouds = cloud(frames, 300, 3, seed=1)
    headings = [0.0] + [np.pi] * (frames - 1)
    retargeter = ScriptedRetargeter(tiny_weights, clouds, headings,
                                    [0.0] + [np.pi - 0.5] * (frames - 1), **options)
    retargeter.set_target(target, tpose_joints=facing(0.0),
                          skin_weights=np.full((len(target), NUM_JOINTS), 1 / NUM_JOINTS))
    return retargeter, clouds


@pytest.mark.parametrize("mirror_source", [False, True])
def test_the_reference_waits_confirm_frames_and_resumes_mid_wait(tiny_weights, tiny_stream,
                                                                 mirror_source):
    target, _, _ = tiny_stream
    frames = CONFIRM + 3
    retargeter, clouds = scripted(tiny_weights, target, frames, mirror_source=mirror_source)
    got, states = [], []
    for cloud in clouds:
        got.append(retargeter.step(cloud))
        states.append(retargeter.state)
    # Frames 1 .. CONFIRM: both readings face away; the nearer (second) is used and the
    # reference stays 0, until frame CONFIRM moves it to the first reading's heading (pi).
    # After it the readings face the reference and stand.
    for t in range(1, frames):
        kept = (half_turned(facing(np.pi - 0.5 + np.pi, seed=100 + t), clouds[t].mean(axis=0))
                if t <= CONFIRM else facing(np.pi, seed=t))
        np.testing.assert_allclose(got[t].source_joints, kept, atol=1e-5, err_msg=str(t))
        if t < CONFIRM:
            assert tuple(states[t].stages["facing_check"]) == (0.0, t)
    assert states[CONFIRM].stages["facing_check"].away_frames == 0
    assert abs(wrapped(states[CONFIRM].stages["facing_check"].reference - np.pi)) < 1e-5
    assert set(retargeter.mirrored) == {mirror_source}     # the second readings' finder too
    # Resumed mid-wait on another retargeter: the same frames as the unbroken stream.
    resumed, _ = scripted(tiny_weights, target, frames, mirror_source=mirror_source)
    resumed.state = states[2]
    for t in range(3, frames):
        np.testing.assert_array_equal(resumed.step(clouds[t]).vertices, got[t].vertices)


class FlippingRetargeter(Retargeter):
    """SKR replaced: frame 0's cloud reads as facing 0, frame 1's as facing pi (backwards),
    and frame 1's cloud half turned as facing pi + 0.2 (0.2 once turned back)."""
    def __init__(self, weights, clouds, **options):
        super().__init__(weights, PipelineConfig(smoothing=None, denoise=False, **options),
                         warn=False)
        centre = clouds[1].mean(axis=0)
        self.answers = [(clouds[0], facing(0.0)), (clouds[1], facing(np.pi, seed=1)),
                        (half_turned(clouds[1], centre), facing(np.pi + 0.2, seed=2))]

    def _reader(self, mirrored):
        return ScriptedReading(self.answers, [], mirrored)


@pytest.mark.parametrize("facing_check", [True, False])
def test_the_retargeter_hands_smrm_the_reading_facing_nearer(tiny_weights, tiny_stream,
                                                             facing_check):
    target, _, _ = tiny_stream
    clouds = cloud(2, 300, 3)
    retargeter = FlippingRetargeter(tiny_weights, clouds, facing_check=facing_check)
    retargeter.set_target(target, tpose_joints=facing(0.0),
                          skin_weights=np.full((len(target), NUM_JOINTS), 1 / NUM_JOINTS))
    second = half_turned(facing(np.pi + 0.2, seed=2), clouds[1].mean(axis=0))
    expected = second if facing_check else facing(np.pi, seed=1)
    frames = [retargeter.step(cloud) for cloud in clouds]
    # No smoothing, no denoiser: SMRM sees the chosen reading itself.
    np.testing.assert_allclose(frames[1].source_joints, expected, atol=1e-6)
    if facing_check:
        assert wrapped(retargeter.state.stages["facing_check"].reference - 0.2) == (
            pytest.approx(0.0, abs=1e-5))
    else:
        assert "facing_check" not in retargeter.state.stages
    # The same through step_skeleton with the clouds, and offline.
    retargeter.reset()
    readings = retargeter.skeleton(clouds)
    again = [retargeter.step_skeleton(j, c) for j, c in zip(readings, clouds)]
    offline = retargeter.retarget_sequence(clouds)
    for got in (again[1].source_joints, offline.source_joints[1]):
        np.testing.assert_allclose(got, expected, atol=1e-6)
    np.testing.assert_allclose(offline.vertices, [f.vertices for f in frames], atol=1e-5)
    # Without the clouds there is nothing to read again: the skeleton stands.
    retargeter.reset()
    plain = [retargeter.step_skeleton(j) for j in readings]
    np.testing.assert_allclose(plain[1].source_joints, facing(np.pi, seed=1), atol=1e-6)
