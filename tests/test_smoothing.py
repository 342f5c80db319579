"""Source skeleton smoothing (minretarget.smoothing): the kernel against its NumPy twin, hand
cases, pass-through, and its place in the stream (retarget_step, Retargeter, resume)."""
import numpy as np
import pytest
import twins

from minretarget.conventions import NUM_JOINTS
from minretarget.retargeter import Retargeter
from minretarget.smoothing import Smoothing, check_smoothing, smooth_joints
from minretarget.smrm import retarget_step
from minretarget.pipeline import PipelineConfig


def run_filter(frames, smoothing):
    previous, velocity = frames[0], np.zeros_like(frames[0])
    out = [previous]
    for joints in frames[1:]:
        previous, velocity = smooth_joints(joints, previous, velocity, smoothing)
        out.append(previous)
    return np.stack(out)


def test_kernel_matches_the_twin():
    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(0, 0.02, (40, NUM_JOINTS, 3)), axis=0).astype(np.float32)
    for smoothing in (Smoothing(), Smoothing(0.3, 0.05), Smoothing(0.9, 0.9)):
        np.testing.assert_allclose(run_filter(walk, smoothing), twins.alpha_beta(walk, *smoothing),
                                   atol=1e-5)


def test_hand_cases():
    still = np.ones((NUM_JOINTS, 3), np.float32)
    zero = np.zeros((NUM_JOINTS, 3), np.float32)
    # A joint at rest stays put, its velocity stays zero.
    out, velocity = smooth_joints(still, still, zero)
    np.testing.assert_array_equal(out, still)
    assert not velocity.any()
    # A step from 0 to 1 m with gains (0.5, 0.2): the prediction is 0, so the output is 0.5 and
    # the velocity 0.2 * 30 * 1 = 6 m/s. The next frame at 1 m again: prediction 0.5 + 6 / 30
    # = 0.7, error 0.3, output 0.85, velocity 6 + 0.2 * 30 * 0.3 = 7.8 m/s.
    out, velocity = smooth_joints(still, zero, zero, Smoothing(0.5, 0.2))
    np.testing.assert_allclose(out, 0.5, atol=1e-6)
    np.testing.assert_allclose(velocity, 6.0, atol=1e-5)
    out, velocity = smooth_joints(still, out, velocity, Smoothing(0.5, 0.2))
    np.testing.assert_allclose(out, 0.85, atol=1e-6)
    np.testing.assert_allclose(velocity, 7.8, atol=1e-5)


def test_none_passes_through_exactly_and_tracks_velocity():
    rng = np.random.default_rng(1)
    joints, previous, velocity = rng.normal(size=(3, NUM_JOINTS, 3)).astype(np.float32)
    out, new_velocity = smooth_joints(joints, previous, velocity, None)
    np.testing.assert_array_equal(out, joints)
    np.testing.assert_allclose(new_velocity, 30 * (joints - previous), rtol=1e-4, atol=1e-4)


def test_smoothing_removes_jitter_and_follows_steady_motion_without_lag():
    """A still body with 2 cm white jitter: the output jitters 40 % less (the defaults); a body
    moving at 1 m/s with the same jitter: after a second, the smoothed path is on the true one
    on average (the prediction uses the velocity: no steady lag, where a One-Euro filter with
    the same jitter lagged by about 2 cm)."""
    rng = np.random.default_rng(2)
    base = rng.normal(size=(NUM_JOINTS, 3)).astype(np.float32)
    noisy = base + rng.normal(0, 0.02, (90, NUM_JOINTS, 3)).astype(np.float32)
    raw_jitter = twins_jitter(noisy)
    assert twins_jitter(run_filter(noisy, Smoothing())) < 0.6 * raw_jitter
    moving = noisy + np.arange(90, dtype=np.float32)[:, None, None] / 30 * [1, 0, 0]
    smoothed = run_filter(moving, Smoothing())
    truth = base + np.arange(90)[:, None, None] / 30 * [1, 0, 0]
    assert np.abs((smoothed - truth)[30:].mean(axis=(0, 1))).max() < 0.003


def twins_jitter(frames):
    return np.linalg.norm(frames[2:] - 2 * frames[1:-1] + frames[:-2], axis=-1).mean()


def test_bad_settings_are_named():
    assert check_smoothing(None) is None
    assert check_smoothing((0.5, 0.25)) == Smoothing(0.5, 0.25)
    for bad in (Smoothing(0.0, 0.0), Smoothing(1.5, 0.1), Smoothing(0.5, -0.1),
                Smoothing(0.5, 0.6), Smoothing(np.nan, 0.1), (0.5, 0.2, 1.0), (0.5,),
                "fast"):
        with pytest.raises(ValueError, match="smoothing"):
            check_smoothing(bad)


def test_stream_smooths_what_smrm_sees(tiny_weights, tiny_stream):
    """retarget_step with smoothing = retarget_step without, on the filtered joints; the
    Retargeter reports them as source_joints; None gives the raw SKR joints."""
    target, sources, _ = tiny_stream
    # SMRM's rotations alone: no foot lock, no denoiser (test_retargeter checks it).
    raw = Retargeter(tiny_weights, PipelineConfig(smoothing=None, foot_lock=None, denoise=False),
        warn=False)
    smooth = Retargeter(tiny_weights, PipelineConfig(foot_lock=None, denoise=False), warn=False)
    raw.set_target(target)
    smooth.set_target(target)
    raw_frames, smooth_frames = list(raw.run(sources[:20])), list(smooth.run(sources[:20]))
    skr = np.stack([f.source_joints for f in raw_frames])
    filtered = run_filter(skr, Smoothing())
    np.testing.assert_allclose(np.stack([f.source_joints for f in smooth_frames]), filtered,
                               atol=1e-6)
    state = None
    for t in range(20):
        rotations, root, state = retarget_step(tiny_weights.smrm, state, filtered[t],
                                               smooth.target.tpose_joints)
        np.testing.assert_allclose(smooth_frames[t].rotations, rotations, atol=1e-5)
        np.testing.assert_allclose(smooth_frames[t].root, root, atol=1e-5)
    # Offline: the same smoothing.
    offline = smooth.retarget_sequence(np.stack([s[:200] for s in sources[:20]]))
    online = list(smooth.run([s[:200] for s in sources[:20]]))
    np.testing.assert_allclose(offline.source_joints, np.stack([f.source_joints for f in online]),
                               atol=2e-5)
