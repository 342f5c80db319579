"""The rest-pose model: its kernel against a NumPy twin and the torch twin, its properties,
its fit, and its place in SMRM's prior."""
import dataclasses

import numpy as np
import pytest

import twins
from minretarget.checkpoint import run_record
from minretarget.config import ModelConfig
from minretarget.conventions import MIRROR, NUM_JOINTS, PARENTS
from minretarget.pipeline import PipelineConfig
from minretarget.kinematics import forward_kinematics, matrix_to_quaternion
from minretarget.rest_pose import (NUM_BONES, NUM_FEATURES, RestPoseWeights, bone_lengths,
                                   prior_reference, rest_pose_features)
from minretarget.smrm import check_state, initial_state, retarget_step
from minretarget.units import make_space
from minretarget.weights import load_weights, save_weights

torch = pytest.importorskip("torch")

from reference_models import TINY_CONFIG, random_reference  # noqa: E402
from training.export import import_weights, runtime_weights  # noqa: E402
from training.models.rest_pose import torch_prior_reference  # noqa: E402
from training.rest_pose import bone_directions, fit_rest_pose, main  # noqa: E402

# A T-pose skeleton to start from: joints on a plausible body, symmetric in x.
_OFFSETS = {1: (0.09, -0.08, 0), 2: (-0.09, -0.08, 0), 3: (0, 0.11, 0), 4: (0.01, -0.38, 0),
            5: (-0.01, -0.38, 0), 6: (0, 0.13, 0), 7: (0, -0.40, -0.02), 8: (0, -0.40, -0.02),
            9: (0, 0.06, 0.02), 10: (0, -0.06, 0.12), 11: (0, -0.06, 0.12), 12: (0, 0.22, -0.02),
            13: (0.08, 0.12, 0), 14: (-0.08, 0.12, 0), 15: (0, 0.10, 0.04), 16: (0.10, 0.02, 0),
            17: (-0.10, 0.02, 0), 18: (0.26, 0, 0), 19: (-0.26, 0, 0), 20: (0.25, 0, 0),
            21: (-0.25, 0, 0)}


def tpose_skeleton():
    joints = np.zeros((NUM_JOINTS, 3))
    joints[0] = (0, 0.95, 0)
    for child in range(1, NUM_JOINTS):
        joints[child] = joints[PARENTS[child]] + _OFFSETS[child]
    return joints.astype(np.float32)


def random_model(seed=0):
    rng = np.random.default_rng(seed)
    return RestPoseWeights(rng.normal(size=(NUM_FEATURES, 3 * NUM_BONES)).astype(np.float32))


def test_prior_reference_matches_the_numpy_twin():
    rng = np.random.default_rng(1)
    model, tpose = random_model(), tpose_skeleton()
    for _ in range(5):
        lengths = bone_lengths(tpose) * rng.uniform(0.7, 1.3, NUM_BONES).astype(np.float32)
        np.testing.assert_allclose(prior_reference(model, tpose, lengths),
                                   twins.rest_pose_reference(model.directions, tpose, lengths),
                                   atol=2e-6)


def test_same_proportions_leave_the_target_tpose_as_it_is():
    """Bodies with the same (mirror-averaged) bone lengths have the same predicted rest pose:
    the reference is the target's T-pose, and the prior the plain analytic one."""
    model, tpose = random_model(2), tpose_skeleton()
    lengths = bone_lengths(tpose)
    np.testing.assert_allclose(prior_reference(model, tpose, lengths), tpose, atol=1e-6)
    # A source with other, uneven lengths, and the same with left and right exchanged.
    uneven = lengths * np.linspace(0.8, 1.2, NUM_BONES, dtype=np.float32)
    swapped = uneven[np.asarray(MIRROR[1:]) - 1]
    assert np.abs(swapped - uneven).max() > 0.005
    np.testing.assert_allclose(prior_reference(model, tpose, swapped),
                               prior_reference(model, tpose, uneven), atol=1e-6)


