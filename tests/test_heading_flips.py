"""The bookkeeping of benchmarks/heading_flips.py on hand-made skeletons."""
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import facing, turned_about_up

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
