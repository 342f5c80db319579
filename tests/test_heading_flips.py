"""The bookkeeping of benchmarks/heading_flips.py on hand-made skeletons."""
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import facing, turned_about_up
from minretarget.conventions import JOINT_INDEX

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import heading_flips  # noqa: E402


def test_sequence_flips_counts_the_frames_facing_the_wrong_way():
    angles = np.radians([170.0, 180.0, -170.0, -150.0, -150.0, -140.0])
    truth = np.stack([facing(angle, seed) for seed, angle in enumerate(angles)])
    sequence = {"name": "s", "category": "dance", "source_points": None, "source_joints": truth}
    half_turned = np.isin(np.arange(len(truth)), [1, 4])
    out = heading_flips.sequence_flips({"a": turned_about_up(truth,
                                                             np.where(half_turned, np.pi, 0.0)),
                                        "b": truth}, sequence)
    assert out["frames"] == 6
    assert {name: found["flipped"] for name, found in out["found"].items()} == {"a": 2, "b": 0}
    assert out["found"]["b"]["toe_error_sum_flipped"] == 0.0
    assert out["found"]["b"]["toe_error_sum_other"] == pytest.approx(0.0, abs=1e-9)
    # A half turn about +Y takes a toe (x, z) off the pelvis to (-x, -z): twice its distance.
    toes = truth[:, heading_flips.TOES] - truth[:, :1]
    expected = 2 * np.linalg.norm(toes[[1, 4]][..., [0, 2]], axis=-1).sum()
    assert out["found"]["a"]["toe_error_sum_flipped"] == pytest.approx(expected)
    # -170 -> -150 degrees; the turns across +-180 (170 -> 180 -> -170) count 10, not 350.
    assert out["truth_largest_turn_degrees"] == pytest.approx(20.0)


def test_legs_swapped_counts_exchanged_feet_and_lower_legs_in_frames_facing_right():
    """Frame 1 has its feet (ankle, toe) exchanged, frame 2 its lower legs (knee too), frame 3
    its feet exchanged and its hips and shoulders half turned (counted as flipped only), frame
    4 its feet exchanged while they stand 2 cm apart (under the margin); the truth's feet are
    0.5 m apart."""
    truth = np.stack([facing(0.0, seed) for seed in range(5)])
    left, right = heading_flips.LOWER_LEGS
    truth[:, left] = truth[:, right] + (0.5, 0.0, 0.0)
    truth[4, left] = truth[4, right] + (0.02, 0.0, 0.0)
    read = truth.copy()
    for t, exchanged in ((1, slice(1, 3)), (2, slice(0, 3)), (3, slice(1, 3)),
                         (4, slice(1, 3))):
        read[t, left[exchanged]], read[t, right[exchanged]] = (truth[t, right[exchanged]],
                                                               truth[t, left[exchanged]])
    across = [JOINT_INDEX[f"{side}_{name}"] for side in ("left", "right")
              for name in ("hip", "shoulder")]
    read[3, across] = turned_about_up(read[3, across] - read[3, 0], np.pi) + read[3, 0]
    np.testing.assert_array_equal(heading_flips.legs_swapped(read, truth),
                                  [False, True, True, True, False])
    sequence = {"name": "s", "category": "indian", "source_points": None, "source_joints": truth}
    found = heading_flips.sequence_flips({"a": read}, sequence)["found"]["a"]
    assert (found["flipped"], found["legs_swapped"]) == (1, 2)
    toes = heading_flips.toe_errors(read, truth)
    assert found["toe_error_sum_legs_swapped"] == pytest.approx(toes[[1, 2]].sum())
