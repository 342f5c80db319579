"""The leg check (minretarget.legs) on hand-made skeletons, in the Retargeter, in the weights
file and in a resumed stream."""
import dataclasses

import numpy as np
import pytest

import minretarget.retargeter as retargeter_module
from conftest import facing
from minretarget.conventions import JOINT_INDEX, NUM_JOINTS
from minretarget.legs import EXCHANGES, JUMP, check_legs, exchanged, leg_distance
from minretarget.retargeter import Retargeter
from minretarget.weights import flatten_weights, weights_from_arrays
from training.export import with_legs

LEFT_FOOT = [JOINT_INDEX["left_ankle"], JOINT_INDEX["left_foot"]]
RIGHT_FOOT = [JOINT_INDEX["right_ankle"], JOINT_INDEX["right_foot"]]
LEFT_KNEE, RIGHT_KNEE = JOINT_INDEX["left_knee"], JOINT_INDEX["right_knee"]


def standing(seed=0):
    """A skeleton facing +Z whose legs stand 0.2 m apart (left at +x), the rest random."""
    joints = facing(0.0, seed)
    for side, x in (("left", 0.1), ("right", -0.1)):
        for name, y in (("knee", 0.5), ("ankle", 0.1), ("foot", 0.03)):
            joints[JOINT_INDEX[f"{side}_{name}"]] = (0.3 + x, y, -0.2 + 0.1 * (name == "foot"))
    return joints


def never():
    raise AssertionError("the second SKR must not run")


def test_exchanged_swaps_exactly_the_pair_and_leg_distance_sums_six_joints():
    joints = standing()
    feet = exchanged(joints, EXCHANGES[0])
    np.testing.assert_array_equal(feet[LEFT_FOOT], joints[RIGHT_FOOT])
    np.testing.assert_array_equal(feet[RIGHT_FOOT], joints[LEFT_FOOT])
    others = [j for j in range(NUM_JOINTS) if j not in LEFT_FOOT + RIGHT_FOOT]
    np.testing.assert_array_equal(feet[others], joints[others])
    legs = exchanged(joints, EXCHANGES[1])
    assert (legs[LEFT_KNEE] == joints[RIGHT_KNEE]).all()
    np.testing.assert_array_equal(exchanged(feet, EXCHANGES[0]), joints)   # an involution
    # Each of the four foot joints is 0.2 m from its exchange: 0.8 m in all.
    assert leg_distance(feet, joints) == pytest.approx(0.8, abs=1e-6)


def test_a_reading_that_does_not_jump_stands_without_the_second_skr():
    previous = standing()
    reading = previous + np.float32(0.01)       # every joint moved 1.7 cm: no exchange saves
    np.testing.assert_array_equal(check_legs(reading, previous, never), reading)


@pytest.mark.parametrize("pair", [0, 1])
def test_legs_that_jump_are_exchanged_when_the_second_skr_agrees(pair):
    previous = standing()
    swapped = exchanged(previous, EXCHANGES[pair])
    # The second SKR reads them as they were: the exchange is taken.
    np.testing.assert_allclose(check_legs(swapped, previous, lambda: previous), previous)
    # It reads them swapped too: the reading stands, though its legs jumped.
    np.testing.assert_array_equal(check_legs(swapped, previous, lambda: swapped), swapped)


def test_lower_legs_must_move_jump_less_than_the_feet_again():
    previous = standing()
    reading = exchanged(previous, EXCHANGES[1])
    # Knees 0.2 m apart: exchanging them too saves 0.4 m over the feet alone: taken.
    assert (check_legs(reading, previous, lambda: previous)[LEFT_KNEE]
            == previous[LEFT_KNEE]).all()
    # Knees side by side (4 cm apart): the knees' exchange saves 0.08 m < JUMP over the feet.
    close = previous.copy()
    close[LEFT_KNEE, 0], close[RIGHT_KNEE, 0] = 0.32, 0.28
    reading = exchanged(close, EXCHANGES[1])
    checked = check_legs(reading, close, lambda: close)
    np.testing.assert_array_equal(checked, exchanged(reading, EXCHANGES[0]))


def test_the_result_is_always_the_reading_or_one_exchange_of_it():
    rng = np.random.default_rng(3)
    for trial in range(200):
        previous = standing(trial)
        reading = previous + rng.normal(0, 0.1, previous.shape).astype(np.float32)
        second = previous + rng.normal(0, 0.1, previous.shape).astype(np.float32)
        checked = check_legs(reading, previous, lambda: second)
        allowed = [reading] + [exchanged(reading, pair) for pair in EXCHANGES]
        assert any(np.array_equal(checked, a) for a in allowed)
        assert leg_distance(checked, previous) <= leg_distance(reading, previous)


def test_check_legs_refuses_bad_input():
    with pytest.raises(ValueError, match="reading"):
        check_legs(np.zeros((21, 3)), standing(), never)
    with pytest.raises(ValueError, match="jump"):
        check_legs(standing(), standing(), never, jump=-0.1)


