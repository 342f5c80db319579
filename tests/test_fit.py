"""The source fit (minretarget.fit): kernels against NumPy twins and finite differences,
rotations kept rotations, and fits that recover a known pose and shape."""
import warnings

import numpy as np
import pytest
from minretarget.nearest import build_grid

from minretarget import fit
from minretarget.conventions import NUM_JOINTS, PARENTS
from minretarget.analytic import analytic_rotations
from minretarget.kinematics import quaternion_to_matrix
from minretarget.pipeline import PipelineConfig

import twins
from conftest import one_sided


@pytest.fixture(scope="module")
def model():
    return fit.load_body_model()


def random_local(rng, scale):
    quaternions = np.concatenate([np.ones((NUM_JOINTS, 1)),
                                  rng.normal(scale=scale, size=(NUM_JOINTS, 3))], axis=1)
    return quaternion_to_matrix(quaternions).astype(np.float64)


def posed_state(model, seed=0, turn=0.3):
    """A shaped, posed model with rotations exactly on SO(3) (passed through apply_step)."""
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=len(model.points_basis))
    rest, tpose = fit.shaped(model, shape)
    local, root = random_local(rng, turn), np.array([0.1, 0.9, -0.2])
    rotations, _ = fit.forward(local, root, tpose)
    local, root = fit.apply_step(local, root, rotations, np.zeros(fit.PARAMETERS))
    rotations, joints = fit.forward(local, root, tpose)
    return shape, rest, tpose, local, root, rotations, joints


def test_shipped_model_shapes_and_weights(model):
    assert model.points.shape == model.normals.shape and model.joints.shape == (NUM_JOINTS, 3)
    np.testing.assert_allclose(model.bone_weight.sum(axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(model.normals, axis=1), 1, atol=1e-5)


def test_forward_matches_twin(model):
    _, _, tpose, local, root, rotations, joints = posed_state(model)
    quaternions = np.stack([twins._matrix_to_quaternion(r) for r in local])
    twin_joints, twin_rotations = twins.forward_kinematics(quaternions, root, tpose)
    np.testing.assert_allclose(joints, twin_joints, atol=1e-6)
    np.testing.assert_allclose(rotations, twin_rotations, atol=1e-6)


def dense(posed):
    """A ``Posed``'s lever over its chains as the twin's: lever (Q, J, 3) and reach (Q, J),
    zero about the joints that do not move a point."""
    chains = posed.chains
    lever = np.zeros((len(posed.points), NUM_JOINTS, 3))
    reach = np.zeros((len(posed.points), NUM_JOINTS))
    for q, count in enumerate(chains.count):
        lever[q, chains.joints[q, :count]] = posed.lever[q, :count]
        reach[q, chains.joints[q, :count]] = chains.reach[q, :count]
    return posed.points, posed.normals, lever, reach


def test_model_chains_are_the_joints_that_move_each_point(model):
    chains = fit.model_chains(model)
    assert chains is fit.model_chains(model)                          # computed once

    def at_or_above(k):
        joints = set()
        while k >= 0:
            joints.add(int(k))
            k = PARENTS[k]
        return joints
    for q in range(0, len(model.points), 7):
        active = [b for b in range(model.bone_index.shape[1]) if model.bone_weight[q, b] > 0]
        moving = set().union(*(at_or_above(model.bone_index[q, b]) for b in active))
        count = chains.count[q]
        assert list(chains.joints[q, :count]) == sorted(moving)
        assert (chains.joints[q, count:] == -1).all()
        assert list(chains.slots[q, :chains.slot_count[q]]) == active
        for t, b in enumerate(active):
            places = chains.links[q, t, :chains.link_count[q, t]]
            assert list(chains.joints[q, places]) == sorted(at_or_above(model.bone_index[q, b]))


def test_pose_model_matches_twin(model):
    _, rest, tpose, _, _, rotations, joints = posed_state(model)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    for got, want in zip(dense(posed),
                         twins.body_model_pose(model, rest, tpose, rotations, joints)):
        np.testing.assert_allclose(got, want, atol=1e-9)


def plane_rows(arguments):
    """Every pair's row and value, by ``fit._plane_row`` (the kernels' own)."""
    index = arguments[0]
    rows, values = np.zeros((len(index), fit.PARAMETERS)), np.empty(len(index))
    entries, columns = np.empty(fit.PARAMETERS), np.empty(fit.PARAMETERS, np.int64)
    for i, q in enumerate(index):
        count, values[i] = fit._plane_row(q, arguments[1][i], arguments[2][i], *arguments[3:],
                                          entries, columns)
        assert (np.diff(columns[:count]) > 0).all()
        rows[i, columns[:count]] = entries[:count]
    return rows, values


def numeric_derivative(model, state, measure, eps=1e-6):
    """d measure(local, root) / d step, by forward differences: (..., PARAMETERS)."""
    _, rest, tpose, local, root, rotations, _ = state
    base = measure(local, root)
    columns = []
    for n in range(fit.PARAMETERS):
        step = np.zeros(fit.PARAMETERS)
        step[n] = eps
        columns.append((measure(*fit.apply_step(local, root, rotations, step)) - base) / eps)
    return np.stack(columns, axis=-1)


def test_plane_rows_are_the_derivative_of_the_plane_distance(model):
    state = posed_state(model, seed=1)
    _, rest, tpose, _, _, rotations, joints = state
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    rng = np.random.default_rng(2)
    index = rng.integers(0, len(rest), 40)
    targets = posed.points[index] + rng.normal(scale=0.01, size=(40, 3))
    weights = rng.uniform(0.5, 2.0, 40)
    rows, values = plane_rows((index, targets, weights, posed.points, posed.normals,
                               posed.lever, posed.chains.joints, posed.chains.count))
    normals = posed.normals[index]

    def plane_distance(local, root):
        moved = fit.pose_model(model, rest, tpose, *fit.forward(local, root, tpose))
        return np.sqrt(weights) * np.sum(normals * (moved.points[index] - targets), axis=1)

    np.testing.assert_allclose(values, plane_distance(*state[3:5]), atol=1e-12)
    np.testing.assert_allclose(rows, numeric_derivative(model, state, plane_distance), atol=2e-5)


def test_normal_equations_are_the_rows_products(model):
    _, rest, tpose, _, _, rotations, joints = posed_state(model, seed=11)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    rng = np.random.default_rng(12)
    index = rng.integers(0, len(rest), 300)
    targets = posed.points[index] + rng.normal(scale=0.02, size=(300, 3))
    weights = rng.uniform(0.1, 1.0, 300)
    arguments = (index, targets, weights, posed.points, posed.normals, posed.lever,
                 posed.chains.joints, posed.chains.count)
    rows, values = plane_rows(arguments)
    start = rng.normal(size=(fit.PARAMETERS, fit.PARAMETERS))
    start = start + start.T                                   # any symmetric matrix, added to
    hessian, gradient = start.copy(), np.ones(fit.PARAMETERS)
    fit._plane_normal_equations_kernel(*arguments, hessian, gradient)
    np.testing.assert_allclose(hessian, start + rows.T @ rows, atol=1e-12)
    np.testing.assert_allclose(gradient, 1 + rows.T @ values, atol=1e-12)


def test_gauss_newton_step_is_the_solution_of_the_normal_equations():
    """The fit's Cholesky solve (not np.linalg.solve: its LAPACK wrapper is slow to compile)
    gives -H^-1 g for positive definite H, and refuses a matrix that is not."""
    rng = np.random.default_rng(13)
    rows = rng.normal(size=(400, fit.PARAMETERS)) * 10.0 ** rng.uniform(-3, 0, fit.PARAMETERS)
    hessian = rows.T @ rows + 1e-5 * np.eye(fit.PARAMETERS)     # condition number ~6e5
    gradient = rng.normal(size=fit.PARAMETERS)
    step = np.empty(fit.PARAMETERS)
    fit._solve_positive_definite(hessian.copy(), gradient, step)
    want = -np.linalg.solve(hessian, gradient)
    np.testing.assert_allclose(step, want, rtol=1e-8, atol=1e-8 * np.abs(want).max())
    indefinite = hessian - 2 * np.linalg.eigvalsh(hessian).max() * np.eye(fit.PARAMETERS)
    with pytest.raises(ValueError, match="positive definite"):
        fit._solve_positive_definite(indefinite, gradient, step)


def test_damped_step_is_the_capped_solution_of_the_damped_equations():
    """``_damped_step_kernel`` against NumPy: Levenberg-Marquardt's damping and floor on the
    diagonal, the solve, then the root's shift and each joint's turn capped (some steps here
    are large enough to be capped, some not)."""
    rng = np.random.default_rng(19)
    rows = rng.normal(size=(300, fit.PARAMETERS))
    hessian = rows.T @ rows
    gradient = rng.normal(size=fit.PARAMETERS) * 10.0 ** rng.uniform(-3, 2, fit.PARAMETERS)
    step = np.empty(fit.PARAMETERS)
    fit._damped_step_kernel(hessian.copy(), gradient, step)
    damped = hessian + np.diag(1e-3 * np.diag(hessian) + 1e-5)
    want = -np.linalg.solve(damped, gradient).reshape(-1, 3)
    limits = np.r_[fit.MAX_SHIFT, np.full(NUM_JOINTS, fit.MAX_TURN)]
    norms = np.linalg.norm(want, axis=1)
    assert (norms > limits).any() and (norms < limits).any()
    want *= np.minimum(1, limits / norms)[:, None]
    np.testing.assert_allclose(step, want.ravel(), rtol=1e-8, atol=1e-12)


def test_pull_normal_equations_are_the_joints_derivative_products(model):
    state = posed_state(model, seed=3)
    tpose, joints = state[2], state[6]
    numeric = numeric_derivative(model, state, lambda local, root:
                                 fit.forward(local, root, tpose)[1].ravel())     # (J * 3, P)
    rows, values = twins.joint_pull_rows(joints, joints + 0.01, weight=NUM_JOINTS)  # scale 1
    np.testing.assert_allclose(rows, numeric, atol=2e-5)
    # joint by joint: some pulled harder, some not at all
    weight = np.random.default_rng(8).uniform(0, 2 * NUM_JOINTS, NUM_JOINTS)
    weight[[3, 10]] = 0.0
    rows, values = twins.joint_pull_rows(joints, joints + 0.01, weight=weight)
    hessian, gradient = np.eye(fit.PARAMETERS), np.ones(fit.PARAMETERS)
    fit._pull_normal_equations_kernel(joints, joints + 0.01, weight, fit._PARENTS,
                                      hessian, gradient)
    np.testing.assert_allclose(hessian, np.eye(fit.PARAMETERS) + rows.T @ rows, atol=1e-12)
    np.testing.assert_allclose(gradient, 1 + rows.T @ values, atol=1e-12)


def test_shape_rows_are_the_derivative_of_the_posed_points_along_their_normals(model):
    shape, _, _, local, root, rotations, _ = posed_state(model, seed=4)

    def posed_points(coefficients):
        rest, tpose = fit.shaped(model, coefficients)
        return fit.pose_model(model, rest, tpose, *fit.forward(local, root, tpose)).points

    base, eps = posed_points(shape), 1e-6
    numeric = np.stack([(posed_points(shape + eps * np.eye(len(shape))[k]) - base) / eps
                        for k in range(len(shape))], axis=-1)                # (Q, 3, K)
    index = np.random.default_rng(13).integers(0, len(base), 200)
    normals = np.random.default_rng(14).normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    np.testing.assert_allclose(fit.shape_rows(model, rotations, index, normals),
                               np.einsum("na,nak->nk", normals, numeric[index]), atol=1e-7)


def surface_arguments(model, seed, stride=1):
    """A posed model and a cloud of another pose of it (some points far off), with settings."""
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=seed)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    rng = np.random.default_rng(seed + 100)
    cloud = posed.points[rng.choice(len(rest), 700, replace=False)] + rng.normal(
        scale=0.02, size=(700, 3))
    cloud[:20] += 0.5                                                 # past the robust width
    settings = fit.FitSettings(model_stride=stride)
    return rest, tpose, local, root, posed, cloud, settings


