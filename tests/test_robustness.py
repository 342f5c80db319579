"""Perturbations and bookkeeping of benchmarks/robustness.py: seeded, shapes, kept fractions,
noise scale, gap-free acceleration."""
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minretarget.conventions import NUM_JOINTS
from minretarget.metrics import acceleration_error, pa_acceleration_error

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import robustness  # noqa: E402


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.tuples(st.integers(1, 4), st.integers(1, 50)),
       st.sampled_from(robustness.NOISE_SIGMAS[1:]))
def test_add_noise_seeded_and_shaped(seed, shape, sigma):
    points = np.random.default_rng(seed).random(shape + (3,)).astype(np.float32)
    first = robustness.add_noise(points, sigma, np.random.default_rng(seed))
    again = robustness.add_noise(points, sigma, np.random.default_rng(seed))
    assert first.shape == points.shape and first.dtype == np.float32
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, points)


@pytest.mark.parametrize("sigma", robustness.NOISE_SIGMAS[1:])
def test_noise_std_is_sigma_per_axis(sigma):
    points = np.random.default_rng(0).random((20, 1000, 3)).astype(np.float32)
    noise = robustness.add_noise(points, sigma, np.random.default_rng(1)) - points
    np.testing.assert_allclose(noise.reshape(-1, 3).std(axis=0), sigma, rtol=0.03)
    np.testing.assert_allclose(noise.reshape(-1, 3).mean(axis=0), 0, atol=0.02 * sigma)


def test_sigma_zero_returns_the_input():
    points = np.random.default_rng(0).random((5, 64, 3)).astype(np.float32)
    rng = np.random.default_rng(2)
    state = rng.bit_generator.state
    assert robustness.add_noise(points, 0.0, rng) is points
    assert rng.bit_generator.state == state


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.integers(3, 400),
       st.sampled_from(robustness.DROP_FRACTIONS))
def test_drop_frames_keeps_the_right_fraction(seed, count, fraction):
    kept = robustness.drop_frames(count, fraction, np.random.default_rng(seed))
    assert kept.dtype == np.int64 and len(kept) == count - round(fraction * count)
    assert np.all(np.diff(kept) > 0) and kept.min() >= 0 and kept.max() < count
    np.testing.assert_array_equal(kept, robustness.drop_frames(
        count, fraction, np.random.default_rng(seed)))


def test_drop_frames_nested_and_identity():
    np.testing.assert_array_equal(robustness.drop_frames(50, 0.0, np.random.default_rng(0)),
                                  np.arange(50))
    kept = [set(robustness.drop_frames(200, f, np.random.default_rng(3)))
            for f in robustness.DROP_FRACTIONS]
    assert all(later <= earlier for earlier, later in zip(kept, kept[1:]))


def test_consecutive_centres():
    np.testing.assert_array_equal(robustness.consecutive_centres([0, 1, 2, 4, 5, 6, 7]),
                                  [1, 4, 5])
    np.testing.assert_array_equal(robustness.consecutive_centres(np.arange(6)), [1, 2, 3, 4])
    assert len(robustness.consecutive_centres([0, 2, 4, 6])) == 0


def test_gap_free_acceleration_without_drops_is_the_metric():
    rng = np.random.default_rng(0)
    pred, gt = rng.random((2, 12, NUM_JOINTS, 3))
    acc, pa_acc = robustness.gap_free_acceleration(
        pred, gt, robustness.consecutive_centres(np.arange(12)))
    assert acc == pytest.approx(acceleration_error(pred, gt), rel=1e-12)
    assert pa_acc == pytest.approx(pa_acceleration_error(pred, gt), rel=1e-12)


def test_gap_free_acceleration_ignores_gaps():
    # The kept stream jumps across the gap; only the runs 0-1-2 and 5-6-7 count.
    kept = np.array([0, 1, 2, 5, 6, 7])
    gt = np.zeros((6, NUM_JOINTS, 3))
    pred = gt.copy()
    pred[2:4, :, 0] = 1.0                  # a step right at the gap, invisible to Acc
    centres = robustness.consecutive_centres(kept)
    assert robustness.gap_free_acceleration(pred, gt, centres)[0] == pytest.approx(1.0)
    pred[2:4, :, 0] = 0.0
    assert robustness.gap_free_acceleration(pred, gt, centres)[0] == 0.0
    assert np.isnan(robustness.gap_free_acceleration(pred, gt, [])).all()


def test_conditions_share_the_benchmark_input():
    todo, sweeps = robustness.conditions(2048)
    assert [len(sweeps[k]) for k in ("points", "noise", "drop")] == [7, 6, 4]
    assert len(todo) == len(set(todo)) == 7 + 5 + 3
    assert sweeps["points"][3] == sweeps["noise"][0] == sweeps["drop"][0] == (None, 0.0, 0.0)


def test_perturb_drops_the_same_frames_everywhere():
    frames, rng = 40, np.random.default_rng(0)
    sequence = {key: rng.random((frames, 5, 3)).astype(np.float32)
                for key in robustness.FRAME_KEYS}
    sequence["target_tpose_points"] = rng.random((7, 3))
    out, kept = robustness.perturb(sequence, (None, 0.01, 0.25), 0, 0, bodies={})
    assert len(kept) == 30
    for key in ("source_joints", "target_joints", "target_points"):
        np.testing.assert_array_equal(out[key], sequence[key][kept])
    assert np.abs(out["source_points"] - sequence["source_points"][kept]).max() > 0
    assert out["target_tpose_points"] is sequence["target_tpose_points"]


def test_pooled_weights_by_frames_and_skips_empty_acc():
    def result(frames, acc_frames, value):
        metrics = {name: value for name in robustness.METRIC_NAMES}
        return {"frames": frames, "acc_frames": acc_frames,
                "metrics": {row: metrics for row in robustness.ROWS}}
    pooled = robustness.pooled([result(10, 0, 1.0), result(30, 5, 3.0)])
    assert pooled["model"]["MPJPE"] == pytest.approx(2.5)
    assert pooled["analytic"]["Acc"] == pytest.approx(3.0)


@pytest.mark.parametrize("frames", [1, 3, 4])
def test_too_few_frames_for_the_drop_sweep_is_refused_at_once(frames, capsys):
    """Half of 4 frames or fewer dropped leaves fewer than the 3 the metrics need: refused by
    the parser, naming the count, before any weights or data are read."""
    with pytest.raises(SystemExit) as exit_info:
        robustness.main(["--frames", str(frames), "--data", "/nonexistent"])
    assert exit_info.value.code == 2 and f"--frames {frames}" in capsys.readouterr().err


def test_six_frames_pass_the_check():
    """6 frames keep 3 at the largest drop: the run goes on, and stops at the missing data."""
    with pytest.raises(SystemExit) as exit_info:
        robustness.main(["--frames", "6", "--data", "/nonexistent", "--report"])
    assert "no test sequence" in str(exit_info.value.code)
