"""The one-view SKR: the turn that puts the camera in front, the weights that carry it, and
the reading a told frame gets (``skr.view_turn``, ``read_from_view``, ``Weights.skr_view``)."""
import numpy as np
import pytest

from conftest import one_sided, turned_about_up
from minretarget import stages
from minretarget.conventions import FORWARD_AXIS, UP_AXIS
from minretarget.pipeline import preset
from minretarget.retargeter import Retargeter
from minretarget.skr import read_from_view, regress_joints, view_turn
from minretarget.weights import load_weights, save_weights


def with_view_skr(weights, scale=1.0):
    """``weights`` given a one-view SKR: their own SKR with its output layer scaled (another
    network, so which one read a cloud shows)."""
    head = weights.skr.regressor.head
    output = head.output._replace(weight=head.output.weight * np.float32(scale))
    view = weights.skr._replace(regressor=weights.skr.regressor._replace(
        head=head._replace(output=output)))
    return weights._replace(config=weights.config.with_view_skr(), skr_view=view)


@pytest.mark.parametrize("camera", [(0.0, 1.5, 3.0), (2.0, 0.5, 0.0), (-1.0, 2.0, -2.5),
                                    (0.3, 1.2, 0.4)])
def test_view_turn_puts_the_camera_in_front(camera):
    points = np.random.default_rng(0).normal(0.0, 0.3, (200, 3)).astype(np.float32) + 1.0
    turn = view_turn(points, camera).astype(np.float64)
    np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(turn) == pytest.approx(1.0, abs=1e-6)
    up = np.eye(3)[UP_AXIS]
    np.testing.assert_allclose(turn @ up, up, atol=1e-6)               # a turn about up
    toward = np.asarray(camera, np.float64) - points.mean(axis=0)
    toward[UP_AXIS] = 0.0
    turned = turn @ toward
    assert turned[FORWARD_AXIS] == pytest.approx(np.linalg.norm(toward), rel=1e-5)


def test_view_turn_is_the_identity_for_a_camera_straight_above():
    points = np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32)
    camera = points.mean(axis=0) + (0.0, 3.0, 0.0)
    np.testing.assert_array_equal(view_turn(points, camera), np.eye(3, dtype=np.float32))


def test_view_turn_matches_a_hand_computed_turn():
    """A camera on the +X side of the cloud: turning it onto +Z is a turn of -90 degrees
    about +Y (x -> z), so (1, 0, 0) -> (0, 0, 1) and (0, 0, 1) -> (-1, 0, 0)."""
    points = np.zeros((10, 3), np.float32)
    turn = view_turn(points, (4.0, 1.0, 0.0))
    np.testing.assert_allclose(turn @ (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), atol=1e-7)
    np.testing.assert_allclose(turn @ (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0), atol=1e-7)


def test_read_from_view_turns_the_joints_back():
    """A finder that returns the first 22 points it is given: read from any view, it gives
    the untouched cloud's first 22 points; the cloud it saw is the cloud turned."""
    rng = np.random.default_rng(2)
    clouds = rng.normal(size=(3, 100, 3)).astype(np.float32)
    seen = []

    def first_points(batch):
        seen.append(batch.copy())
        return batch[:, :22]
    camera = np.array([1.0, 1.5, -2.0], np.float32)
    joints = read_from_view(first_points, clouds, camera)
    np.testing.assert_allclose(joints, clouds[:, :22], atol=1e-5)
    for cloud, given in zip(clouds, seen):
        np.testing.assert_allclose(given[0], cloud @ view_turn(cloud, camera).T, atol=1e-6)
    np.testing.assert_allclose(read_from_view(first_points, clouds[0], camera), clouds[0, :22],
                               atol=1e-5)


def test_the_one_view_reading_turns_with_the_camera(tiny_weights, tiny_stream):
    """Cloud and camera turned together about the up axis: the one-view reading turns with
    them (the network sees the same turned cloud)."""
    cloud = tiny_stream[1][0]
    camera = cloud.mean(axis=0) + np.array([0.5, 0.4, 2.0], np.float32)
    view = with_view_skr(tiny_weights).skr_view

    def skr(batch):
        return regress_joints(batch, view)
    plain = read_from_view(skr, cloud, camera)
    angle = 1.1
    turned = read_from_view(skr, turned_about_up(cloud, angle).astype(np.float32),
                            turned_about_up(camera[None], angle)[0].astype(np.float32))
    np.testing.assert_allclose(turned, turned_about_up(plain, angle), atol=2e-5)