@pytest.mark.parametrize("stride, viewpoint", [(1, None), (3, None), (1, (0.4, 1.3, 2.6)),
                                               (3, (-2.5, 1.0, 0.3))])
def test_surface_terms_summed_per_model_point_give_the_pairs_normal_equations(model, stride,
                                                                              viewpoint):
    _, _, _, _, posed, cloud, settings = surface_arguments(model, 15, stride)
    index, targets, weights, cost = fit.surface_terms(posed, cloud, build_grid(cloud), settings,
                                                      viewpoint)
    assert len(np.unique(index)) == len(index)                 # one row per model point
    seen = None if viewpoint is None else twins.seen_points(
        posed.points, posed.normals, np.array(viewpoint), fit.HIDDEN_DEPTH, fit.SEEN_CELL)
    pairs = twins.surface_pairs(posed.points, cloud, settings.robust_width,
                                settings.model_to_cloud, stride, fit.TRUNCATE, seen)
    assert cost == pytest.approx(pairs[3], abs=1e-12)
    got = twins.plane_normal_equations(index, targets, weights, *dense(posed))
    want = twins.plane_normal_equations(*pairs[:3], *dense(posed))
    for got_part, want_part in zip(got, want):
        np.testing.assert_allclose(got_part, want_part, atol=1e-12)


def fit_pose_twin(model, rest, tpose, cloud, local, root, settings, pull_weight, pull_goal):
    """``fit.fit_pose`` from the twins: brute-force pairs, dense rows, NumPy solve."""
    cost = None
    for _ in range(settings.iterations):
        rotations, joints = fit.forward(local, root, tpose)
        posed = twins.body_model_pose(model, rest, tpose, rotations, joints)
        index, targets, weights, cost = twins.surface_pairs(
            posed[0], cloud, settings.robust_width, settings.model_to_cloud,
            settings.model_stride, fit.TRUNCATE)
        hessian, gradient = twins.plane_normal_equations(index, targets, weights, *posed)
        rows, values = twins.joint_pull_rows(joints, pull_goal, pull_weight)
        hessian, gradient = hessian + rows.T @ rows, gradient + rows.T @ values
        hessian[np.diag_indices_from(hessian)] += 1e-3 * np.diag(hessian) + 1e-5
        step = -np.linalg.solve(hessian, gradient).reshape(-1, 3)
        limits = np.r_[fit.MAX_SHIFT, np.full(NUM_JOINTS, fit.MAX_TURN)]
        step *= np.minimum(1, limits / np.maximum(np.linalg.norm(step, axis=1), 1e-300))[:, None]
        local, root = fit.apply_step(local, root, rotations, step.ravel())
    return local, root, fit.forward(local, root, tpose)[1], cost


def test_fit_pose_matches_its_twin(model):
    rest, tpose, local, root, _, cloud, settings = surface_arguments(model, 16)
    start = fit.apply_step(local, root, fit.forward(local, root, tpose)[0],
                           np.random.default_rng(17).normal(scale=0.2, size=fit.PARAMETERS))
    goal = fit.forward(local, root, tpose)[1] + 0.03
    settings = settings._replace(iterations=3)
    per_joint = np.linspace(0.0, 0.008, NUM_JOINTS)
    got = fit.fit_pose(model, rest, tpose, cloud, build_grid(cloud), *start, settings,
                       ((0.004, goal), (per_joint, goal + 0.02)))
    want = fit_pose_twin(model, rest, tpose, cloud, *start, settings, 0.004 + per_joint,
                         goal + 0.02 * (per_joint / (0.004 + per_joint))[:, None])
    for got_part, want_part in zip(got, want):
        np.testing.assert_allclose(got_part, want_part, atol=1e-9)


def test_apply_step_keeps_rotations_and_zero_is_no_step(model):
    _, _, _, local, root, rotations, _ = posed_state(model, seed=5)
    same, same_root = fit.apply_step(local, root, rotations, np.zeros(fit.PARAMETERS))
    np.testing.assert_allclose(same, local, atol=1e-12)
    np.testing.assert_array_equal(same_root, root)
    step = np.random.default_rng(6).normal(scale=0.5, size=fit.PARAMETERS)
    moved, _ = fit.apply_step(local, root, rotations, step)
    np.testing.assert_allclose(moved @ moved.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), moved.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(moved), 1, atol=1e-12)


def test_fit_pose_recovers_a_pose_from_its_own_surface(model):
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=7, turn=0.2)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    start = fit.apply_step(local, root, rotations,
                           np.random.default_rng(8).normal(scale=0.02, size=fit.PARAMETERS))
    settings = fit.FitSettings(iterations=12, reading_pull=0, motion_pull=0)
    *_, found, cost = fit.fit_pose(model, rest, tpose, cloud, build_grid(cloud), *start, settings)
    assert np.linalg.norm(found - joints, axis=1).mean() < 0.005
    assert cost < 0.002


def test_lost_legs_matches_its_twin(model):
    """The share of each lower leg's points in empty space, against brute force, on a cloud
    of the model in another pose (some of each leg's points far from it, some near)."""
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=11, turn=0.5)
    *_, other_rotations, other_joints = posed_state(model, seed=12, turn=0.5)
    cloud = fit.pose_model(model, rest, tpose, other_rotations, other_joints).points[::2]
    for far in (0.02, 0.08):
        got = fit.lost_legs(model, rest, tpose, local, root, build_grid(cloud), far)
        want = twins.lost_legs(model, rest, tpose, rotations, joints, cloud, far)
        np.testing.assert_allclose(got, want, atol=1e-12)
    assert 0 < got.min() < 1            # a leg partly in empty space
    own = fit.pose_model(model, rest, tpose, rotations, joints).points
    np.testing.assert_array_equal(
        fit.lost_legs(model, rest, tpose, local, root, build_grid(own), 0.02), [0, 0])
    # the thighs' share (the swapped start's gate), against the same brute force
    for far in (0.02, 0.08):
        got = fit.lost_legs(model, rest, tpose, local, root, build_grid(cloud), far,
                            parts=fit._THIGHS)
        want = twins.lost_legs(model, rest, tpose, rotations, joints, cloud, far,
                               bones=("hip",))
        np.testing.assert_allclose(got, want, atol=1e-12)


