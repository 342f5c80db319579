"""Tests of minretarget.metrics: hand-computed cases, a slow twin of the alignment, properties."""
import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from minretarget.conventions import FPS, JOINT_INDEX
from minretarget.metrics import (
    METRIC_NAMES, acceleration_error, crossed_feet, evaluate, foot_contacts, foot_sliding,
    foot_speeds, jitter, joint_errors, knn_edges, mean_point_error, medl, mpjpe, mpvd,
    pa_acceleration_error, pa_mpjpe, pa_mpvd, procrustes_align, skating_steps)


# ----------------------------------------------------------------------------- helpers

def rotation_from_quaternion(q):
    """(4,) quaternion (w, x, y, z), any norm -> (3, 3) float64 rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def naive_procrustes_align(pred, gt):
    """Slow twin of ``procrustes_align`` by another method: Horn's (1987) quaternion solution,
    one (N, 3) set at a time. The best proper rotation is the top eigenvector of a symmetric
    4x4 matrix, so reflections cannot occur by construction."""
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    out = np.empty_like(pred)
    for index in np.ndindex(pred.shape[:-2]):
        x = pred[index] - pred[index].mean(axis=0)
        y = gt[index] - gt[index].mean(axis=0)
        s = x.T @ y                                      # s[a, b] = sum_n x_a y_b
        (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = s
        horn = np.array([
            [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
            [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
            [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
            [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
        ])
        _, vectors = np.linalg.eigh(horn)
        rotation = rotation_from_quaternion(vectors[:, -1])
        rotated = x @ rotation.T
        scale = np.sum(y * rotated) / np.sum(x * x)
        out[index] = scale * rotated + gt[index].mean(axis=0)
    return out


def random_rotation(rng):
    return rotation_from_quaternion(rng.normal(size=4))


# Four points for hand computation, and a generic chiral cloud.
CORNER = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
# 90 degrees about +Y: (x, y, z) -> (z, y, -x).
ROT_Y_90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
CUBE = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])


# ----------------------------------------------------------------------------- MPJPE / MPVD

def test_constant_offset_of_3_4_0_cm_gives_5_cm():
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(7, 22, 3))
    pred = gt + np.array([0.03, 0.04, 0.0])
    assert mpjpe(pred, gt) == pytest.approx(0.05, abs=1e-15)
    assert mpvd(pred, gt) == pytest.approx(0.05, abs=1e-15)
    assert pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-12)
    assert pa_mpvd(pred, gt) == pytest.approx(0.0, abs=1e-12)


def test_similarity_copy_by_hand():
    # pred = 2 R gt + (0, 0, 1), R = 90 degrees about +Y. Per point, by hand:
    # (1,0,0) -> (0,0,-1): sqrt(2); (0,1,0) -> (0,2,1): sqrt(2); (0,0,1) -> (2,0,1): 2;
    # (0,0,0) -> (0,0,1): 1.
    gt = CORNER[None]                                                # (1, 4, 3)
    pred = 2.0 * gt @ ROT_Y_90.T + np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(pred[0], [[0, 0, -1], [0, 2, 1], [2, 0, 1], [0, 0, 1]])
    assert mpjpe(pred, gt) == pytest.approx((2 * math.sqrt(2) + 3) / 4, abs=1e-15)
    assert pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(procrustes_align(pred, gt), gt, atol=1e-12)


def test_mean_over_frames_and_points():
    gt = np.zeros((2, 2, 3))
    pred = np.array([[[1.0, 0, 0], [0, 2.0, 0]], [[0, 0, 3.0], [0, 0, 0]]])
    assert mean_point_error(pred, gt) == pytest.approx((1 + 2 + 3 + 0) / 4)


def test_float32_input_is_computed_in_float64():
    rng = np.random.default_rng(1)
    gt = rng.normal(size=(3, 22, 3)).astype(np.float32)
    pred = (gt + rng.normal(scale=0.01, size=gt.shape)).astype(np.float32)
    assert isinstance(pa_mpjpe(pred, gt), float)
    assert pa_mpjpe(pred, gt) == pa_mpjpe(pred.astype(np.float64), gt.astype(np.float64))
    assert procrustes_align(pred, gt).dtype == np.float64


# ----------------------------------------------------------------------------- Procrustes

def test_procrustes_matches_horn_twin_over_batch_dims():
    rng = np.random.default_rng(2)
    gt = rng.normal(size=(2, 5, 22, 3))
    # Noisy similarity copies, half of them mirrored so that the det < 0 branch is taken.
    pred = np.empty_like(gt)
    for index in np.ndindex(2, 5):
        mirror = np.diag([-1.0, 1.0, 1.0]) if index[1] % 2 else np.eye(3)
        pred[index] = (rng.uniform(0.5, 2.0) * gt[index] @ (random_rotation(rng) @ mirror).T
                       + rng.normal(size=3) + rng.normal(scale=0.1, size=(22, 3)))
    np.testing.assert_allclose(procrustes_align(pred, gt), naive_procrustes_align(pred, gt),
                               atol=1e-10)


def test_reflected_copy_is_not_aligned_to_zero():
    rng = np.random.default_rng(3)
    gt = rng.normal(size=(4, 22, 3))                                 # generic, so chiral
    pred = gt * np.array([-1.0, 1.0, 1.0])                           # mirror x
    aligned = procrustes_align(pred, gt)
    assert pa_mpjpe(pred, gt) > 0.1
    np.testing.assert_allclose(aligned, naive_procrustes_align(pred, gt), atol=1e-10)
    # The aligned set is a proper similarity image of pred: same handedness, so the signed
    # volume of any 4 points keeps its sign (det > 0 times scale^3).
    def volumes(points):                                             # (T, N, 3) -> (T,)
        return np.linalg.det(points[:, 1:4] - points[:, :1])
    assert np.all(np.sign(volumes(aligned)) == np.sign(volumes(pred)))
    # While an alignment allowed to reflect would fit exactly: the minimum is really lost.
    assert np.all(np.sign(volumes(pred)) != np.sign(volumes(gt)))


def test_collapsed_prediction_lands_on_gt_centroid():
    gt = CORNER[None]
    pred = np.ones((1, 4, 3))
    np.testing.assert_allclose(procrustes_align(pred, gt), np.broadcast_to(gt.mean(1), (1, 4, 3)))


def test_procrustes_shape_errors():
    with pytest.raises(ValueError,
                       match=r"pred and gt must have the same shape.*\(4, 3\).*\(5, 3\)"):
        procrustes_align(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"pred must have shape \(\.\.\., N, 3\), got \(4, 2\)"):
        procrustes_align(np.zeros((4, 2)), np.zeros((4, 2)))


# ----------------------------------------------------------------------------- Acc / PA-Acc

def test_constant_velocity_against_static_gt_has_zero_acceleration_error():
    rng = np.random.default_rng(4)
    start = rng.normal(size=(22, 3))
    t = np.arange(10.0)[:, None, None]
    pred = start + t * np.array([0.1, -0.2, 0.05])                   # (10, 22, 3)
    gt = np.broadcast_to(start, pred.shape)
    assert acceleration_error(pred, gt) == pytest.approx(0.0, abs=1e-14)
    assert mpjpe(pred, gt) > 0


def test_quadratic_trajectory_has_known_second_difference():
    # x(t) = a + b t + c t^2 has second difference 2 c at every frame; |2 c| = 2 * 0.03.
    c = np.array([0.01, 0.02, -0.02])
    t = np.arange(6.0)[:, None, None]
    pred = 0.5 + np.array([0.3, 0.0, -0.1]) * t + c * t ** 2       # (6, 1, 3)
    gt = np.zeros_like(pred)
    assert acceleration_error(pred, gt) == pytest.approx(0.06, abs=1e-13)
    # Relative to a gt with the same acceleration, the error vanishes.
    assert acceleration_error(pred, gt + c * t ** 2) == pytest.approx(0.0, abs=1e-13)


def test_pa_acceleration_forgives_per_frame_similarity():
    rng = np.random.default_rng(5)
    gt = np.cumsum(rng.normal(scale=0.01, size=(8, 22, 3)), axis=0) + rng.normal(size=(22, 3))
    pred = np.stack([rng.uniform(0.8, 1.2) * frame @ random_rotation(rng).T + rng.normal(size=3)
                     for frame in gt])
    assert acceleration_error(pred, gt) > 0.1
    assert pa_acceleration_error(pred, gt) == pytest.approx(0.0, abs=1e-12)


def test_acceleration_needs_three_frames():
    two = np.zeros((2, 22, 3))
    for metric in (acceleration_error, pa_acceleration_error):
        with pytest.raises(ValueError, match=r"pred and gt need at least 3 frame.*T = 2"):
            metric(two, two)
    assert acceleration_error(np.zeros((3, 22, 3)), np.zeros((3, 22, 3))) == 0.0


# ----------------------------------------------------------------------------- MEDL

def test_knn_edges_of_a_cube_are_its_12_edges():
    edges = knn_edges(CUBE, k=3)
    assert edges.shape == (12, 2)
    assert np.all(edges[:, 0] < edges[:, 1])
    np.testing.assert_allclose(np.linalg.norm(CUBE[edges[:, 0]] - CUBE[edges[:, 1]], axis=1), 1.0)


def test_knn_edges_with_duplicate_points_have_no_self_loops():
    points = np.concatenate([CUBE, CUBE[:2]])                        # two points twice
    edges = knn_edges(points, k=3)
    assert np.all(edges[:, 0] != edges[:, 1])
    assert {(0, 8), (1, 9)} <= set(map(tuple, edges.tolist()))     # each duplicate is nearest


def test_medl_of_scaled_cube_by_hand():
    # Side 0.2 m, k = 3: the graph is the 12 cube edges, each stretched from 0.2 to 0.2 s.
    gt = np.stack([0.2 * CUBE, 0.2 * CUBE + 1.0])                    # (2, 8, 3)
    s = 1.5
    pred = s * gt
    assert medl(pred, gt, k=3) == pytest.approx((s - 1) * 0.2, abs=1e-15)


def test_medl_of_scaled_cloud_is_scale_minus_one_times_mean_edge_length():
    rng = np.random.default_rng(6)
    gt = rng.normal(size=(3, 300, 3))
    edges = knn_edges(gt[0], k=6)
    lengths = np.linalg.norm(gt[:, edges[:, 0]] - gt[:, edges[:, 1]], axis=-1)  # (T, E)
    assert medl(1.1 * gt, gt) == pytest.approx(0.1 * lengths.mean(), rel=1e-12)


def test_medl_of_rigidly_moved_cloud_is_zero():
    rng = np.random.default_rng(7)
    gt = rng.normal(size=(4, 200, 3))
    pred = np.stack([frame @ random_rotation(rng).T + rng.normal(size=3) for frame in gt])
    assert mpvd(pred, gt) > 0.1
    assert medl(pred, gt) == pytest.approx(0.0, abs=1e-12)


def test_medl_builds_its_graph_once_on_rest_or_first_frame():
    rng = np.random.default_rng(8)
    gt = rng.normal(size=(3, 50, 3))
    pred = gt + rng.normal(scale=0.05, size=gt.shape)
    rest = rng.normal(size=(50, 3))

    def by_hand(graph_points):
        i, j = knn_edges(graph_points, k=6).T
        pred_length = np.linalg.norm(pred[:, i] - pred[:, j], axis=-1)
        gt_length = np.linalg.norm(gt[:, i] - gt[:, j], axis=-1)
        return np.abs(pred_length - gt_length).mean()

    assert medl(pred, gt) == pytest.approx(by_hand(gt[0]), rel=1e-12)
    assert medl(pred, gt, rest=rest) == pytest.approx(by_hand(rest), rel=1e-12)
    assert medl(pred, gt, rest=rest) != pytest.approx(medl(pred, gt), rel=1e-6)


def test_medl_kernel_matches_the_numpy_formula():
    """The edge loop against (T, E) arrays of edge lengths, on a random noisy sequence."""
    rng = np.random.default_rng(11)
    gt = rng.normal(size=(7, 40, 3))
    pred = gt + rng.normal(scale=0.05, size=gt.shape)
    i, j = knn_edges(gt[0]).T
    lengths = [np.linalg.norm(x[:, i] - x[:, j], axis=-1) for x in (pred, gt)]   # (T, E)
    assert medl(pred, gt) == pytest.approx(np.abs(lengths[0] - lengths[1]).mean(), rel=1e-12)


def test_medl_errors():
    gt = np.zeros((2, 5, 3))
    with pytest.raises(ValueError, match=r"k must satisfy 1 <= k < V, got k = 6 for 5 points"):
        medl(gt, gt)
    with pytest.raises(ValueError, match=r"rest must have shape \(V, 3\) with V = 5.*\(4, 3\)"):
        medl(gt, gt, k=2, rest=np.zeros((4, 3)))


# ----------------------------------------------------------------------------- shape errors

@pytest.mark.parametrize("metric", [mpjpe, pa_mpjpe, mpvd, pa_mpvd, acceleration_error,
                                    pa_acceleration_error, medl])
def test_metrics_refuse_bad_shapes_and_values(metric):
    good = np.zeros((4, 22, 3))
    with pytest.raises(ValueError, match=r"pred and gt must have the same shape.*"
                                         r"pred \(4, 22, 3\) and gt \(4, 21, 3\)"):
        metric(good, np.zeros((4, 21, 3)))
    with pytest.raises(ValueError, match=r"pred and gt must have the same shape.*\(5, 22, 3\)"):
        metric(good, np.zeros((5, 22, 3)))
    with pytest.raises(ValueError, match=r"pred must have shape \(T, N, 3\), got \(22, 3\)"):
        metric(np.zeros((22, 3)), good)
    with pytest.raises(ValueError, match=r"gt must have shape \(T, N, 3\), got \(4, 22, 4\)"):
        metric(good, np.zeros((4, 22, 4)))
    with pytest.raises(ValueError, match=r"must have shape \(T, N, 3\), got \(2, 4, 22, 3\)"):
        metric(np.zeros((2, 4, 22, 3)), np.zeros((2, 4, 22, 3)))
    bad = good.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"gt has a non-finite value nan at index \(1, 2, 0\)"):
        metric(good, bad)


# ----------------------------------------------------------------------------- evaluate

def test_evaluate_returns_every_metric_as_the_single_functions_do():
    rng = np.random.default_rng(9)
    gt_joints = rng.normal(size=(6, 22, 3))
    gt_points = rng.normal(size=(6, 100, 3))
    pred_joints = gt_joints + rng.normal(scale=0.05, size=gt_joints.shape)
    pred_points = 1.05 * gt_points + rng.normal(scale=0.02, size=gt_points.shape)
    result = evaluate(pred_joints, gt_joints, pred_points, gt_points)
    assert tuple(result) == METRIC_NAMES
    assert set(result) == {"MPJPE", "PA-MPJPE", "Acc", "PA-Acc", "MPVD", "PA-MPVD", "MEDL"}
    assert all(type(value) is float for value in result.values())
    expected = {
        "MPJPE": mpjpe(pred_joints, gt_joints),
        "PA-MPJPE": pa_mpjpe(pred_joints, gt_joints),
        "Acc": acceleration_error(pred_joints, gt_joints),
        "PA-Acc": pa_acceleration_error(pred_joints, gt_joints),
        "MPVD": mpvd(pred_points, gt_points),
        "PA-MPVD": pa_mpvd(pred_points, gt_points),
        "MEDL": medl(pred_points, gt_points),
    }
    assert result == pytest.approx(expected, rel=1e-12)


def test_evaluate_names_the_bad_argument():
    joints = np.zeros((5, 22, 3))
    points = np.zeros((5, 30, 3))
    with pytest.raises(ValueError, match=r"pred_points and gt_points must have the same shape"):
        evaluate(joints, joints, points, np.zeros((5, 31, 3)))
    with pytest.raises(ValueError, match=r"pred_joints and gt_joints need at least 3 frame"):
        evaluate(joints[:2], joints[:2], points[:2], points[:2])
    with pytest.raises(ValueError, match=r"same number of frames T.*\(5, 22, 3\).*\(4, 30, 3\)"):
        evaluate(joints, joints, points[:4], points[:4])


# ----------------------------------------------------------------------------- properties

coordinates = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)


similarity = dict(quaternion=arrays(np.float64, (4,), elements=coordinates),
                  scale=st.floats(0.01, 100.0),
                  translation=arrays(np.float64, (3,), elements=st.floats(-10.0, 10.0)))
point_sets = arrays(np.float64, st.tuples(st.integers(1, 3), st.integers(3, 30), st.just(3)),
                    elements=coordinates)


@settings(max_examples=200, deadline=None)
@given(points=point_sets, **similarity)
def test_pa_mpjpe_of_a_similarity_copy_is_zero(points, quaternion, scale, translation):
    assume(np.linalg.norm(quaternion) > 0.1)
    pred = scale * points @ rotation_from_quaternion(quaternion).T + translation
    assert pa_mpjpe(pred, points) <= 1e-9 * (1.0 + np.abs(points).max())


@settings(max_examples=200, deadline=None)
@given(points=point_sets, **similarity)
def test_pa_mpjpe_ignores_a_similarity_of_pred(points, quaternion, scale, translation):
    assume(np.linalg.norm(quaternion) > 0.1)
    # Sets that (nearly) collapse to one point are left out: there, rounding in the transform
    # decides whether pred still spans a direction to fit, or aligns onto the gt centroid.
    assume(np.all(np.ptp(points, axis=1).max(axis=-1) > 1e-3))
    pred = scale * points @ rotation_from_quaternion(quaternion).T + translation
    gt = points + np.linspace(-0.1, 0.1, points.size).reshape(points.shape)
    assert pa_mpjpe(pred, gt) == pytest.approx(pa_mpjpe(points, gt), abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(pred=arrays(np.float64, (2, 12, 3), elements=coordinates),
       gt=arrays(np.float64, (2, 12, 3), elements=coordinates))
def test_procrustes_never_increases_the_squared_error(pred, gt):
    # What the alignment minimises is the sum of squared distances; the identity is one of the
    # candidates, so per frame the aligned squared error is at most the raw one.
    aligned = procrustes_align(pred, gt)
    aligned_sq = np.sum((aligned - gt) ** 2, axis=(1, 2))
    raw_sq = np.sum((pred - gt) ** 2, axis=(1, 2))
    assert np.all(aligned_sq <= raw_sq + 1e-9)


def test_pa_mpjpe_can_exceed_mpjpe():
    # Not a bug: PA minimises squared distances, MPJPE averages distances. One outlier joint
    # 1 m off gives MPJPE 1/22 m; the least-squares fit spreads it over every joint.
    rng = np.random.default_rng(10)
    gt = rng.normal(size=(1, 22, 3))
    pred = gt.copy()
    pred[0, 0] += np.array([1.0, 0.0, 0.0])
    assert mpjpe(pred, gt) == pytest.approx(1 / 22)
    assert pa_mpjpe(pred, gt) > mpjpe(pred, gt)


# ----------------------------------------------------------------------------- jitter, feet

def _feet_walk(left, right, frames=5):
    """(T, 22, 3) joints, all at the origin but the two feet, given as (T, 3) arrays."""
    from minretarget.conventions import JOINT_INDEX
    joints = np.zeros((frames, 22, 3))
    joints[:, JOINT_INDEX["left_foot"]] = left
    joints[:, JOINT_INDEX["right_foot"]] = right
    return joints


def test_jitter_hand_computed():
    t = np.arange(5.0)
    still = np.zeros((5, 2, 3))
    assert jitter(still) == 0.0
    constant_speed = np.zeros((5, 1, 3))
    constant_speed[:, 0, 0] = 2.0 * t                 # second difference 0
    assert jitter(constant_speed) == pytest.approx(0.0, abs=1e-12)
    accelerating = np.zeros((5, 2, 3))
    accelerating[:, 0, 1] = 0.5 * t ** 2              # second difference 1 m/frame^2
    accelerating[:, 1, 2] = 1.5 * t ** 2              # 3 m/frame^2
    assert jitter(accelerating) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="3 frames"):
        jitter(np.zeros((2, 1, 3)))


def test_foot_sliding_hand_computed():
    t = np.arange(5.0)
    zeros = np.zeros(5)
    planted = np.stack([zeros + 0.3, zeros + 0.05, zeros], axis=-1)       # never moves
    dragged = np.stack([t / 30.0, zeros, zeros], axis=-1)                 # 1 m/s on the floor
    # Both planted: 0. One planted, one dragged at 1 m/s: 8 contact steps, 4 of them at 1 m/s.
    assert foot_sliding(_feet_walk(planted, planted)) == 0.0
    assert foot_sliding(_feet_walk(dragged, dragged)) == pytest.approx(1.0)
    assert foot_sliding(_feet_walk(planted, dragged)) == pytest.approx(0.5)
    # A foot moving fast in the air (0.2 m above its lowest point from frame 1 on) is never in
    # contact (its only low frame, 0, has its next frame in the air), so it is not counted.
    flying = np.stack([3.0 * t, np.where(t > 0, 0.2, 0.0), zeros], axis=-1)
    contact = foot_contacts(_feet_walk(planted, flying))
    assert contact[:, 0].all() and not contact[:, 1].any()
    assert foot_sliding(_feet_walk(planted, flying)) == 0.0
    # Heights within contact_height of the lowest count, and only horizontal speed counts:
    # bobbing 2 cm up and down while dragged at 1 m/s is contact at 1 m/s; with a 1 cm
    # threshold no step has both frames low.
    bobbing = dragged + np.stack([zeros, 0.02 * (t % 2), zeros], axis=-1)
    assert foot_sliding(_feet_walk(bobbing, bobbing), contact_height=0.03) == pytest.approx(1.0)
    assert math.isnan(foot_sliding(_feet_walk(bobbing, bobbing), contact_height=0.01))
    # fps scales the speed; no contact at all gives nan.
    assert foot_sliding(_feet_walk(dragged, dragged), fps=60) == pytest.approx(2.0)
    # Per step and foot: horizontal speed only (the bobbing foot's 2 cm a frame up and down
    # do not count).
    np.testing.assert_allclose(foot_speeds(_feet_walk(planted, bobbing)), [[0, 1]] * 4)
    assert math.isnan(foot_sliding(_feet_walk(flying, flying), contact_height=-1.0))


def _standing(frames, ankle_gap=0.2):
    """(T, J, 3) a T-pose-like skeleton: hips along x (left at +x), ankles ``ankle_gap``
    apart, at rest."""
    joints = np.zeros((frames, 22, 3))
    joints[:, JOINT_INDEX["left_hip"], 0], joints[:, JOINT_INDEX["right_hip"], 0] = 0.1, -0.1
    joints[:, JOINT_INDEX["left_ankle"], 0] = ankle_gap / 2
    joints[:, JOINT_INDEX["right_ankle"], 0] = -ankle_gap / 2
    return joints


def test_crossed_feet_by_hand():
    truth = _standing(3)
    swapped = truth.copy()
    swapped[:, [JOINT_INDEX["left_ankle"], JOINT_INDEX["right_ankle"]]] = \
        truth[:, [JOINT_INDEX["right_ankle"], JOINT_INDEX["left_ankle"]]]
    np.testing.assert_array_equal(crossed_feet(swapped, truth), [True] * 3)
    np.testing.assert_array_equal(crossed_feet(truth, truth), [False] * 3)
    # feet together in the truth: no side to get wrong
    together = _standing(3, ankle_gap=0.02)
    np.testing.assert_array_equal(crossed_feet(swapped, together), [False] * 3)


def test_skating_steps_by_hand():
    joints = _standing(20)
    foot = JOINT_INDEX["left_foot"]
    joints[:, foot, 2] = np.arange(20) * (1.0 / FPS)        # 1 m/s forward, on the ground
    joints[10:, foot, 1] = 0.2                              # lifted for the second half
    steps = skating_steps(joints)
    assert steps.shape == (19, 2)
    assert steps[:8, 0].all() and not steps[10:, 0].any()  # low and fast, then lifted
    assert not steps[:, 1].any()                           # the right foot stands still
    slow = _standing(20)
    slow[:, foot, 2] = np.arange(20) * (0.3 / FPS)
    assert not skating_steps(slow).any()


def test_skeleton_measures_refuse_what_does_not_pair():
    joints = _standing(10)
    with pytest.raises(ValueError, match="one shape"):
        joint_errors(joints[:1], joints)
    with pytest.raises(ValueError, match="one shape"):
        crossed_feet(joints, joints[:, :21])
    with pytest.raises(ValueError, match="odd"):
        skating_steps(joints, window=4)


def test_joint_errors_by_group():
    truth = np.zeros((2, 22, 3))
    joints = truth.copy()
    joints[:, JOINT_INDEX["left_knee"], 1] = 0.08           # one leg joint 8 cm off
    errors = joint_errors(joints, truth)
    assert errors["all"] == pytest.approx(0.08 / 22)
    assert errors["legs"] == pytest.approx(0.01) and errors["arms"] == 0 == errors["torso"]