def test_weights_with_a_one_view_skr_round_trip(tiny_weights, tmp_path):
    weights = with_view_skr(tiny_weights, 0.5)
    save_weights(tmp_path / "w.npz", weights)
    loaded = load_weights(tmp_path / "w.npz")
    assert loaded.config.skr_view and not tiny_weights.config.skr_view
    assert tiny_weights.skr_view is None
    np.testing.assert_array_equal(loaded.skr_view.regressor.head.output.weight,
                                  weights.skr_view.regressor.head.output.weight)
    save_weights(tmp_path / "plain.npz", tiny_weights)
    assert load_weights(tmp_path / "plain.npz").skr_view is None


def test_a_told_frame_is_read_by_the_one_view_skr(tiny_weights, tiny_stream):
    """Told the camera, the reading is the one-view SKR's, turned, not refined; untold, or
    with ``skr_view`` off, the plain SKR's, refined."""
    weights = with_view_skr(tiny_weights, 0.5)
    clouds, camera = one_sided(tiny_stream[1][:2])
    config = preset("fitted")
    assert config.refine and config.skr_view and weights.refine is not None
    reading = stages.Reading(weights, config.refine, False, 1)
    told = reading.read(clouds[0], camera)
    expected = read_from_view(
        lambda batch: regress_joints(batch, weights.skr_view), clouds[0], camera)
    np.testing.assert_allclose(told, expected, atol=1e-5)
    plain = stages.Reading(weights, config.refine, False, 1, view=False).read(clouds[0], camera)
    np.testing.assert_array_equal(plain, reading.read(clouds[0]))
    assert np.abs(told - plain).max() > 1e-3

    retargeter = Retargeter(weights, config.replace(fit_source=None, foot_lock=None,
                                                    allow_untrained=True), warn=False)
    np.testing.assert_allclose(retargeter.skeleton(clouds[0], camera), told, atol=1e-6)
    np.testing.assert_array_equal(retargeter.skeleton(clouds[0]), plain)
    off = Retargeter(weights, config.replace(fit_source=None, foot_lock=None, skr_view=False,
                                             allow_untrained=True), warn=False)
    np.testing.assert_array_equal(off.skeleton(clouds[0], camera), plain)