VIEWPOINTS = ((0.1, 1.2, 2.5), (2.5, 1.3, -0.2), (0.3, 1.0, -2.4), (1.5, 2.0, 1.5))


@pytest.mark.parametrize("viewpoint", VIEWPOINTS)
def test_seen_points_match_their_twin(model, viewpoint):
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=21, turn=0.4)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    got = fit.seen_points(posed, viewpoint)
    want = twins.seen_points(posed.points, posed.normals, np.array(viewpoint),
                             fit.HIDDEN_DEPTH, fit.SEEN_CELL)
    np.testing.assert_array_equal(got, want)
    assert 0.2 < got.mean() < 0.6                          # about one side of the body
    assert fit.seen_points(posed, None).all()              # a whole cloud: every point


def test_a_camera_at_one_side_sees_that_side_and_not_the_arm_behind_the_body(model):
    from minretarget.conventions import JOINT_INDEX
    rest, tpose = fit.shaped(model, np.zeros(len(model.points_basis)))
    rotations, joints = fit.forward(np.tile(np.eye(3), (NUM_JOINTS, 1, 1)), tpose[0], tpose)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    heaviest = model.bone_index[np.arange(len(rest)), model.bone_weight.argmax(axis=1)]
    chest = joints[JOINT_INDEX["spine3"]]
    front = fit.seen_points(posed, chest + (0, 0, 2.5))          # the T-pose faces +Z
    assert not front[posed.normals[:, 2] < -0.5].any()          # its back
    assert front[posed.normals[:, 2] > 0.5].mean() > 0.8         # its front, but what hides
    left = fit.seen_points(posed, chest + (2.5, 0, 0))           # its left arm points at +X
    assert left[heaviest == JOINT_INDEX["left_wrist"]].mean() > 0.4
    for hidden in ("right_wrist", "right_elbow"):                # behind the left arm, chest
        assert not left[heaviest == JOINT_INDEX[hidden]].any()


@pytest.mark.parametrize("distance", [0.31, 0.5, 0.7])
def test_a_camera_among_the_model_s_points_sees_only_what_lies_before_it(model, distance):
    """A camera inside the arm span of a T-pose (the left hand beside or behind it): the
    points behind its image plane are not seen, and the image stays bounded."""
    rest, tpose = fit.shaped(model, np.zeros(len(model.points_basis)))
    rotations, joints = fit.forward(np.tile(np.eye(3), (NUM_JOINTS, 1, 1)), tpose[0], tpose)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    viewpoint = posed.points.mean(axis=0) + (distance, 0.0, 0.0)
    got = fit.seen_points(posed, viewpoint)
    want = twins.seen_points(posed.points, posed.normals, viewpoint, fit.HIDDEN_DEPTH,
                             fit.SEEN_CELL)
    # this near, a point's cell is its coordinate times up to 40: a few land on a cell's edge,
    # where the kernel's rounding and NumPy's part
    assert (got != want).sum() <= 0.01 * len(got)
    behind = (posed.points - viewpoint)[:, 0] > -fit.NEAR_PLANE      # the view looks along -X
    assert behind.any() and not got[behind].any() and got.any()


def test_lost_legs_from_one_camera_count_only_what_it_sees(model):
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=11, turn=0.5)
    *_, other_rotations, other_joints = posed_state(model, seed=12, turn=0.5)
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    cloud = fit.pose_model(model, rest, tpose, other_rotations, other_joints).points[::2]
    viewpoint = np.array([0.5, 1.0, 2.5])
    seen = twins.seen_points(posed.points, posed.normals, viewpoint, fit.HIDDEN_DEPTH,
                             fit.SEEN_CELL)
    got = fit.lost_legs(model, rest, tpose, local, root, build_grid(cloud), 0.02, viewpoint)
    want = twins.lost_legs(model, rest, tpose, rotations, joints, cloud, 0.02, seen)
    np.testing.assert_allclose(got, want, atol=1e-12)
    # the back of a shin seen from the front is far from a cloud of its front: not lost
    front = posed.points[seen]
    np.testing.assert_array_equal(
        fit.lost_legs(model, rest, tpose, local, root, build_grid(front), 0.02, viewpoint),
        [0, 0])
    assert fit.lost_legs(model, rest, tpose, local, root, build_grid(front), 0.02).max() > 0.2


def test_a_fit_told_the_camera_is_not_drawn_onto_the_side_it_sees(model):
    """A cloud of what one camera sees of the model, the fit started 5 cm towards the camera:
    told the viewpoint, it goes back to the pose; not told, the model's unseen back is pulled
    onto the seen front and the body stays nearer the camera."""
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=7, turn=0.2)
    viewpoint = joints[0] + np.array([0.3, 0.4, 2.5])
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    cloud = posed.points[fit.seen_points(posed, viewpoint)]
    towards = (viewpoint - joints[0]) / np.linalg.norm(viewpoint - joints[0])
    settings = fit.FitSettings(iterations=12, reading_pull=0, motion_pull=0)
    errors = {}
    for told in (viewpoint, None):
        *_, found, _ = fit.fit_pose(model, rest, tpose, cloud, build_grid(cloud), local,
                                    root + 0.05 * towards, settings, viewpoint=told)
        errors[told is None] = np.linalg.norm(found - joints, axis=1).mean()
    assert errors[False] < 0.005
    assert errors[True] > 2 * errors[False]


def test_every_step_of_a_stream_told_its_camera_is_told_it(model, monkeypatch):
    """Every Gauss-Newton run, lost-leg test and shape step of a stream told its camera gets
    that camera, whichever start and branch runs: the settings make every one of them run
    (the swapped start, the aimed starts, the lost-leg steps, the steps more, the
    calibration's settling)."""
    calls = {"steps": [], "lost legs": [], "shape": []}
    gauss_newton, lost_legs, surface_terms = fit._gauss_newton, fit.lost_legs, fit.surface_terms

    def spy_steps(*args):
        calls["steps"].append(args[-4])                    # viewpoint, before local, root, joints
        return gauss_newton(*args)

    def spy_lost_legs(*args, **kwargs):
        calls["lost legs"].append(args[7] if len(args) > 7 else kwargs.get("viewpoint"))
        return lost_legs(*args, **kwargs)

    def spy_surface_terms(posed, cloud, grid, settings, viewpoint=None):
        calls["shape"].append(viewpoint)
        return surface_terms(posed, cloud, grid, settings, viewpoint)

    monkeypatch.setattr(fit, "_gauss_newton", spy_steps)
    monkeypatch.setattr(fit, "lost_legs", spy_lost_legs)
    monkeypatch.setattr(fit, "surface_terms", spy_surface_terms)
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=7, turn=0.2)
    viewpoint = joints[0] + np.array([0.3, 0.4, 2.5])
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    cloud = posed.points[fit.seen_points(posed, viewpoint)]
    settings = fit.FitSettings(calibration_frames=2, settle_rounds=1, swap_legs_cost=1e-6,
                               stray_share=1e-6, lost_leg_distance=0.005, lost_leg_share=1e-6,
                               still_falling=0.0, still_falling_told=0.0)
    readings = np.stack([joints + 0.03 * k for k in range(3)])
    fit.track(model, settings, [cloud] * 3, readings, [viewpoint] * 3)
    for name, told in calls.items():
        assert len(told) >= 2, name
        assert all(camera is not None and np.array_equal(camera, viewpoint)
                   for camera in told), name


