"""Each numba kernel against its plain NumPy twin (tests/twins.py), and stage properties."""
import numpy as np
import pytest

import twins
from conftest import denoised_stream
from minretarget.conventions import NUM_JOINTS
from minretarget.kinematics import forward_kinematics, skinning_transforms
from minretarget.nn import dense, gru_layer_step, mlp
from minretarget.refine import MAX_POINTS, refine_joints
from minretarget.skin import linear_blend_skinning, skinning_weights
from minretarget.skr import regress_joints
from minretarget.smrm import initial_state, retarget_step


def test_dense_and_mlp_match_twins(tiny_weights):
    rng = np.random.default_rng(0)
    net = tiny_weights.skin
    x = rng.normal(size=(50, net.hidden[0].weight.shape[0])).astype(np.float32)
    for relu in (True, False):
        np.testing.assert_allclose(dense(x, net.hidden[0], relu),
                                   twins.dense(x, net.hidden[0], relu), atol=1e-5)
    np.testing.assert_allclose(mlp(x, net), twins.mlp(x, net), atol=1e-5)


def test_skr_matches_twin_for_any_point_count(tiny_weights):
    rng = np.random.default_rng(1)
    for count in (64, 100, 1000):
        points = rng.normal(size=(count, 3)).astype(np.float32)
        joints = regress_joints(points, tiny_weights.skr)
        assert joints.shape == (NUM_JOINTS, 3) and joints.dtype == np.float32
        np.testing.assert_allclose(joints, twins.pointnet(points, tiny_weights.skr), atol=1e-5)


def test_refiner_matches_twin_for_any_point_count(tiny_weights):
    """Fewer points than neighbours, between, and more than MAX_POINTS (thinned by stride)."""
    rng = np.random.default_rng(5)
    k = tiny_weights.config.refine_neighbours
    for count in (k - 3, 500, MAX_POINTS + 1, 3 * MAX_POINTS):
        points = rng.normal(size=(count, 3)).astype(np.float32)
        joints = rng.normal(size=(NUM_JOINTS, 3)).astype(np.float32)
        refined = refine_joints(points, joints, tiny_weights.refine, k)
        assert refined.shape == (NUM_JOINTS, 3) and refined.dtype == np.float32
        np.testing.assert_allclose(refined, twins.refine_joints(points, joints,
                                                                tiny_weights.refine, k),
                                   atol=1e-5, err_msg=f"{count} points")
        assert np.abs(refined - joints).max() > 1e-3        # it does move the joints


def test_refiner_batches_and_is_translation_equivariant_and_order_invariant(tiny_weights):
    rng = np.random.default_rng(6)
    k, net = tiny_weights.config.refine_neighbours, tiny_weights.refine
    points = rng.normal(size=(2, 300, 3)).astype(np.float32)
    joints = rng.normal(size=(2, NUM_JOINTS, 3)).astype(np.float32)
    batch = refine_joints(points, joints, net, k)
    for b in range(2):
        np.testing.assert_allclose(batch[b], refine_joints(points[b], joints[b], net, k),
                                   atol=1e-6)
    shift = np.float32([5.0, -2.0, 3.0])
    np.testing.assert_allclose(refine_joints(points[0] + shift, joints[0] + shift, net, k),
                               batch[0] + shift, atol=1e-4)
    np.testing.assert_allclose(refine_joints(rng.permutation(points[0]), joints[0], net, k),
                               batch[0], atol=1e-5)
    with pytest.raises(ValueError, match="joints"):
        refine_joints(points, joints[0], net, k)
    with pytest.raises(ValueError, match="joints"):
        refine_joints(points[0], joints[0, :5], net, k)
    with pytest.raises(ValueError, match="neighbours"):
        refine_joints(points[0], joints[0], net, 0)
    with pytest.raises(ValueError, match="P >= 1"):
        refine_joints(points[0, :0], joints[0], net, k)
    assert refine_joints(points[:0], joints[:0], net, k).shape == (0, NUM_JOINTS, 3)