def test_the_told_reading_matches_the_torch_reference(tmp_path):
    """Two random torch SKRs exported as a weights file's SKR and one-view SKR: a told
    frame's reading (refiner off) is the second network on the cloud turned, turned back."""
    import torch
    from reference_models import random_reference
    from training.export import export_weights, skr_runtime_weights

    model, view = random_reference(seed=0), random_reference(seed=1)
    export_weights(tmp_path / "w.npz", model.skr, model.smrm, model.skin,
                   skr_view=skr_runtime_weights(view.skr.eval()))
    weights = load_weights(tmp_path / "w.npz")
    cloud = np.random.default_rng(3).normal(0.0, 0.4, (300, 3)).astype(np.float32)
    camera = np.array([1.5, 1.0, 2.0], np.float32)
    turn = view_turn(cloud, camera)
    with torch.no_grad():
        want = view.skr.eval()(torch.from_numpy(cloud @ turn.T)[None])[0].numpy() @ turn
    got = stages.Reading(weights, False, False, 1).read(cloud, camera)
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_one_view_training_frames_are_the_seen_side_turned_to_face_the_camera(monkeypatch):
    """``training.skr_view.one_view`` on a cube 'body' (pelvis at its centre): every point
    lies on the cube's faces turned about up by the same turn as the joints, on the side
    the camera saw, which is turned to face +Z."""
    from test_depth_camera import cube
    from training import skr_view

    monkeypatch.setattr(skr_view, "NOISE_SHARE", 0.0)
    vertices, faces = cube(0.4)
    vertices = vertices + (0.0, 1.0, 0.0)
    joints = np.random.default_rng(4).normal(0.0, 0.2, (22, 3)) + (0.0, 1.0, 0.0)
    joints[0] = (0.0, 1.0, 0.0)
    rng = np.random.default_rng(5)
    for _ in range(5):
        points, turned_joints = skr_view.one_view(vertices, faces, joints, 256, rng)
        assert points.shape == (256, 3) and turned_joints.shape == (22, 3)
        np.testing.assert_allclose(turned_joints[:, 1], joints[:, 1], atol=1e-6)
        # The turn, from the joints (about up through the origin), undone on the points.
        a, b = joints[1:, [2, 0]] - joints[0, [2, 0]], turned_joints[1:, [2, 0]]
        angle = np.arctan2((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum(),
                           (a * b).sum())
        back = turned_about_up(points[None].astype(np.float64), -angle)[0]
        np.testing.assert_allclose(turned_about_up(turned_joints[None].astype(np.float64),
                                                   -angle)[0], joints, atol=1e-5)
        offset = np.abs(back - (0.0, 1.0, 0.0))
        assert np.allclose(offset.max(axis=1), 0.4, atol=1e-4)      # on the cube's faces
        assert points[:, 2].mean() > turned_joints[0, 2] + 0.05      # the camera's side: +Z


def test_every_told_frame_of_a_stream_is_read_by_the_one_view_skr(tiny_weights, tiny_stream,
                                                                  monkeypatch):
    """``step(points, viewpoint)``, ``run`` and ``retarget_sequence`` read each told cloud
    with the one-view SKR and that cloud's camera; ``step(points)`` never does."""
    weights = with_view_skr(tiny_weights, 0.5)
    clouds, camera = one_sided(tiny_stream[1][:3])
    calls = []
    real = stages.read_from_view

    def spy(skeleton, points, viewpoint):
        calls.append((points.shape, np.asarray(viewpoint).copy()))
        return real(skeleton, points, viewpoint)
    monkeypatch.setattr(stages, "read_from_view", spy)
    config = preset("fitted").replace(allow_untrained=True)
    retargeter = Retargeter(weights, config, warn=False)
    retargeter.set_target(tiny_stream[0])
    for cloud in clouds:
        retargeter.step(cloud, camera)
    assert [shape for shape, _ in calls] == [cloud.shape for cloud in clouds]
    assert all(np.array_equal(seen, camera) for _, seen in calls)
    calls.clear()
    retargeter.reset()
    list(retargeter.run(clouds, camera))
    assert len(calls) == len(clouds)
    calls.clear()
    retargeter.reset()
    for cloud in clouds:
        retargeter.step(cloud)
    assert not calls
    same = np.stack([cloud[:min(len(c) for c in clouds)] for cloud in clouds])
    retargeter.retarget_sequence(same, camera)
    assert [shape for shape, _ in calls] == [same.shape]


def test_the_fit_keeps_the_one_view_reading_s_depth(tiny_weights, tiny_stream, monkeypatch):
    """With a one-view SKR the told fit is built to keep the reading's depth
    (``reading_depth``), without one to take it from the motion; ``fit_frame`` with
    ``reading_depth`` is the fit with no depth taken from the motion."""
    from minretarget import fit
    clouds, camera = one_sided(tiny_stream[1][:3])
    given = []
    real = stages.fit_frame

    def spy(*args):
        given.append(args[5:])
        return real(*args)
    monkeypatch.setattr(stages, "fit_frame", spy)
    config = preset("fitted").replace(allow_untrained=True)
    for weights, kept in ((with_view_skr(tiny_weights), True), (tiny_weights, False)):
        given.clear()
        retargeter = Retargeter(weights, config, warn=False)
        retargeter.set_target(tiny_stream[0])
        for cloud in clouds:
            retargeter.step(cloud, camera)
        assert len(given) == len(clouds) - 1
        assert all(np.array_equal(v, camera) and depth is kept for v, depth in given)

    from minretarget.sources import load_sample    # a body, so that the fit finds one
    source = load_sample()[0]
    whole = [cloud for cloud, _ in zip(source.frames, range(3))]
    clouds, camera = one_sided(whole)
    model = fit.body_model()
    settings = fit.FitSettings(calibration_frames=1, settle_rounds=0)
    reading = Retargeter.from_weights(None, warn=False).skeleton(whole[0])
    state, joints = fit.start_fit(model, settings, clouds[0], reading, camera)
    state, joints, _ = fit.fit_frame(model, settings, state, clouds[1], joints, camera)
    reading = joints + (0.04, 0.0, 0.04)     # near the fit, so that it pulls; off in depth
    kept = fit.fit_frame(model, settings, state, clouds[2], reading, camera, True)[1]
    moved = fit.fit_frame(model, settings, state, clouds[2], reading, camera)[1]
    monkeypatch.setattr(fit, "_depth_from", lambda reading, predicted, viewpoint: reading)
    np.testing.assert_array_equal(
        kept, fit.fit_frame(model, settings, state, clouds[2], reading, camera)[1])
    assert np.abs(kept - moved).max() > 1e-4


def test_only_the_one_view_skr_s_reading_is_flagged_as_such(tiny_weights, tiny_stream):
    """``Frame.view_read`` (the fit keeps such a reading's depth) is set by a told frame's
    one-view reading only: not untold, not without a one-view SKR, not for a given skeleton."""
    weights = with_view_skr(tiny_weights, 0.5)
    clouds, camera = one_sided(tiny_stream[1][:1])
    cloud = clouds[0]
    reading = stages.Reading(weights, True, False, 1)
    for frame, flagged in ((stages.Frame(0, cloud, None, viewpoint=camera), True),
                           (stages.Frame(0, cloud, None), False),
                           (stages.Frame(0, cloud, np.zeros((22, 3), np.float32),
                                         viewpoint=camera), False)):
        assert reading.step(None, frame)[1].view_read is flagged
    plain = stages.Reading(tiny_weights, True, False, 1)
    assert not plain.step(None, stages.Frame(0, cloud, None, viewpoint=camera))[1].view_read