def test_depth_from_the_motion_keeps_the_reading_across_its_ray():
    viewpoint = np.array([0.0, 1.0, 3.0])
    reading = np.array([[0.0, 1.0, 1.0], [0.5, 1.0, 1.0]])
    predicted = np.array([[0.1, 1.2, 0.5], [0.5, 1.0, 1.0]])
    got = fit._depth_from(reading, predicted, viewpoint)
    # the first joint's ray is the -Z axis: its depth is the prediction's, the rest the reading's
    np.testing.assert_allclose(got[0], [0.0, 1.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(got[1], reading[1], atol=1e-12)      # the same point: unmoved


def turned(axis, angle):
    """The rotation matrix of ``angle`` radians about the unit ``axis``."""
    x, y, z = np.asarray(axis, np.float64) * np.sin(angle / 2)
    return quaternion_to_matrix(np.array([[np.cos(angle / 2), x, y, z]]))[0].astype(np.float64)


def test_a_shin_in_empty_space_is_reached_for(model):
    """A kick that neither the last frame nor SKR's reading followed (docs/source_fit.md,
    05_14): the shin hangs where the cloud has none, too far for the robust terms. The steps
    at ``lost_leg_width`` without the reading's pull bring the ankle more than halfway back;
    without them it stays where it was (the stray points' start off in both: it finds this
    shin too)."""
    shape = np.zeros(len(model.points_basis))
    rest, tpose = fit.shaped(model, shape)
    hip, knee = fit.JOINT_INDEX["left_hip"], fit.JOINT_INDEX["left_knee"]
    start, root = np.tile(np.eye(3), (NUM_JOINTS, 1, 1)), np.array([0.0, 0.95, 0.0])
    start[hip] = turned([1, 0, 0], -0.6)                     # the thigh forward
    kicked = start.copy()
    kicked[knee] = turned([1, 0, 0], 0.7)                    # the shin swung on
    rotations, joints = fit.forward(kicked, root, tpose)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    _, held = fit.forward(start, root, tpose)
    assert fit.lost_legs(model, rest, tpose, start, root, build_grid(cloud),
                         fit.FitSettings().lost_leg_distance)[0] > 0.5
    state = fit.FitState(30, shape, start, root, np.stack([held, held]), (), 0.03)
    ankle = fit.JOINT_INDEX["left_ankle"]
    miss = {}
    for width in (0.0, fit.FitSettings().lost_leg_width):
        settings = fit.FitSettings(lost_leg_width=width, stray_share=0.0)
        _, found, _ = fit.fit_frame(model, settings, state, cloud,
                                    held)                     # the reading as lost as the track
        miss[width] = np.linalg.norm(found[ankle] - joints[ankle])
    assert miss[0.0] > 0.2
    assert miss[fit.FitSettings().lost_leg_width] < 0.5 * miss[0.0]


def test_stray_points_are_the_cloud_points_far_from_the_model(model):
    """Against brute force: the cloud points farther than ``far`` from every posed model
    point (``pose_model``'s) whose nearest is a leg's, on a cloud of the model in another
    pose."""
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=11, turn=0.5)
    *_, other_rotations, other_joints = posed_state(model, seed=12, turn=0.5)
    cloud = fit.pose_model(model, rest, tpose, other_rotations, other_joints).points[::2]
    posed = fit.pose_model(model, rest, tpose, rotations, joints).points
    distances = np.sqrt(((cloud[:, None] - posed[None]) ** 2).sum(-1))
    nearest, which = distances.min(1), distances.argmin(1)
    heaviest = model.bone_index[np.arange(len(posed)), model.bone_weight.argmax(1)]
    leg = np.isin(heaviest, [fit.JOINT_INDEX[f"{side}_{joint}"] for side in ("left", "right")
                             for joint in ("hip", "knee", "ankle", "foot")])[which]
    assert 0 < leg.sum() < len(cloud)
    for far in (0.02, 0.08):
        got = fit.stray_points(model, rest, tpose, local, root, build_grid(cloud), far)
        want = cloud[(nearest > far) & leg]
        assert 0 < len(want) < len(cloud)
        np.testing.assert_allclose(got[np.lexsort(got.T)], want[np.lexsort(want.T)],
                                   atol=1e-12)


@pytest.mark.parametrize("b", [[0.0, 0.6, 0.8], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0],
                               [-1.0, 1e-12, 0.0]])
def test_rotation_between_takes_one_direction_to_the_other(b):
    a = np.array([1.0, 0.0, 0.0])
    b = np.asarray(b) / np.linalg.norm(b)
    turn = fit._rotation_between(a, b)
    np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(turn) == pytest.approx(1.0)
    np.testing.assert_allclose(turn @ a, b, atol=1e-9)


@pytest.mark.parametrize("joint, moved_below", [
    ("left_knee", ("left_ankle", "left_foot")),
    ("right_hip", ("right_knee", "right_ankle", "right_foot"))])