def test_reference_keeps_the_target_bone_lengths_and_root_and_turns_its_bones():
    model, tpose = random_model(3), tpose_skeleton()
    lengths = bone_lengths(tpose) * np.linspace(0.8, 1.2, NUM_BONES, dtype=np.float32)
    reference = prior_reference(model, tpose, lengths)
    np.testing.assert_allclose(bone_lengths(reference), bone_lengths(tpose), rtol=1e-5)
    np.testing.assert_array_equal(reference[0], tpose[0])
    assert np.abs(reference - tpose).max() > 1e-3


def test_prior_reference_refuses_bad_lengths():
    model, tpose = random_model(), tpose_skeleton()
    lengths = bone_lengths(tpose)
    lengths[4] = 0.0
    with pytest.raises(ValueError, match="source_lengths must be positive.*bone 4"):
        prior_reference(model, tpose, lengths)
    with pytest.raises(ValueError, match="source_lengths"):
        prior_reference(model, tpose, lengths[:5])


def test_a_bad_model_is_refused_by_name():
    tpose = tpose_skeleton()
    with pytest.raises(ValueError, match=r"rest_pose.directions must have shape \(23, 63\)"):
        prior_reference(RestPoseWeights(np.zeros((22, 63))), tpose, bone_lengths(tpose))
    bad = random_model().directions.copy()
    bad[3, 7] = np.nan
    with pytest.raises(ValueError, match="rest_pose.directions"):
        retarget_step(None, None, tpose, tpose, rest_pose=RestPoseWeights(bad))
    with pytest.raises(ValueError, match="rest_pose must be RestPoseWeights, got ndarray"):
        prior_reference(bad, tpose, bone_lengths(tpose))


def test_torch_twin_matches_the_kernel_batched():
    rng = np.random.default_rng(4)
    model, tpose = random_model(5), tpose_skeleton()
    lengths = (bone_lengths(tpose) * rng.uniform(0.8, 1.2, (2, 3, NUM_BONES))).astype(np.float32)
    got = torch_prior_reference(torch.from_numpy(model.directions),
                                torch.from_numpy(tpose)[None, None], torch.from_numpy(lengths))
    for index in np.ndindex(2, 3):
        np.testing.assert_allclose(got[index].numpy(),
                                   prior_reference(model, tpose, lengths[index]), atol=2e-6)


def synthetic_bodies(count, seed):
    """T-poses whose rest bone directions follow their proportions through a fixed linear
    map of the features (what the model can represent), lengths varied per bone pair."""
    base = tpose_skeleton()
    truth = np.zeros((NUM_FEATURES, 3 * NUM_BONES))    # the same map for every seed
    truth[0] = bone_directions(base).ravel()
    truth[1:-1] = np.random.default_rng(0).normal(0.0, 1.0, (NUM_BONES, 3 * NUM_BONES))
    rng = np.random.default_rng(seed)
    mirror = np.asarray(MIRROR[1:]) - 1
    bodies = []
    for _ in range(count):
        scale = rng.uniform(0.85, 1.15, NUM_BONES)
        scale = np.sqrt(scale * scale[mirror])                 # symmetric bodies
        lengths = bone_lengths(base) * scale
        directions = (rest_pose_features(lengths.astype(np.float32)) @ truth).reshape(-1, 3)
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        joints = np.zeros((NUM_JOINTS, 3))
        joints[0] = base[0]
        for child in range(1, NUM_JOINTS):
            joints[child] = joints[PARENTS[child]] + directions[child - 1] * lengths[child - 1]
        bodies.append(joints)
    return np.asarray(bodies, np.float32)


