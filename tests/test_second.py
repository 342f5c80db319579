"""The second reading (minretarget.second): hand-made readings, the weights file, the
Retargeter and the command line's checkpoint record."""
import dataclasses

import numpy as np
import pytest

from conftest import facing
from minretarget.conventions import JOINT_INDEX
from minretarget.retargeter import Retargeter
from minretarget.second import (EXCHANGES, SecondReader, combined_readings, exchanged,
                                leg_distance, legs_agree)
from minretarget.weights import flatten_weights, weights_from_arrays
from training.export import with_second_reader

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


def test_exchanged_swaps_exactly_the_pair_and_leg_distance_sums_six_joints():
    joints = standing()
    feet = exchanged(joints, EXCHANGES[0])
    np.testing.assert_array_equal(feet[LEFT_FOOT], joints[RIGHT_FOOT])
    np.testing.assert_array_equal(feet[RIGHT_FOOT], joints[LEFT_FOOT])
    others = [j for j in range(len(joints)) if j not in LEFT_FOOT + RIGHT_FOOT]
    np.testing.assert_array_equal(feet[others], joints[others])
    assert (exchanged(joints, EXCHANGES[1])[LEFT_KNEE] == joints[RIGHT_KNEE]).all()
    np.testing.assert_array_equal(exchanged(feet, EXCHANGES[0]), joints)   # an involution
    # Each of the four foot joints is 0.2 m from its exchange: 0.8 m in all.
    assert leg_distance(feet, joints) == pytest.approx(0.8, abs=1e-6)


def test_readings_that_agree_are_averaged_and_others_keep_the_first():
    first = np.stack([standing(0), standing(1), standing(2)])
    second = first + np.float32(0.01)                 # frame 0: near; agrees
    second[1] = exchanged(first[1], EXCHANGES[0])     # frame 1: its feet swapped
    second[2] = exchanged(first[2], EXCHANGES[1])     # frame 2: its lower legs swapped
    assert legs_agree(first, second).tolist() == [True, False, False]
    combined = combined_readings(first, second)
    np.testing.assert_allclose(combined[0], first[0] + 0.005, atol=1e-6)
    np.testing.assert_array_equal(combined[1:], first[1:])
    # One frame at a time, the same.
    np.testing.assert_array_equal(combined_readings(first[1], second[1]), first[1])


def test_feet_side_by_side_agree_whatever_their_labels():
    # Feet 2 cm apart: swapping them gains 8 cm at most, under AGREE (10 cm).
    first = standing()
    first[LEFT_FOOT, 0], first[RIGHT_FOOT, 0] = 0.31, 0.29
    second = exchanged(first, EXCHANGES[0])
    assert legs_agree(first, second)
    assert not legs_agree(first, second, margin=0.05)


def test_combined_is_symmetric_where_they_agree_and_never_leaves_the_pair():
    rng = np.random.default_rng(3)
    first = np.stack([standing(s) for s in range(100)])
    second = first + rng.normal(0, 0.02, first.shape).astype(np.float32)
    second[::2] = exchanged(second[::2], EXCHANGES[0])     # every other frame disagrees
    combined = combined_readings(first, second)
    agree = legs_agree(first, second)
    assert agree.tolist() == [t % 2 == 1 for t in range(len(first))]
    np.testing.assert_allclose(combined[agree], combined_readings(second, first)[agree],
                               atol=1e-6)
    np.testing.assert_array_equal(combined[~agree], first[~agree])


def test_combined_readings_refuses_bad_input():
    with pytest.raises(ValueError, match="first"):
        combined_readings(np.zeros((21, 3)), np.zeros((21, 3)))
    with pytest.raises(ValueError, match="second"):
        combined_readings(standing(), np.zeros((2, 22, 3)))
    with pytest.raises(ValueError, match="margin"):
        combined_readings(standing(), standing(), margin=-1.0)


def other_reader(weights, seed=1):
    """A SecondReader the shape of ``weights``' SKR and refiner, its arrays perturbed."""
    arrays = flatten_weights(weights)
    rng = np.random.default_rng(seed)
    for key in arrays:
        if key.startswith(("skr.", "refine.")):
            arrays[key] = arrays[key] * (1 + 0.2 * rng.standard_normal(arrays[key].shape))
            arrays[key] = arrays[key].astype(np.float32)
    other = weights_from_arrays(arrays)
    return SecondReader(other.skr, other.refine)


@pytest.fixture(scope="module")
def two_readers(tiny_weights):
    """The tiny weights with a joint refiner, and the same with a second reader."""
    assert tiny_weights.refine is not None
    return tiny_weights, with_second_reader(tiny_weights, other_reader(tiny_weights),
                                            {"recipe": "test"})


def test_weights_carry_the_second_reader_and_refuse_other_sizes(two_readers):
    first, both = two_readers
    assert both.config.second_reading and both.metadata["second"] == {"recipe": "test"}
    arrays = flatten_weights(both)
    assert {k for k in arrays if k.startswith("second.")} == {
        "second." + k for k in arrays if k.startswith(("skr.", "refine."))}
    loaded = weights_from_arrays(arrays)
    np.testing.assert_array_equal(loaded.second.refine.head.output.weight,
                                  both.second.refine.head.output.weight)
    del arrays["second.skr.regressor.head.output.bias"]
    with pytest.raises(ValueError, match="missing.*second.skr.regressor.head.output.bias"):
        weights_from_arrays(arrays)
    narrow = both.second._replace(refine=both.second.refine._replace(
        point=both.second.refine.point[:-1]))
    with pytest.raises(ValueError, match="sizes of the weights' SKR and refiner"):
        with_second_reader(first, narrow, {})
    with pytest.raises(ValueError, match="second_reading needs a joint refiner"):
        dataclasses.replace(first.config.without_refiner(), second_reading=True)


@pytest.mark.parametrize("mirrored", [False, True])
def test_the_retargeter_reads_with_both_and_combines(two_readers, tiny_stream, mirrored):
    first, both = two_readers
    _, sources, _ = tiny_stream
    clouds = np.stack([s[:200] for s in sources[:4]])
    alone = Retargeter(first, warn=False, mirror_source=mirrored).skeleton(clouds)
    second_alone = Retargeter(first._replace(skr=both.second.skr, refine=both.second.refine),
                              warn=False, mirror_source=mirrored).skeleton(clouds)
    assert not np.allclose(alone, second_alone, atol=1e-3)   # the readers differ
    expected = combined_readings(alone, second_alone)
    got = Retargeter(both, warn=False, mirror_source=mirrored).skeleton(clouds)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    # Switched off, or weights without one: the first reader alone.
    off = Retargeter(both, warn=False, mirror_source=mirrored, second_reading=False)
    np.testing.assert_allclose(off.skeleton(clouds), alone, atol=1e-6)


def test_the_target_skeleton_and_a_stream_use_both(two_readers, tiny_stream):
    first, both = two_readers
    target, sources, _ = tiny_stream
    with_both, alone = Retargeter(both, warn=False), Retargeter(first, warn=False)
    for retargeter in (with_both, alone):
        retargeter.set_target(target)
    assert not np.allclose(with_both.target.tpose_joints, alone.target.tpose_joints)
    frame = with_both.step(sources[0])
    readings = with_both.skeleton(sources[0])
    with_both.reset()
    again = with_both.step_skeleton(readings, sources[0])
    np.testing.assert_array_equal(frame.vertices, again.vertices)