def test_aim_bone_points_the_bone_at_the_strays_and_moves_nothing_else(model, joint,
                                                                        moved_below):
    _, rest, tpose, local, root, rotations, joints = posed_state(model, seed=5, turn=0.3)
    start, end = fit.JOINT_INDEX[joint], fit.JOINT_INDEX[moved_below[0]]
    goal = joints[start] + np.array([0.1, 0.0, 0.3])
    strays = goal + np.random.default_rng(0).normal(scale=0.02, size=(40, 3))
    aimed = fit.aim_bone(local, root, tpose, start, strays)
    _, moved = fit.forward(aimed, root, tpose)
    bone = moved[end] - moved[start]
    target = strays.mean(0) - joints[start]
    np.testing.assert_allclose(bone / np.linalg.norm(bone), target / np.linalg.norm(target),
                               atol=1e-9)
    below = [fit.JOINT_INDEX[name] for name in moved_below]
    others = [j for j in range(NUM_JOINTS) if j not in below]
    np.testing.assert_allclose(moved[others], joints[others], atol=1e-12)
    # only the joint's own rotation changes, and it stays a proper rotation
    changed = [j for j in range(NUM_JOINTS) if not np.array_equal(aimed[j], local[j])]
    assert changed == [start]
    np.testing.assert_allclose(aimed[start] @ aimed[start].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(aimed[start]) == pytest.approx(1.0, abs=1e-12)
    # reach: 1.5 of the aimed bone's own length from the joint
    length = np.linalg.norm(tpose[end] - tpose[start])
    direction = target / np.linalg.norm(target)
    tight = np.random.default_rng(1).normal(scale=1e-4, size=(20, 3))
    for bones, found in ((1.4, True), (1.6, False)):
        near = joints[start] + bones * length * direction + tight
        assert (fit.aim_bone(local, root, tpose, start, near) is not None) == found
    assert fit.aim_bone(local, root, tpose, start, joints[start] + tight * 1e-3) is None
    assert fit.aim_bone(local, root, tpose, start, strays[:9]) is None     # too few


def held_in_t_pose(model):
    """The mean body in the T-pose, 30 frames into a stream whose track has held it there
    (its legs hanging down) -> rest, tpose, start (J, 3, 3) identities, root, held joints, the
    track's ``FitState``."""
    shape = np.zeros(len(model.points_basis))
    rest, tpose = fit.shaped(model, shape)
    start, root = np.tile(np.eye(3), (NUM_JOINTS, 1, 1)), np.array([0.0, 0.95, 0.0])
    _, held = fit.forward(start, root, tpose)
    state = fit.FitState(30, shape, start, root, np.stack([held, held]), (), 0.03)
    return rest, tpose, start, root, held, state


def raised_leg(start, side, thigh=0.0, shin=0.0):
    """``start`` with the ``side`` ("left", "right") thigh turned ``thigh`` radians about x
    at the hip (negative: forward) and the shin ``shin`` at the knee (negative: up behind)."""
    raised = start.copy()
    raised[fit.JOINT_INDEX[f"{side}_hip"]] = turned([1, 0, 0], thigh)
    raised[fit.JOINT_INDEX[f"{side}_knee"]] = turned([1, 0, 0], shin)
    return raised


def test_a_raised_foot_the_fit_left_hanging_is_found_by_its_stray_points(model, monkeypatch):
    """The shin bent up behind (a foot raised), the track's hanging down: the raised foot's
    points lie past the robust width and pull nothing, and SKR reads the leg down as well.
    With ``stray_share`` the shin aimed at them is a start and wins; without, the ankle stays
    where it was (the lost-leg steps off in both, to see this start alone). The cloud is the
    model's own surface, so its costs are a quarter of a real cloud's: the pulls are too."""
    rest, tpose, start, root, held, state = held_in_t_pose(model)
    ankle = fit.JOINT_INDEX["left_ankle"]
    rotations, joints = fit.forward(raised_leg(start, "left", shin=-1.5), root, tpose)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    miss = {}
    for share in (0.0, 0.03):
        settings = fit.FitSettings(lost_leg_width=0.0, stray_share=share,
                                   reading_pull=0.00125, motion_pull=0.00125)
        _, found, _ = fit.fit_frame(model, settings, state, cloud, held)
        miss[share] = np.linalg.norm(found[ankle] - joints[ankle])
    assert miss[0.0] > 0.3
    assert miss[0.03] < 0.05
    calls = []
    aim_bone = fit.aim_bone
    monkeypatch.setattr(fit, "aim_bone", lambda *a: calls.append(a[3]) or aim_bone(*a))
    fit.fit_frame(model, settings, state, cloud, held)
    assert calls == [fit.JOINT_INDEX[f"{side}_{joint}"] for side in ("left", "right")
                     for joint in ("hip", "knee")]          # both thighs and shins tried
    calls.clear()
    fit.fit_frame(model, settings, state, fit.pose_model(model, rest, tpose, *fit.forward(
        start, root, tpose)).points, held)                  # the cloud the track explains
    assert calls == []


def test_a_raised_thigh_the_fit_left_hanging_is_found_and_no_settled_fit_costs_more(model):
    """A thigh raised in front, the shin hanging from it (a passé in a pirouette: docs/
    source_fit.md, 05_11), the track's leg down and SKR reading it down too: the points
    around the raised knee are strays, and the thigh aimed at them is a start that wins once
    settled; without the stray starts the knee stays. All settled starts are compared, the
    race's winner among them, so the frame never costs more than without them (here, or where
    the foot is raised). The cloud is the model's own surface: the pulls are a quarter of a
    real cloud's, as above."""
    rest, tpose, start, root, held, state = held_in_t_pose(model)
    knee = fit.JOINT_INDEX["right_knee"]
    for raised, joint, found_within in ((raised_leg(start, "right", -1.4, 1.4), knee, 0.2),
                                        (raised_leg(start, "right", shin=-1.5), None, None)):
        rotations, joints = fit.forward(raised, root, tpose)
        cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
        miss, cost = {}, {}
        for share in (0.0, 0.03):
            settings = fit.FitSettings(lost_leg_width=0.0, stray_share=share,
                                       reading_pull=0.00125, motion_pull=0.00125)
            fitted, found, _ = fit.fit_frame(model, settings, state, cloud, held)
            cost[share] = fitted.cost
            if joint is not None:
                miss[share] = np.linalg.norm(found[joint] - joints[joint])
        assert cost[0.03] <= cost[0.0]
        if joint is not None:
            assert miss[0.0] > 0.35 and miss[0.03] < found_within


def test_the_lowest_settled_cost_wins_not_the_lowest_race_cost(model, monkeypatch):
    """On a stray frame the race's winner and every aimed start that beat it are settled, and
    the lowest settled cost is kept. ``_settle`` is replaced by a stand-in that settles the
    winner worst and the aimed starts in the reverse of their race order: the aimed start
    that was slowest in the race must win (so more than the race's cheapest is settled)."""
    rest, tpose, start, root, held, state = held_in_t_pose(model)
    cloud = fit.pose_model(model, rest, tpose, *fit.forward(
        raised_leg(start, "right", -1.4, 1.4), root, tpose)).points
    settled = []

    def reversed_settle(model, settings, rest, tpose_joints, cloud, grid, viewpoint, race, pulls,
                        local, root, joints, cost):
        settled.append((cost, joints))
        # below LOST_COST, so that the frame is kept
        return local, root, joints, 0.05 if len(settled) == 1 else 0.04 - cost
    monkeypatch.setattr(fit, "_settle", reversed_settle)
    settings = fit.FitSettings(lost_leg_width=0.0, reading_pull=0.00125, motion_pull=0.00125,
                               more_iterations=0)
    _, found, _ = fit.fit_frame(model, settings, state, cloud, held)
    race_costs = [cost for cost, _ in settled]
    assert len(settled) >= 3 and max(race_costs[1:]) < race_costs[0]     # two aims beat it
    slowest = 1 + int(np.argmax(race_costs[1:]))
    np.testing.assert_array_equal(found, settled[slowest][1])


def test_a_fit_whose_cost_still_falls_takes_more_steps(model):
    """A thigh raised forward and its shin bent back, the track and SKR's reading held in the
    T-pose: the settled fit's cost is still falling fast since the race, and ``more_iterations``
    steps more take it closer to the pose; a cost that fell less than ``still_falling`` takes
    none (the same fit as without them). The cloud is the model's own surface, its costs a
    quarter of a real cloud's: ``still_falling`` 1 mm here stands for the default's 2."""
    rest, tpose, start, root, held, state = held_in_t_pose(model)
    rotations, joints = fit.forward(raised_leg(start, "left", -0.6, 0.6), root, tpose)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    cost, error, found = {}, {}, {}
    for more, falling in ((0, 0.001), (4, 0.001), (4, 1.0)):
        settings = fit.FitSettings(lost_leg_width=0.0, stray_share=0.0, reading_pull=0.00125,
                                   motion_pull=0.00125, more_iterations=more,
                                   still_falling=falling)
        fitted, found[more, falling], _ = fit.fit_frame(model, settings, state, cloud, held)
        cost[more, falling] = fitted.cost
        error[more, falling] = np.linalg.norm(found[more, falling] - joints, axis=1).mean()
    assert cost[4, 0.001] < cost[0, 0.001] - 0.001
    assert error[4, 0.001] < error[0, 0.001] - 0.003
    np.testing.assert_array_equal(found[4, 1.0], found[0, 0.001])


def steps_more_taken(monkeypatch, iterations):
    """A list that ``fit.fit_pose`` (spied on) appends to on each call: whether the call ran
    ``iterations`` steps (set as ``more_iterations``: the steps more, no other call's)."""
    more, fit_pose = [], fit.fit_pose

    def counted(*arguments):
        more.append(arguments[7].iterations == iterations)
        return fit_pose(*arguments)
    monkeypatch.setattr(fit, "fit_pose", counted)
    return more


def test_the_fall_is_measured_on_the_start_that_won(model, monkeypatch):
    """The extra steps go by the chosen start's own fall, from its race to its settling, not
    the race winner's: ``_settle`` is replaced by a stand-in that settles the race's winner
    at 50 mm and every aimed start 2 mm (or 5 mm) below its race cost. An aimed start wins;
    with 2 mm no steps more are taken at ``still_falling`` 3 mm (the race winner's cost minus
    the chosen one's is over 3 mm), with 5 mm ``more_iterations`` steps are."""
    rest, tpose, start, root, held, state = held_in_t_pose(model)
    cloud = fit.pose_model(model, rest, tpose, *fit.forward(
        raised_leg(start, "right", -1.4, 1.4), root, tpose)).points
    more = steps_more_taken(monkeypatch, 7)
    race_costs = []
    for fall, steps in ((0.002, False), (0.005, True)):
        race_costs.clear()

        def settle(model, settings, rest, tpose_joints, cloud, grid, viewpoint, race, pulls,
                   local, root, joints, cost):
            race_costs.append(cost)
            return local, root, joints, 0.05 if len(race_costs) == 1 else cost - fall
        monkeypatch.setattr(fit, "_settle", settle)
        more.clear()
        settings = fit.FitSettings(lost_leg_width=0.0, reading_pull=0.00125,
                                   motion_pull=0.00125, more_iterations=7, still_falling=0.003)
        fit.fit_frame(model, settings, state, cloud, held)
        assert len(race_costs) >= 2                                  # an aimed start won
        assert race_costs[0] - (min(race_costs[1:]) - fall) > settings.still_falling
        assert more[-1] == steps and sum(more) == steps


def test_a_told_frame_goes_on_by_its_own_threshold(model, monkeypatch):
    """A frame told its viewpoint takes the steps more by ``still_falling_told``, a whole
    cloud by ``still_falling``: every start settles 2.5 mm below its race cost (a stand-in
    ``_settle``), between the two thresholds (2 and 3 mm). Untold, ``more_iterations`` steps
    more are taken; told a camera 3 m in front, none; with the thresholds swapped, the
    other way round."""
    rest, tpose, start, root, held, state = held_in_t_pose(model)
    cloud = fit.pose_model(model, rest, tpose, *fit.forward(
        raised_leg(start, "right", -0.6, 0.6), root, tpose)).points
    more = steps_more_taken(monkeypatch, 7)

    def settle(model, settings, rest, tpose_joints, cloud, grid, viewpoint, race, pulls,
               local, root, joints, cost):
        return local, root, joints, cost - 0.0025
    monkeypatch.setattr(fit, "_settle", settle)
    camera = root + np.array([0.0, 0.3, 3.0])
    for untold, told in ((0.002, 0.003), (0.003, 0.002)):
        settings = fit.FitSettings(lost_leg_width=0.0, stray_share=0.0, reading_pull=0.00125,
                                   motion_pull=0.00125, more_iterations=7,
                                   still_falling=untold, still_falling_told=told)
        took = []
        for viewpoint in (None, camera):
            more.clear()
            fit.fit_frame(model, settings, state, cloud, held, viewpoint)
            took.append(sum(more))
        assert took == ([1, 0] if untold < told else [0, 1])


def legs_apart_scene(model):
    """The mean body with its legs apart (one forward, one back, a knee bent) and its own
    surface as the cloud -> shape, tpose, root, true local rotations, joints, cloud."""
    shape = np.zeros(len(model.points_basis))
    rest, tpose = fit.shaped(model, shape)
    truth, root = np.tile(np.eye(3), (NUM_JOINTS, 1, 1)), np.array([0.0, 0.95, 0.0])
    truth[fit.JOINT_INDEX["left_hip"]] = turned([1, 0, 0], -0.7)
    truth[fit.JOINT_INDEX["right_hip"]] = turned([1, 0, 0], 0.4)
    truth[fit.JOINT_INDEX["left_knee"]] = turned([1, 0, 0], 0.5)
    rotations, joints = fit.forward(truth, root, tpose)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    return shape, tpose, root, truth, joints, cloud


def test_legs_read_swapped_are_swapped_back(model):
    """SKR reads the legs swapped (each where the other is) and the track has followed: the
    frame's better start explains the cloud poorly, so the reading with its legs swapped is
    tried too and wins. The cloud is the model's own surface, so its costs are a quarter of a
    real cloud's (0.03-0.04 m): the threshold is lowered to match. Without the third start
    the legs stay swapped; a reading that has the legs right keeps them."""
    shape, tpose, root, _, joints, cloud = legs_apart_scene(model)
    swapped = joints[fit._SWAPPED_LEGS]
    assert np.array_equal(swapped[fit._SWAPPED_LEGS], joints)
    ankle = fit.JOINT_INDEX["left_ankle"]
    assert np.linalg.norm(swapped[ankle] - joints[ankle]) > 0.3

    def fitted(reading, swap_legs_cost):
        local = fit.local_from_joints(reading, tpose)          # the track as the reading
        _, held = fit.forward(local, root, tpose)
        state = fit.FitState(30, shape, local, root, np.stack([held, held]), (), 0.03)
        settings = fit.FitSettings(swap_legs_cost=swap_legs_cost, swap_legs_distance=0.0)
        return fit.fit_frame(model, settings, state, cloud, reading)[1]

    def error(found):
        return np.linalg.norm(found - joints, axis=1).mean()

    assert error(fitted(swapped, 0.0)) > 0.1
    assert error(fitted(swapped, 0.01)) < 0.015
    assert error(fitted(joints, 0.01)) < 0.015


def test_legs_read_swapped_stay_where_a_garment_covers_the_thighs(model):
    """The scene above with the thighs' points moved 6 cm out along their normals (a tube
    around them, as a coat's): only the thighs tell the legs apart, and a garment hides them,
    so the swapped start may not win and the track keeps its legs; without the gate
    (``swap_legs_hidden`` 0) it wins as above. With the thighs' points cut away instead
    (nothing near them: not a garment) it wins with the gate too."""
    shape, tpose, root, truth, joints, cloud = legs_apart_scene(model)
    rest, _ = fit.shaped(model, shape)
    posed = fit.pose_model(model, rest, tpose, *fit.forward(truth, root, tpose))
    heaviest = model.bone_index[np.arange(len(rest)), model.bone_weight.argmax(axis=1)]
    thighs = np.isin(heaviest, [fit.JOINT_INDEX["left_hip"], fit.JOINT_INDEX["right_hip"]])
    assert 0.05 < thighs.mean() < 0.3
    covered = cloud.copy()
    covered[thighs] += 0.06 * posed.normals[thighs]
    swapped = joints[fit._SWAPPED_LEGS]

    def error(points, **gate):
        local = fit.local_from_joints(swapped, tpose)            # the track read swapped
        _, held = fit.forward(local, root, tpose)
        state = fit.FitState(30, shape, local, root, np.stack([held, held]), (), 0.03)
        settings = fit.FitSettings(swap_legs_cost=0.01, swap_legs_distance=0.0, **gate)
        found = fit.fit_frame(model, settings, state, points, swapped)[1]
        return np.linalg.norm(found - joints, axis=1).mean()

    assert error(covered, swap_legs_hidden=0.0) < 0.02
    assert error(covered) > 0.1
    assert error(cloud[~thighs]) < 0.015
    grid = build_grid(covered)
    local = fit.local_from_joints(joints, tpose)
    assert fit.covered_thighs(model, rest, tpose, local, root, grid, fit.FitSettings())
    assert not fit.covered_thighs(model, rest, tpose, local, root, build_grid(cloud),
                                  fit.FitSettings())


def test_the_swapped_start_is_refused_only_where_both_poses_thighs_are_covered(model,
                                                                           monkeypatch):
    """The scene above, the track read swapped, with ``covered_thighs`` answering in turn for
    the better start's pose and the swapped start's: the swap wins unless both are covered."""
    shape, tpose, root, _, joints, cloud = legs_apart_scene(model)
    swapped = joints[fit._SWAPPED_LEGS]

    def error(answers):
        replies = iter(answers)
        monkeypatch.setattr(fit, "covered_thighs", lambda *args: next(replies))
        local = fit.local_from_joints(swapped, tpose)
        _, held = fit.forward(local, root, tpose)
        state = fit.FitState(30, shape, local, root, np.stack([held, held]), (), 0.03)
        settings = fit.FitSettings(swap_legs_cost=0.01, swap_legs_distance=0.0)
        found = fit.fit_frame(model, settings, state, cloud, swapped)[1]
        return np.linalg.norm(found - joints, axis=1).mean()

    assert error([True, True]) > 0.1
    assert error([True, False]) < 0.015
    assert error([False, True]) < 0.015


def test_reading_weight_falls_with_the_distance_from_the_motion():
    """Geman-McClure in the distance between each joint's reading and its prediction: the
    full pull where they agree, a quarter at ``reading_width``, almost none ten times as far;
    without a width, the one weight as before."""
    settings = fit.FitSettings(reading_pull=0.004, reading_width=0.1)
    misread = np.zeros(NUM_JOINTS)
    misread[1], misread[2] = 0.1, 1.0
    weight = fit.reading_weight(settings, misread)
    assert weight.shape == (NUM_JOINTS,)
    assert weight[0] == 0.004 and weight[1] == pytest.approx(0.001)
    assert weight[2] == pytest.approx(0.004 / 101 ** 2)
    assert fit.reading_weight(settings._replace(reading_width=0.0), misread) == 0.004


def test_a_reading_far_from_the_motion_pulls_less_and_has_its_legs_tried_swapped(model,
                                                                             monkeypatch):
    """The track is right and SKR reads the legs swapped (each lower leg 30 cm and more from
    where the motion puts it): with ``reading_width`` the misread joints barely pull, so the
    fit stays nearer the truth; with ``swap_legs_distance`` the reading with its legs swapped
    is fitted too (one more fit), and not when the reading agrees with the motion."""
    shape, _, root, truth, joints, cloud = legs_apart_scene(model)
    state = fit.FitState(30, shape, truth, root, np.stack([joints, joints]), (), 0.03)
    swapped = joints[fit._SWAPPED_LEGS]
    calls = []
    fit_pose = fit.fit_pose
    monkeypatch.setattr(fit, "fit_pose", lambda *a, **k: calls.append(1) or fit_pose(*a, **k))

    def fitted(reading, after=state, **settings):
        calls.clear()
        plain = fit.FitSettings(swap_legs_cost=0.0, reading_width=0.0, swap_legs_distance=0.0)
        found = fit.fit_frame(model, plain._replace(**settings), after, cloud, reading)[1]
        return np.linalg.norm(found - joints, axis=1).mean(), len(calls)

    plain, plain_calls = fitted(swapped)
    robust, _ = fitted(swapped, reading_width=0.1)
    assert robust < 0.5 * plain
    swapped_start, swapped_calls = fitted(swapped, swap_legs_distance=0.1)
    assert swapped_calls == plain_calls + 1 and swapped_start < 0.5 * plain
    assert fitted(joints + 0.01, swap_legs_distance=0.1)[1] == plain_calls
    # after a frame without the body its motion is stale: the distance says nothing
    lost = state._replace(cost=fit.LOST_COST + 0.01)
    assert fitted(swapped, lost, swap_legs_distance=0.1)[1] == fitted(swapped, lost)[1]


def test_combined_pull_sums_per_joint_and_skips_pulls_that_are_off():
    goal_a, goal_b = np.zeros((NUM_JOINTS, 3)), np.ones((NUM_JOINTS, 3))
    per_joint = np.zeros(NUM_JOINTS)
    per_joint[1] = 3.0
    total, goal = fit.combined_pull(((1.0, goal_a), (per_joint, goal_b),
                                     (0.0, np.full((NUM_JOINTS, 3), np.nan))))
    assert total[0] == 1.0 and total[1] == 4.0
    np.testing.assert_array_equal(goal[0], 0.0)
    np.testing.assert_array_equal(goal[1], 0.75)
    total, goal = fit.combined_pull(((0.0, goal_b),))            # nothing pulls
    assert not total.any() and np.isfinite(goal).all()


def test_the_settling_fits_every_kept_pose_each_round_by_its_own_steps(model, monkeypatch):
    """The calibration's settling fits every kept frame's pose ``settle_rounds`` times with
    ``settle_steps`` Gauss-Newton steps each, whether or not the stream was told its camera,
    and then the shape on them."""
    steps = []
    fit_pose = fit.fit_pose

    def spy_fit_pose(*args, **kwargs):
        steps.append((args[7].iterations, kwargs.get("viewpoint")))   # settings, camera
        return fit_pose(*args, **kwargs)

    shape, rest, tpose, local, root, rotations, joints = posed_state(model, seed=3, turn=0.1)
    viewpoint = joints[0] + np.array([0.2, 0.3, 2.5])
    posed = fit.pose_model(model, rest, tpose, rotations, joints)
    seen = posed.points[fit.seen_points(posed, viewpoint)]
    settings = fit.FitSettings(settle_rounds=3, settle_steps=2)
    monkeypatch.setattr(fit, "fit_pose", spy_fit_pose)
    for cloud, camera in ((posed.points, None), (seen, viewpoint)):
        frames = [(cloud, build_grid(cloud), local, root, camera)] * 2
        steps.clear()
        start = 0.9 * shape
        settled = fit.settle_shape(model, start, frames, settings)
        assert [count for count, _ in steps] == [2] * 6
        assert all(told is camera for _, told in steps)
        # on the model's own surface at the true pose, the shape comes back to the truth
        error = np.linalg.norm(fit.shaped(model, settled)[1] - tpose, axis=1).mean()
        assert error < 0.7 * np.linalg.norm(fit.shaped(model, start)[1] - tpose, axis=1).mean()


def test_a_calibration_whose_last_frame_is_lost_settles_on_the_next(model, monkeypatch):
    settled = []
    settle_shape = fit.settle_shape

    def spy(model, shape, frames, settings):
        settled.append(len(frames))
        return settle_shape(model, shape, frames, settings)

    monkeypatch.setattr(fit, "settle_shape", spy)
    _, rest, tpose, _, _, rotations, joints = posed_state(model, seed=5, turn=0.1)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    settings = fit.FitSettings(calibration_frames=3, settle_rounds=1)
    state, _ = fit.start_fit(model, settings, cloud, joints)
    kept = []
    for shift in (0.0, 3.0, 0.0, 0.0):                  # frame 2 misses the body by 3 m
        state, _, _ = fit.fit_frame(model, settings, state, cloud + [shift, 0.0, 0.0], joints)
        kept.append((len(state.calibration), len(settled), state.cost > fit.LOST_COST))
    # frame 2, the calibration's last, is lost: frame 3 settles on the two frames kept
    assert kept == [(2, 0, False), (2, 0, True), (0, 1, False), (0, 1, False)]
    assert settled == [2]


def test_start_fit_calibrates_the_shape_from_one_cloud(model):
    shape, rest, tpose, _, _, rotations, joints = posed_state(model, seed=9, turn=0.1)
    cloud = fit.pose_model(model, rest, tpose, rotations, joints).points
    reading = joints + np.random.default_rng(10).normal(scale=0.02, size=joints.shape)
    state, found = fit.start_fit(model, fit.FitSettings(), cloud, reading)
    # one frame already takes a third off the reading's error and half off the mean body's
    error = np.linalg.norm(found - joints, axis=1).mean()
    assert error < 0.7 * np.linalg.norm(reading - joints, axis=1).mean()
    calibrated = np.linalg.norm(fit.shaped(model, state.shape)[1] - tpose, axis=1).mean()
    assert calibrated < 0.5 * np.linalg.norm(model.joints - tpose, axis=1).mean()


def test_load_body_model_names_what_is_wrong(tmp_path, model):
    arrays = model._asdict()
    np.savez(tmp_path / "missing.npz", **{k: v for k, v in arrays.items() if k != "normals"})
    with pytest.raises(ValueError, match="missing.*normals"):
        fit.load_body_model(tmp_path / "missing.npz")
    np.savez(tmp_path / "weights.npz", **{**arrays, "bone_weight": arrays["bone_weight"] * 2})
    with pytest.raises(ValueError, match="summing to 1"):
        fit.load_body_model(tmp_path / "weights.npz")


@pytest.fixture(scope="module")
def sample_clouds():
    with np.load(fit.BODY_MODEL.with_name("sample.npz")) as data:
        return data["source_points"][:5], data["target_points"]


def test_retargeter_hands_smrm_the_fit_of_its_readings(sample_clouds):
    from minretarget.retargeter import Retargeter
    from minretarget.weights import load_weights
    clouds, target = sample_clouds
    settings = fit.FitSettings(calibration_frames=2, settle_rounds=1)
    retargeter = Retargeter(load_weights(), PipelineConfig(smoothing=None, denoise=False,
                                                           facing_check=False, foot_lock=None,
                                                           fit_source=settings))
    retargeter.set_target(target)
    seen = np.stack([frame.source_joints for frame in retargeter.run(clouds)])
    fitted, _ = fit.track(fit.body_model(), settings, clouds, retargeter.skeleton(clouds))
    np.testing.assert_allclose(seen, fitted, atol=1e-6)
    # bone lengths are the calibrated body's: constant once the calibration is over
    bones = np.linalg.norm(fitted[:, 1:] - fitted[:, list(fit.PARENTS[1:])], axis=2)
    np.testing.assert_allclose(bones[2:], np.broadcast_to(bones[2], bones[2:].shape), atol=1e-5)
    assert retargeter.state.stages["source_fit"].frames == len(clouds)
    retargeter.reset()
    assert retargeter.state is None


def test_retargeter_refuses_arguments_of_another_kind(tiny_weights):
    from minretarget.retargeter import Retargeter
    with pytest.raises(TypeError, match="fit_source must be a fit.FitSettings"):
        Retargeter(tiny_weights, PipelineConfig(fit_source="yes"))
    with pytest.raises(TypeError, match="weights must be a minretarget.weights.Weights.*str"):
        Retargeter("weights.npz")
    with pytest.raises(TypeError, match="refine must be True or False, got 'no'"):
        Retargeter(tiny_weights, PipelineConfig(refine="no"))
    for field, value in (("iterations", 0), ("model_stride", 0), ("robust_width", 0.0),
                         ("reading_pull", -1.0), ("settle_rounds", -1), ("settle_steps", 0),
                         ("lost_leg_width", -0.1), ("lost_leg_distance", 0.0),
                         ("lost_leg_share", 0.0), ("lost_leg_share", 1.5),
                         ("swap_legs_cost", -0.01), ("reading_width", -0.1),
                         ("swap_legs_distance", float("nan")), ("swap_legs_hidden", -0.01),
                         ("swap_legs_covered", float("inf")), ("swap_legs_covered", 0.0),
                         ("swap_legs_covered", 0.04),
                         ("draw", -1), ("draw", 1.5),
                         ("more_iterations", -1), ("still_falling", -0.001),
                         ("still_falling_told", -0.001)):
        with pytest.raises(ValueError, match=f"FitSettings.{field} must be"):
            Retargeter(tiny_weights, PipelineConfig(
                fit_source=fit.FitSettings()._replace(**{field: value})))


def test_another_draw_reads_another_subset_of_every_cloud(sample_clouds, monkeypatch):
    """Draw 0 reads the points a pipeline thinned to ``cloud_points`` reads; another draw
    reads another subset of the same cloud, the same one whoever asks, and the fit on it
    tracks the same body (the sample's 5 frames: within a few millimetres)."""
    from minretarget.retargeter import Retargeter
    from minretarget.sampling import seeded_subset
    from minretarget.weights import load_weights
    clouds, _ = sample_clouds
    cloud = clouds[3]
    np.testing.assert_array_equal(fit.subsample(cloud, 512, 3), seeded_subset(cloud, 512, 3))
    drawn = fit.subsample(cloud, 512, 3, draw=2)
    np.testing.assert_array_equal(drawn, fit.subsample(cloud, 512, 3, draw=2))
    rows = {tuple(point) for point in cloud.astype(np.float64)}
    assert len({tuple(point) for point in drawn}) == 512 and all(tuple(p) in rows for p in drawn)
    overlap = len({tuple(p) for p in drawn} & {tuple(p) for p in fit.subsample(cloud, 512, 3)})
    assert overlap < 400               # 512 of 2,048 twice: about 128 shared by chance
    assert not np.array_equal(drawn, fit.subsample(cloud, 512, 4, draw=2))
    readings = Retargeter(load_weights()).skeleton(clouds)
    seeds, seeded = [], fit.seeded_subset
    monkeypatch.setattr(fit, "seeded_subset", lambda *a: seeds.append(a[2]) or seeded(*a))
    tracks = []
    for draw, drawn_with in ((0, [0, 1, 2, 3, 4]), (1, [(1, t) for t in range(5)])):
        seeds.clear()
        tracks.append(fit.track(fit.body_model(), fit.FitSettings(
            calibration_frames=2, settle_rounds=1, draw=draw), clouds, readings)[0])
        assert seeds == drawn_with                      # every frame's subset, this draw's
    moved = np.linalg.norm(tracks[1] - tracks[0], axis=2)
    assert 0 < moved.mean() < 0.01


def test_fit_state_set_back_continues_the_stream_exactly(sample_clouds):
    from minretarget.retargeter import Retargeter
    from minretarget.weights import load_weights
    clouds, target = sample_clouds
    settings = fit.FitSettings(calibration_frames=2, settle_rounds=1)
    config = PipelineConfig(smoothing=None, denoise=False, foot_lock=None, fit_source=settings)
    first, second = (Retargeter(load_weights(), config) for _ in range(2))
    for retargeter in (first, second):
        retargeter.set_target(target)
    for points in clouds[:3]:
        first.step(points)
    second.state = first.state
    assert second.state.stages["source_fit"] is not first.state.stages["source_fit"]  # checked
    np.testing.assert_array_equal(second.step(clouds[3]).joints, first.step(clouds[3]).joints)
    with pytest.raises(ValueError, match="source_fit"):
        second.state = first.state._replace(stages={**first.state.stages,
                                                    "source_fit": "a fit"})
    second.state = None
    # without a cloud there is nothing to fit: the skeleton given is handed on
    given = first.skeleton(clouds[4])
    np.testing.assert_array_equal(second.step_skeleton(given).source_joints, given)


def test_a_stream_told_its_camera_is_set_back_and_goes_on_exactly(sample_clouds):
    """The viewpoints of the calibration's frames go into the fit's state (and a checkpoint's
    arrays) and back; a stream told its camera differs from one that is not."""
    from minretarget.retargeter import Retargeter
    from minretarget.weights import load_weights
    clouds, target = sample_clouds
    config = PipelineConfig(smoothing=None, denoise=False, foot_lock=None,
                            fit_source=fit.FitSettings(calibration_frames=3, settle_rounds=1))
    first, second, untold = (Retargeter(load_weights(), config) for _ in range(3))
    for retargeter in (first, second, untold):
        retargeter.set_target(target)
    seen, camera = one_sided(clouds, (0.5, 0.3, 2.5))     # the halves nearer a camera
    for points in seen[:2]:
        first.step(points, camera)
        untold.step(points)
    state = first.state.stages["source_fit"]
    assert len(state.calibration) == 2
    np.testing.assert_array_equal(state.calibration[1][4], camera)
    back = fit.fit_state_from_arrays(fit.fit_state_arrays(state), fit.body_model())
    np.testing.assert_array_equal(back.calibration[1][4], camera)
    second.state = first.state
    np.testing.assert_array_equal(second.step(seen[2], camera).joints,
                                  first.step(seen[2], camera).joints)
    assert np.abs(first.step(seen[3], camera).source_joints
                  - untold.step(seen[3]).source_joints).max() > 1e-3
    # a checkpoint from before viewpoints (no such array) is whole clouds
    arrays = fit.fit_state_arrays(untold.state.stages["source_fit"])
    del arrays["calibration_viewpoints"]
    assert all(frame[4] is None for frame in fit.fit_state_from_arrays(
        arrays, fit.body_model()).calibration)


def test_every_way_in_hands_the_fit_the_viewpoint(sample_clouds):
    """``run``, ``retarget_sequence`` and ``step_skeleton`` with a viewpoint give what
    ``step`` gives with it."""
    from minretarget.retargeter import Retargeter
    from minretarget.weights import load_weights
    clouds, target = sample_clouds
    config = PipelineConfig(smoothing=None, denoise=False, foot_lock=None,
                            fit_source=fit.FitSettings(calibration_frames=2, settle_rounds=1))
    retargeter = Retargeter(load_weights(), config)
    retargeter.set_target(target)
    clouds, camera = one_sided(clouds, (0.5, 0.3, 2.5))   # the halves nearer a camera
    clouds = np.stack(clouds)                      # as many points each: retarget_sequence
    stepped = [retargeter.step(cloud, camera).source_joints for cloud in clouds]
    ran = [frame.source_joints for frame in retargeter.run(clouds, camera)]
    np.testing.assert_array_equal(ran, stepped)
    np.testing.assert_allclose(retargeter.retarget_sequence(clouds, camera).source_joints,
                               stepped, atol=1e-5)
    # A given skeleton is not the one-view SKR's: its depth is the motion's (``view_read``),
    # so it matches ``step`` where the one-view SKR is off.
    plain = Retargeter(load_weights(), config.replace(skr_view=False))
    plain.set_target(target)
    plain_stepped = [plain.step(cloud, camera).source_joints for cloud in clouds]
    plain.reset()
    readings = plain.skeleton(clouds)
    given = [plain.step_skeleton(reading, cloud, camera).source_joints
             for reading, cloud in zip(readings, clouds)]
    np.testing.assert_allclose(given, plain_stepped, atol=1e-5)
    assert np.abs(np.array(plain_stepped) - stepped).max() > 1e-3     # the one-view SKR read
    retargeter.reset()
    assert np.abs(np.array([frame.source_joints for frame in retargeter.run(clouds)])
                  - stepped).max() > 1e-3
    with pytest.raises(ValueError, match="give the points too"):
        retargeter.step_skeleton(readings[0], viewpoint=camera)


def test_a_viewpoint_is_refused_where_it_cannot_be_used(sample_clouds, tiny_weights):
    from minretarget.retargeter import Retargeter
    from minretarget.weights import load_weights
    clouds, target = sample_clouds
    regressed = Retargeter(tiny_weights, "regressed")
    regressed.set_target(target)
    with pytest.raises(ValueError, match="needs the source fit.*regressed"):
        regressed.step(clouds[0], (0.0, 1.0, 3.0))
    fitted = Retargeter(load_weights(), "fitted")
    fitted.set_target(target)
    centre = clouds[0].mean(axis=0)
    with pytest.raises(ValueError, match=r"0.10 m from the cloud's centre"):
        fitted.step(clouds[0], centre + (0.1, 0.0, 0.0))
    with pytest.raises(ValueError, match="viewpoint"):
        fitted.step(clouds[0], (0.0, 1.0))
    with pytest.raises(ValueError, match="viewpoint"):
        fitted.step(clouds[0], (0.0, np.nan, 3.0))
    assert fitted.state is None                      # nothing of the stream was changed
    from minretarget.validation import InputWarning
    with pytest.warns(InputWarning, match="250.0 m from the cloud's centre.*units"):
        fitted.step(clouds[0], centre + (0.0, 0.0, 250.0))     # centimetres, say
    with pytest.warns(InputWarning, match="past any depth sensor's range"):   # mid-stream too
        fitted.retarget_sequence(clouds[:2], centre + (0.0, 0.0, 250.0))


def test_a_cloud_without_the_body_is_warned_of_by_frame_and_recovered_from(sample_clouds):
    from minretarget.retargeter import Retargeter
    from minretarget.validation import FitWarning
    from minretarget.weights import load_weights
    clouds, target = sample_clouds
    settings = fit.FitSettings(calibration_frames=2, settle_rounds=1)
    retargeter = Retargeter(load_weights(), PipelineConfig(smoothing=None, denoise=False,
                                                           foot_lock=None, facing_check=False,
                                                           fit_source=settings), warn=False)
    retargeter.set_target(target)
    plain = Retargeter(load_weights(), PipelineConfig(smoothing=None, denoise=False,
                                                      foot_lock=None, facing_check=False,
                                                      fit_source=settings), warn=False)
    plain.set_target(target)
    stream = list(clouds)
    stream[3] = stream[3] + [3.0, 0.0, 0.0]           # frame 3 misses the body by 3 m
    with pytest.warns(FitWarning, match="frame 3: the source fit found no body"):
        frames = list(retargeter.run(stream))
    assert np.isfinite(frames[3].source_joints).all()
    # one frame later the fit is where it would have been without the lost frame
    expected = list(plain.run(clouds))[4].source_joints
    assert np.linalg.norm(frames[4].source_joints - expected, axis=1).mean() < 0.02


def test_a_body_that_jumps_away_is_found_again_the_next_frame():
    """A cut in the capture (the body 2.5 m away from one frame on, as when a clip restarts):
    the last motion must not pull the fit back to where the body was; one frame is held (the
    motion still pulls there), then the fit follows the body."""
    from minretarget.retargeter import Retargeter
    from minretarget.validation import FitWarning
    from minretarget.weights import load_weights
    with np.load(fit.BODY_MODEL.with_name("sample.npz")) as data:
        clouds, target = data["source_points"][:8], data["target_points"]
    settings = fit.FitSettings(calibration_frames=2, settle_rounds=1)
    config = PipelineConfig(smoothing=None, denoise=False, foot_lock=None, facing_check=False,
                            fit_source=settings)
    retargeter, moved = (Retargeter(load_weights(), config, warn=False) for _ in range(2))
    for each in (retargeter, moved):
        each.set_target(target)
    jump = np.float32([2.5, 0.0, 0.0])
    stream = [*clouds[:4], *(cloud + jump for cloud in clouds[4:])]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FitWarning)
        frames = [retargeter.step(cloud) for cloud in stream]
        lost = [t for t in range(1, len(stream))            # held: the last frame's joints
                if np.array_equal(frames[t].source_joints, frames[t - 1].source_joints)]
        # the same body read where it now is, from a stream that never saw the jump
        truth = [moved.step(cloud + jump) for cloud in clouds][-1].source_joints
    assert lost in ([], [4]), lost
    assert np.linalg.norm(frames[-1].source_joints - truth, axis=1).mean() < 0.03