@pytest.fixture
def legs_weights(tiny_weights):
    """The tiny weights with their own SKR as the leg check's second SKR."""
    return with_legs(tiny_weights, tiny_weights.skr, {"recipe": "test"})


def test_weights_carry_the_second_skr_and_refuse_other_sizes(tiny_weights, legs_weights):
    assert legs_weights.config.legs and legs_weights.metadata["legs"] == {"recipe": "test"}
    arrays = flatten_weights(legs_weights)
    assert {k for k in arrays if k.startswith("legs.")} == {
        "legs" + k[3:] for k in arrays if k.startswith("skr.")}
    loaded = weights_from_arrays(arrays)
    np.testing.assert_array_equal(loaded.legs.regressor.head.output.weight,
                                  tiny_weights.skr.regressor.head.output.weight)
    del arrays["legs.regressor.head.output.bias"]
    with pytest.raises(ValueError, match="missing.*legs.regressor.head.output.bias"):
        weights_from_arrays(arrays)
    wider = tiny_weights.skr._replace(regressor=tiny_weights.skr.regressor._replace(
        point=tiny_weights.skr.regressor.point[:2] + (
            tiny_weights.skr.regressor.point[2]._replace(
                weight=np.zeros((tiny_weights.skr.regressor.point[2].weight.shape[0], 7),
                                np.float32)),)))
    with pytest.raises(ValueError, match="same sizes"):
        with_legs(tiny_weights, wider, {})


class LabelledStream:
    """Frames 0 and 2 are given the standing skeleton, frame 1 the same with its feet
    exchanged; the second SKR (patched) reads every cloud as standing."""
    def __init__(self, monkeypatch, weights):
        self.clouds = np.random.default_rng(0).normal(size=(3, 300, 3)).astype(np.float32)
        self.skeletons = [standing(), exchanged(standing(), EXCHANGES[0]), standing()]
        real = retargeter_module.regress_joints
        self.calls = 0

        def regress(points, skr_weights, workers=1):
            if skr_weights is weights.legs:
                self.calls += 1
                return standing()
            return real(points, skr_weights, workers)
        monkeypatch.setattr(retargeter_module, "regress_joints", regress)


@pytest.mark.parametrize("leg_check", [True, False])
def test_the_retargeter_hands_smrm_the_exchanged_legs(monkeypatch, tiny_stream, legs_weights,
                                                      leg_check):
    target, _, _ = tiny_stream
    stream = LabelledStream(monkeypatch, legs_weights)
    retargeter = Retargeter(legs_weights, warn=False, smoothing=None, denoise=False,
                            foot_lock=None, facing_check=False, leg_check=leg_check)
    retargeter.set_target(target)
    frames = [retargeter.step_skeleton(j, c) for j, c in zip(stream.skeletons, stream.clouds)]
    # No smoothing, no denoiser: SMRM sees the checked skeleton itself.
    expected = standing() if leg_check else stream.skeletons[1]
    np.testing.assert_allclose(frames[1].source_joints, expected, atol=1e-6)
    np.testing.assert_allclose(frames[2].source_joints, standing(), atol=1e-6)
    assert stream.calls == (1 if leg_check else 0)          # frame 1 only: it jumped
    # Without the clouds, or with weights that have no second SKR, the skeletons stand.
    retargeter.reset()
    plain = [retargeter.step_skeleton(j) for j in stream.skeletons]
    np.testing.assert_allclose(plain[1].source_joints, stream.skeletons[1], atol=1e-6)
    without = Retargeter(legs_weights._replace(
        config=dataclasses.replace(legs_weights.config, legs=False), legs=None), warn=False,
        smoothing=None, denoise=False, foot_lock=None, facing_check=False)
    without.set_target(target)
    unchecked = [without.step_skeleton(j, c) for j, c in zip(stream.skeletons, stream.clouds)]
    np.testing.assert_allclose(unchecked[1].source_joints, stream.skeletons[1], atol=1e-6)


def test_a_stream_resumed_after_the_exchange_goes_on_as_unbroken(monkeypatch, tiny_stream,
                                                                 legs_weights):
    target, _, _ = tiny_stream
    stream = LabelledStream(monkeypatch, legs_weights)
    skeletons = stream.skeletons + [exchanged(standing(), EXCHANGES[0])]
    clouds = np.concatenate([stream.clouds, stream.clouds[:1]])
    retargeter = Retargeter(legs_weights, warn=False)
    retargeter.set_target(target)
    unbroken = [retargeter.step_skeleton(j, c) for j, c in zip(skeletons, clouds)]
    retargeter.reset()
    for j, c in zip(skeletons[:2], clouds[:2]):
        retargeter.step_skeleton(j, c)
    np.testing.assert_allclose(retargeter.state.given_joints, standing(), atol=1e-6)
    resumed = Retargeter(legs_weights, warn=False)
    resumed.set_target(target)
    resumed.state = retargeter.state
    for t in (2, 3):
        np.testing.assert_array_equal(resumed.step_skeleton(skeletons[t], clouds[t]).vertices,
                                      unbroken[t].vertices)