def test_skr_is_translation_equivariant_and_order_invariant(tiny_weights):
    rng = np.random.default_rng(2)
    points = rng.normal(size=(300, 3)).astype(np.float32)
    joints = regress_joints(points, tiny_weights.skr)
    shift = np.float32([5.0, -2.0, 3.0])
    np.testing.assert_allclose(regress_joints(points + shift, tiny_weights.skr), joints + shift,
                               atol=1e-4)
    np.testing.assert_allclose(regress_joints(rng.permutation(points), tiny_weights.skr),
                               joints, atol=1e-5)


def test_skr_batch_equals_per_item_calls(tiny_weights):
    batch = np.random.default_rng(3).normal(size=(5, 128, 3)).astype(np.float32)
    joints = regress_joints(batch, tiny_weights.skr)
    side_by_side = regress_joints(batch, tiny_weights.skr, workers=3)    # clouds on 3 threads
    for b in range(5):
        np.testing.assert_array_equal(joints[b], regress_joints(batch[b], tiny_weights.skr))
        np.testing.assert_array_equal(side_by_side[b], joints[b])
        shared = regress_joints(batch[b], tiny_weights.skr, workers=3)     # points on 3 threads
        np.testing.assert_allclose(shared, joints[b], atol=1e-6)


def test_gru_layer_step_matches_twin(tiny_weights):
    rng = np.random.default_rng(4)
    layer = tiny_weights.smrm.encoder[0]
    x = rng.normal(size=(1, layer.input_weight.shape[0])).astype(np.float32)
    h = rng.normal(size=(1, layer.hidden_weight.shape[0])).astype(np.float32)
    np.testing.assert_allclose(gru_layer_step(x, h, layer), twins.gru_layer_step(x, h, layer),
                               atol=1e-6)


@pytest.mark.parametrize("target_leg_length", [None, 0.9])
def test_retarget_step_matches_twin_and_streams(tiny_weights, target_leg_length):
    """Three frames through the kernel against the twin GRU stack and heads; the root scaled
    by the target skeleton's legs, or by a leg length given."""
    rng = np.random.default_rng(5)
    smrm = tiny_weights.smrm
    tpose = rng.normal(size=(NUM_JOINTS, 3)).astype(np.float32)
    frames = rng.normal(size=(3, NUM_JOINTS, 3)).astype(np.float32)
    state = None
    hidden = np.zeros((2, len(smrm.encoder), 1, smrm.encoder[0].hidden_weight.shape[0]))
    previous_root, legs = frames[0, 0], []
    for t, joints in enumerate(frames):
        rotations, root, state = retarget_step(smrm, state, joints, tpose,
                                               target_leg_length=target_leg_length)
        x, turn = twins.heading_features(joints, previous_root)
        for i, layer in enumerate(smrm.encoder):
            x = hidden[0, i] = twins.gru_layer_step(x, hidden[0, i], layer)
        x = np.concatenate([x, (tpose - tpose[0]).ravel()[None]], axis=1)
        for i, layer in enumerate(smrm.decoder):
            x = hidden[1, i] = twins.gru_layer_step(x, hidden[1, i], layer)
        q = twins.dense(x, smrm.rotation_head, False).reshape(-1, 4)
        matrices = twins.quaternion_to_matrix(q)
        matrices[0] = turn @ matrices[0]
        np.testing.assert_allclose(twins.quaternion_to_matrix(rotations), matrices, atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(rotations, axis=1), 1.0, atol=1e-5)
        legs.append(twins_leg_length(joints))
        target_legs = twins_leg_length(tpose) if target_leg_length is None else 0.9
        scale = target_legs / np.mean(legs)                     # mean over the frames so far
        np.testing.assert_allclose(root, scale * joints[0]
                                   + turn @ twins.dense(x, smrm.root_head, False)[0], atol=1e-5)
        previous_root = joints[0]
    assert state.frames_seen == 3


def test_denoiser_matches_twin_and_turns_with_the_body(tiny_weights):
    rng = np.random.default_rng(8)
    frames = (rng.normal(0, 0.3, (1, NUM_JOINTS, 3))
              + np.cumsum(rng.normal(0, 0.02, (12, NUM_JOINTS, 3)), axis=0)).astype(np.float32)
    denoised = denoised_stream(tiny_weights.denoise, frames)
    np.testing.assert_allclose(denoised, twins.denoise(frames, tiny_weights.denoise), atol=1e-5)
    assert np.abs(denoised - frames).max() > 1e-3           # it does move the joints
    # Turned about +Y and shifted, the stream's corrections turn and shift with it.
    angle = 1.1
    turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                     [-np.sin(angle), 0, np.cos(angle)]], np.float32)
    moved = (frames @ turn.T + [3.0, 0.0, -2.0]).astype(np.float32)
    np.testing.assert_allclose(denoised_stream(tiny_weights.denoise, moved),
                               denoised @ turn.T + [3.0, 0.0, -2.0], atol=1e-4)
    # Mirror-averaged: the mirror image's stream gets the mirrored corrections, exactly.
    np.testing.assert_allclose(denoised_stream(tiny_weights.denoise, twins.mirrored(frames)),
                               twins.mirrored(denoised), atol=1e-5)