def angles_degrees(model, bodies):
    features = rest_pose_features(bone_lengths(bodies))
    predicted = (features @ model.directions).reshape(len(bodies), NUM_BONES, 3)
    predicted /= np.linalg.norm(predicted, axis=-1, keepdims=True)
    cosine = (predicted * bone_directions(bodies)).sum(-1)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def test_fit_recovers_rest_directions_and_noise_shrinks_the_fit():
    bodies, held_out = synthetic_bodies(400, seed=6), synthetic_bodies(50, seed=7)
    exact = fit_rest_pose(bodies, noise=0.0, copies=1, ridge=1e-8)
    spread = np.degrees(np.arccos(np.clip(
        (bone_directions(held_out) * bone_directions(held_out).mean(0)).sum(-1)
        / np.linalg.norm(bone_directions(held_out).mean(0), axis=-1), -1, 1)))
    assert spread.mean() > 0.5                          # the bodies do differ (degrees)
    assert angles_degrees(exact, held_out).mean() < 0.05 * spread.mean()
    # Noise on the lengths shrinks the predictions towards the mean body's.
    spreads = []
    for noise in (0.0, 0.05, 0.2):
        model = fit_rest_pose(bodies, noise=noise, copies=10)
        features = rest_pose_features(bone_lengths(held_out))
        spreads.append(np.std(features @ model.directions, axis=0).mean())
    assert spreads[0] > spreads[1] > spreads[2]


def test_fit_command_adds_the_model_to_a_weights_file(tmp_path, monkeypatch):
    model = random_reference(dataclasses.replace(TINY_CONFIG, smrm_analytic_prior=True), 1)
    save_weights(tmp_path / "in.npz", runtime_weights(model.skr, model.smrm, model.skin,
                                                      {"recipe": "tiny"}, model.refine,
                                                      model.denoise))
    monkeypatch.setattr("training.rest_pose.training_tpose_joints",
                        lambda count: synthetic_bodies(count, seed=8))
    main(["--init", str(tmp_path / "in.npz"), "--out", str(tmp_path / "out.npz"),
          "--bodies", "40", "--noise", "0.05"])
    weights = load_weights(tmp_path / "out.npz")
    assert weights.config.rest_pose and weights.rest_pose.directions.shape == (
        NUM_FEATURES, 3 * NUM_BONES)
    assert weights.metadata["recipe"] == "tiny" and weights.metadata["rest_pose"]["bodies"] == 40
    assert weights.metadata["selected_on"] == ["validation", "training dances"]
    np.testing.assert_allclose(
        weights.rest_pose.directions,
        fit_rest_pose(synthetic_bodies(40, seed=8), noise=0.05).directions, atol=1e-6)


def test_fit_command_refuses_weights_without_the_analytic_prior(tmp_path, capsys):
    model = random_reference(TINY_CONFIG, 1)
    save_weights(tmp_path / "in.npz", runtime_weights(model.skr, model.smrm, model.skin, {},
                                                      model.refine, model.denoise))
    with pytest.raises(SystemExit):
        main(["--init", str(tmp_path / "in.npz"), "--out", str(tmp_path / "out.npz")])
    assert "no analytic prior" in capsys.readouterr().err
    assert not (tmp_path / "out.npz").exists()


@pytest.fixture(scope="module")
def prior_weights():
    config = dataclasses.replace(TINY_CONFIG, smrm_analytic_prior=True, rest_pose=True)
    model = random_reference(config, 2)
    weights = runtime_weights(model.skr, model.smrm, model.skin, {}, model.refine,
                              model.denoise)
    return weights._replace(rest_pose=RestPoseWeights(
        fit_rest_pose(synthetic_bodies(200, seed=9), noise=0.05).directions))