def test_warm_up_does_not_warn_of_its_own_frames(tiny_weights, tiny_stream):
    """warm_up retargets two frames of the target's own points: a source fit that finds no
    body in them (random weights read no skeleton) must not warn of frames the caller never
    gave; the same points given to step do warn."""
    import warnings
    from minretarget.retargeter import Retargeter
    from minretarget.validation import FitWarning
    target = tiny_stream[0]
    retargeter = Retargeter(tiny_weights, "fitted", warn=False)
    retargeter.set_target(target)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        retargeter.warm_up()
    assert not [w for w in caught if issubclass(w.category, FitWarning)]
    assert retargeter.state is None
    points = np.ascontiguousarray(target[::max(1, len(target) // 1024)])
    with pytest.warns(FitWarning, match="frame 1: the source fit found no body"):
        for _ in range(2):
            retargeter.step(points)


def test_shaped_keeps_its_last_answer_and_only_that(model):
    first, second = np.full(len(model.points_basis), 0.5), np.full(len(model.points_basis), -1.0)
    for shape in (first, second, first):
        rest, tpose = fit.shaped(model, shape)
        np.testing.assert_array_equal(rest, model.points + np.tensordot(shape, model.points_basis,
                                                                        1))
        np.testing.assert_array_equal(tpose, model.joints + np.tensordot(shape,
                                                                         model.joints_basis, 1))
    assert fit.shaped(model, first.copy())[0] is rest                  # kept, by value


def test_local_from_joints_is_the_analytic_rotations(model):
    _, _, tpose, _, _, _, joints = posed_state(model, seed=8)
    want = quaternion_to_matrix(analytic_rotations(joints.astype(np.float32),
                                                   tpose.astype(np.float32)))
    np.testing.assert_array_equal(fit.local_from_joints(joints, tpose), want.astype(np.float64))