def test_the_stages_smooth_then_denoise_then_retarget(tiny_weights, tiny_stream):
    """A frame goes down the stages in order: smoothing, then the denoiser on the smoothed
    joints (its previous root the smoothed one), then SMRM on the result as on clean joints;
    each stage keeps its own state."""
    from minretarget.pipeline import PipelineConfig
    from minretarget.retargeter import Retargeter
    from minretarget.smoothing import Smoothing
    rng = np.random.default_rng(9)
    frames = (rng.normal(0, 0.3, (1, NUM_JOINTS, 3))
              + np.cumsum(rng.normal(0, 0.02, (8, NUM_JOINTS, 3)), axis=0)).astype(np.float32)
    smoothed = twins.alpha_beta(frames, *Smoothing())
    denoised = twins.denoise(smoothed.astype(np.float32), tiny_weights.denoise)
    retargeter = Retargeter(tiny_weights, PipelineConfig(rest_pose=False, foot_lock=None),
                            warn=False)
    retargeter.set_target(tiny_stream[0])
    assert [stage.name for stage in retargeter.stages] == [
        "skr", "facing_check", "smoothing", "denoiser", "smrm", "fk", "lbs"]
    tpose, clean = retargeter.target.tpose_joints, None
    for t in range(len(frames)):
        frame = retargeter.step_skeleton(frames[t])
        want_rotations, want_root, clean = retarget_step(tiny_weights.smrm, clean,
                                                         denoised[t], tpose)
        np.testing.assert_allclose(frame.source_joints, denoised[t], atol=1e-5)
        np.testing.assert_allclose(retargeter.state.stages["smoothing"].joints, smoothed[t],
                                   atol=1e-5)
        np.testing.assert_allclose(frame.rotations, want_rotations, atol=1e-4)
        np.testing.assert_allclose(frame.root, want_root, atol=1e-4)
    assert retargeter.state.frames_seen == len(frames)
    assert retargeter.state.stages["smrm"].frames_seen == len(frames)


def twins_leg_length(joints):
    return sum(np.linalg.norm(joints[a] - joints[b]) for a, b in
               ((4, 1), (7, 4), (5, 2), (8, 5))) / 2


def test_initial_state_is_zero_with_the_first_root(tiny_weights):
    joints = np.random.default_rng(6).normal(size=(NUM_JOINTS, 3)).astype(np.float32)
    state = initial_state(tiny_weights.smrm, joints)
    assert not state.encoder_hidden.any() and not state.decoder_hidden.any()
    np.testing.assert_array_equal(state.previous_root, joints[0])
    assert not state.source_bone_lengths.any() and state.frames_seen == 0


def test_skinning_weights_match_twin_and_are_a_partition_of_unity(tiny_weights):
    rng = np.random.default_rng(7)
    points = rng.normal(size=(5000, 3)).astype(np.float32)   # more than one chunk
    tpose = rng.normal(size=(NUM_JOINTS, 3)).astype(np.float32)
    weights = skinning_weights(points, tpose, tiny_weights.skin, chunk=2048)
    np.testing.assert_allclose(weights, twins.skinning_weights(points, tpose, tiny_weights.skin),
                               atol=1e-6)
    assert (weights >= 0).all()
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-5)