def test_smrm_prior_aligns_with_the_reference_from_the_mean_bone_lengths(prior_weights):
    """The rest-pose model only moves the prior: SMRM with it equals SMRM without it fed the
    reference skeleton as its prior's target (same network outputs), and the state keeps
    the mean bone lengths of the frames seen."""
    rng = np.random.default_rng(10)
    tpose = tpose_skeleton()
    source_body = synthetic_bodies(1, seed=11)[0]
    frames = source_body + rng.normal(0.0, 0.01, (6, NUM_JOINTS, 3)).astype(np.float32)
    state, plain_state = None, None
    for t, joints in enumerate(frames):
        rotations, root, state = retarget_step(prior_weights.smrm, state, joints, tpose,
                                               rest_pose=prior_weights.rest_pose)
        mean_lengths = bone_lengths(frames[:t + 1]).mean(0)
        np.testing.assert_allclose(state.source_bone_lengths, mean_lengths, rtol=1e-5)
        reference = prior_reference(prior_weights.rest_pose, tpose, mean_lengths)
        plain, _, plain_state = retarget_step(prior_weights.smrm, plain_state, joints, tpose)
        # the same network correction after the analytic rotation onto either skeleton
        correction = twins.analytic_rotations(joints[None], tpose)[0].transpose(0, 2, 1) \
            @ twins.quaternion_to_matrix(plain)
        want = twins.analytic_rotations(joints[None], reference)[0] @ correction
        np.testing.assert_allclose(twins.quaternion_to_matrix(rotations), want, atol=2e-5)
    assert np.abs(rotations - plain).max() > 1e-3


def test_rest_pose_brings_a_clean_source_closer_to_the_retargeting_truth(prior_weights):
    """With a model fitted on bodies like them, the analytic prior onto the reference poses
    the target like the truth (the source's local rotations on the target's rest skeleton)
    more closely than the plain prior does."""
    bodies = synthetic_bodies(2, seed=12)
    source_rest, target_rest = bodies
    rng = np.random.default_rng(13)
    axis = rng.normal(size=(NUM_JOINTS, 3))
    angle = rng.uniform(0.0, 0.6, (NUM_JOINTS, 1))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    local = np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], -1)[None]
    local = local.astype(np.float32)
    root = np.zeros((1, 3), np.float32)
    source = forward_kinematics(local, root, source_rest)[0][0]
    truth = forward_kinematics(local, root, target_rest)[0][0]
    reference = prior_reference(prior_weights.rest_pose, target_rest, bone_lengths(source))

    def posed(reference_skeleton):
        matrices = twins.analytic_rotations(source[None], reference_skeleton)
        quaternions = matrix_to_quaternion(matrices.astype(np.float32))
        return forward_kinematics(quaternions, root, target_rest)[0][0]

    plain_error = np.linalg.norm(posed(target_rest) - truth, axis=-1).mean()
    rest_error = np.linalg.norm(posed(reference) - truth, axis=-1).mean()
    assert rest_error < 0.5 * plain_error


def test_rest_pose_needs_the_analytic_prior_and_is_recorded_only_when_on(prior_weights):
    with pytest.raises(ValueError, match="rest_pose needs smrm_analytic_prior"):
        ModelConfig(rest_pose=True)

    class Source:
        path, kind, count, fps, space = __file__, "points", 3, 30.0, make_space("m", "y")
        files = None
    records = [run_record(Source, {"points": tpose_skeleton()}, weights, ["npz"],
                          make_space("m", "y"), 2048, 0, PipelineConfig(rest_pose=on))
               for weights, on in ((prior_weights, True), (prior_weights, False),
                                   (prior_weights._replace(rest_pose=None), True))]
    assert [record.get("rest_pose") for record in records] == [True, None, None]


def test_importing_weights_refuses_a_rest_pose_mismatch(prior_weights):
    config = dataclasses.replace(TINY_CONFIG, smrm_analytic_prior=True)
    model = random_reference(config, 4)
    with pytest.raises(ValueError, match="rest_pose=False, the weights have rest-pose model"):
        import_weights(prior_weights, model.skr, model.smrm, model.skin, model.refine,
                       model.denoise)


def test_state_refuses_bad_bone_lengths(prior_weights):
    state = initial_state(prior_weights.smrm, tpose_skeleton())
    with pytest.raises(ValueError, match="source_bone_lengths must be >= 0.*bone 2"):
        check_state(prior_weights.smrm, state._replace(
            source_bone_lengths=np.array([0.1, 0.1, -0.1] + [0.1] * (NUM_BONES - 3),
                                         np.float32)))
    with pytest.raises(ValueError, match="smrm.source_bone_lengths"):
        check_state(prior_weights.smrm, state._replace(source_bone_lengths=np.zeros(3)))
