"""The runtime against outputs stored in tests/golden: the tiny model's torch outputs, and every
preset's on the shipped weights and sample. Runs without torch installed."""
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from conftest import GOLDEN, SHIPPED_FRAMES, SHIPPED_VERTEX_STRIDE, one_sided
from minretarget.pipeline import DEFAULT_PRESET, PRESETS, PipelineConfig
from minretarget.retargeter import Retargeter
from minretarget.sources import load_sample

TOLERANCE = 1e-4   # metres


def test_runtime_reproduces_the_golden_torch_stream(tiny_weights, tiny_stream):
    target, sources, want = tiny_stream
    # The torch reference's pipeline: SKR once on the target, no facing check, no smoothing,
    # no foot contacts.
    retargeter = Retargeter(tiny_weights, PipelineConfig(smoothing=None, foot_lock=None,
                                                         mirror_target=False, facing_check=False))
    retargeter.set_target(target)
    np.testing.assert_allclose(retargeter.target.tpose_joints, want["torch_tpose_joints"],
                               atol=TOLERANCE)
    np.testing.assert_allclose(retargeter.target.skin_weights, want["torch_skin_weights"],
                               atol=1e-5)
    assert len(sources) == 60 and len({len(s) for s in sources}) > 1   # point counts vary
    for t, frame in enumerate(retargeter.run(sources)):
        for key in ("vertices", "joints", "root", "source_joints"):
            np.testing.assert_allclose(getattr(frame, key), want[f"torch_{key}"][t],
                                       atol=TOLERANCE, err_msg=f"frame {t} {key}")
        np.testing.assert_allclose(frame.rotations, want["torch_rotations"][t], atol=1e-5)


SHIPPED = GOLDEN / "shipped_presets.npz"
SHIPPED_TOLERANCE = 1e-3   # metres: other CPUs round the fit's float64 solves differently


@pytest.fixture(scope="module")
def shipped_stream():
    source, target_points, faces, _ = load_sample()
    clouds = [cloud for cloud, _ in zip(source.frames, range(SHIPPED_FRAMES))]
    with np.load(SHIPPED) as data:
        return target_points, faces, clouds, dict(data)


@pytest.mark.parametrize("preset", ["default", *PRESETS])
def test_every_preset_on_the_shipped_weights_and_sample_gives_its_golden_output(shipped_stream,
                                                                               preset):
    """The whole pipeline, as shipped (tests/make_golden.py --shipped wrote the outputs; a
    change of any stage, setting or weight shows here)."""
    target_points, faces, clouds, want = shipped_stream
    name = DEFAULT_PRESET if preset == "default" else preset
    retargeter = (Retargeter.from_weights(warn=False) if preset == "default"
                  else Retargeter.from_weights(None, preset, warn=False))
    retargeter.set_target(target_points, faces)
    with threadpool_limits(1):
        frames = list(retargeter.run(clouds))
    for field in ("joints", "root", "source_joints", "vertices"):
        got = np.stack([getattr(f, field) for f in frames])
        if field == "vertices":
            got = got[:, ::SHIPPED_VERTEX_STRIDE]
        np.testing.assert_allclose(got, want[f"{name}_{field}"], atol=SHIPPED_TOLERANCE,
                                   err_msg=f"{preset}: {field}")
    # rotations: the same turn up to the quaternion's sign
    rotations = np.stack([f.rotations for f in frames])
    agreement = np.abs(np.sum(rotations * want[f"{name}_rotations"], axis=-1))
    assert agreement.min() > 1 - 1e-5, preset


def test_the_fit_told_a_camera_on_the_shipped_sample_gives_its_golden_output(shipped_stream):
    """The fitted preset told where a camera stands, on the one-sided halves of the shipped
    sample's clouds (``conftest.one_sided``; tests/make_golden.py --shipped wrote it)."""
    target_points, faces, clouds, want = shipped_stream
    told, camera = one_sided(clouds)
    retargeter = Retargeter.from_weights(None, "fitted", warn=False)
    retargeter.set_target(target_points, faces)
    with threadpool_limits(1):
        frames = list(retargeter.run(told, camera))
    for field in ("joints", "root", "source_joints", "vertices"):
        got = np.stack([getattr(f, field) for f in frames])
        if field == "vertices":
            got = got[:, ::SHIPPED_VERTEX_STRIDE]
        np.testing.assert_allclose(got, want[f"fitted_viewpoint_{field}"],
                                   atol=SHIPPED_TOLERANCE, err_msg=field)
    # the camera is read: untold, the same clouds give another skeleton
    untold = np.stack([f.source_joints for f in retargeter.run(told)])
    assert np.abs(untold - want["fitted_viewpoint_source_joints"]).max() > 0.01