def test_lbs_matches_twin():
    rng = np.random.default_rng(8)
    points = rng.normal(size=(400, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(NUM_JOINTS), size=400).astype(np.float32)
    tpose = rng.normal(size=(NUM_JOINTS, 3)).astype(np.float32)
    joints, rotations = forward_kinematics(rng.normal(size=(NUM_JOINTS, 4)), rng.normal(size=3),
                                           tpose)
    transforms = skinning_transforms(joints, rotations, tpose)
    np.testing.assert_allclose(linear_blend_skinning(points, weights, transforms),
                               twins.linear_blend_skinning(points, weights, transforms), atol=1e-5)


def test_lbs_of_many_frames_is_each_frame_posed_alone():
    """(T, J, 3, 4) over several chunks equals T single-frame twins."""
    rng = np.random.default_rng(11)
    points = rng.normal(size=(300, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(NUM_JOINTS), size=300).astype(np.float32)
    transforms = rng.normal(size=(7, NUM_JOINTS, 3, 4)).astype(np.float32)
    posed = linear_blend_skinning(points, weights, transforms, chunk=3)
    assert posed.shape == (7, 300, 3)
    for frame, maps in zip(posed, transforms):
        np.testing.assert_allclose(frame, twins.linear_blend_skinning(points, weights, maps),
                                   atol=1e-5)


def test_lbs_with_identity_transforms_returns_its_input():
    rng = np.random.default_rng(9)
    points = rng.normal(size=(100, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(NUM_JOINTS), size=100).astype(np.float32)
    identity = np.tile(np.eye(3, 4, dtype=np.float32), (NUM_JOINTS, 1, 1))
    np.testing.assert_allclose(linear_blend_skinning(points, weights, identity), points,
                               atol=1e-6)


def test_lbs_with_a_rigid_motion_moves_points_rigidly():
    """Weights summing to one blend identical maps into that map."""
    rng = np.random.default_rng(10)
    points = rng.normal(size=(100, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(NUM_JOINTS), size=100).astype(np.float32)
    rotation = twins.quaternion_to_matrix(rng.normal(size=4))
    shift = rng.normal(size=3)
    transforms = np.tile(np.concatenate([rotation, shift[:, None]], 1), (NUM_JOINTS, 1, 1))
    np.testing.assert_allclose(linear_blend_skinning(points, weights, transforms),
                               points @ rotation.T + shift, atol=1e-5)


def test_stage_inputs_are_validated(tiny_weights):
    with pytest.raises(ValueError, match="at least 64"):
        regress_joints(np.zeros((10, 3)), tiny_weights.skr)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., any, 3\)"):
        regress_joints(np.zeros((100, 2)), tiny_weights.skr)
    with pytest.raises(ValueError, match="skin_weights must have shape"):
        linear_blend_skinning(np.zeros((5, 3)), np.zeros((4, 22)), np.zeros((22, 3, 4)))
    with pytest.raises(ValueError, match="source_joints"):
        retarget_step(tiny_weights.smrm, None, np.zeros((21, 3)), np.zeros((22, 3)))
    for bad in (0.0, -1.0, float("nan"), 1e39, np.ones(2), "0.8", True, 1j):
        with pytest.raises(ValueError, match="target_leg_length must be a finite length > 0"):
            retarget_step(tiny_weights.smrm, None, np.zeros((22, 3)), np.zeros((22, 3)),
                          target_leg_length=bad)


def test_retarget_step_is_equivariant_to_turns_about_up(tiny_weights):
    """A source motion turned about +Y gives the same motion turned: the root's rotation and
    path turn, every other local rotation is unchanged."""
    rng = np.random.default_rng(11)
    tpose = rng.normal(size=(NUM_JOINTS, 3)).astype(np.float32)
    frames = rng.normal(size=(4, NUM_JOINTS, 3)).astype(np.float32)
    angle = 2.5
    turn = twins.quaternion_to_matrix([np.cos(angle / 2), 0, np.sin(angle / 2), 0])
    state = turned_state = None
    for joints in frames:
        rotations, root, state = retarget_step(tiny_weights.smrm, state, joints, tpose)
        turned, turned_root, turned_state = retarget_step(
            tiny_weights.smrm, turned_state, joints @ turn.T.astype(np.float32), tpose)
        np.testing.assert_allclose(turned_root, turn @ root, atol=1e-4)
        np.testing.assert_allclose(twins.quaternion_to_matrix(turned[0]),
                                   turn @ twins.quaternion_to_matrix(rotations[0]), atol=1e-4)
        np.testing.assert_allclose(np.abs((turned[1:] * rotations[1:]).sum(-1)), 1, atol=1e-4)
