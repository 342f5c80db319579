"""Bodies from anny: canonical T-pose, weights, and posing against anny's own FK and LBS.

Builds one body with anny (about 5 s once anny's model cache exists; the very first anny build
on a machine takes about 90 s and writes under ~/.cache/anny).
"""
import numpy as np
import pytest

pytest.importorskip("anny")
import torch  # noqa: E402

from minretarget.conventions import JOINT_INDEX, NUM_JOINTS  # noqa: E402
from minretarget.kinematics import forward_kinematics  # noqa: E402
from training.data import bodies  # noqa: E402


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    return bodies.get_body(bodies.TEST_TARGET_PHENOTYPES["target_female_heavy_tall"],
                           "target_female_heavy_tall", tmp_path_factory.mktemp("bodies"))


def _random_rotations(rng, shape):
    q = rng.normal(size=shape + (NUM_JOINTS, 4))
    q[..., 0] += 3.0                                       # mostly moderate angles (< ~60 deg)
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32)


def _anny_posed(body, rotations, root):
    """Naive twin of ``pose_body``: the same canonical rotations converted to anny
    'local-bone-world' deltas, posed by anny's own FK and LBS from its A-pose rest.
    Returns canonical (V, 3) vertices and (J, 3) joints."""
    model = bodies.anny_model()
    axes = bodies.ANNY_TO_CANONICAL
    with torch.no_grad():
        tpose = model(pose_parameters=bodies._tpose_deltas(), phenotype_kwargs=body.phenotype)
    rest = tpose["rest_bone_poses"][0].numpy()                       # (bones, 4, 4) A-pose
    tposed = tpose["bone_poses"][0].numpy()                          # (bones, 4, 4) T-pose
    bone_joint = [bodies._bone_to_joint(b) for b in model.bone_labels]
    offset = body.joints[0] - axes @ tposed[model.bone_labels.index("pelvis"), :3, 3]
    joints, global_rotations = forward_kinematics(rotations, root, body.joints)
    world = axes.T @ global_rotations[bone_joint].astype(np.float64) @ axes @ tposed[:, :3, :3]
    parents = model.bone_parents
    deltas = np.tile(np.eye(4), (len(parents), 1, 1))
    for c in range(1, len(parents)):
        # W_c = W_p (U_p^T U_c) D_c in 'local-bone', U the rest orientations.
        p = parents[c]
        deltas[c, :3, :3] = rest[c, :3, :3].T @ rest[p, :3, :3] @ world[p].T @ world[c]
    # The Root bone (local-bone-world: W_0 = Q_0 D_0) moves rigidly with the pelvis joint.
    head = axes @ tposed[0, :3, 3] + offset
    root_pose = np.eye(4)
    root_pose[:3, :3] = world[0]
    root_pose[:3, 3] = axes.T @ (global_rotations[0] @ (head - body.joints[0]) + joints[0] - offset)
    deltas[0] = np.linalg.inv(rest[0]) @ root_pose
    with torch.no_grad():
        out = model(pose_parameters=torch.as_tensor(deltas[None]), phenotype_kwargs=body.phenotype)
    heads = out["bone_poses"][0, :, :3, 3].numpy()[[model.bone_labels.index(b)
                                                     for b in bodies.JOINT_BONES]]
    return out["vertices"][0].numpy() @ axes.T + offset, heads @ axes.T + offset


def test_shapes_and_dtypes(body):
    assert body.vertices.shape == (13718, 3) and body.vertices.dtype == np.float32
    assert body.faces.shape == (27420, 3) and body.faces.dtype == np.int32
    assert body.joints.shape == (NUM_JOINTS, 3) and body.weights.shape == (13718, NUM_JOINTS)
    assert body.faces.min() == 0 and body.faces.max() == len(body.vertices) - 1


def test_feet_on_the_ground_pelvis_above_origin(body):
    assert body.vertices[:, 1].min() == 0.0
    np.testing.assert_allclose(body.joints[0, [0, 2]], 0.0, atol=1e-6)
    assert 1.7 < body.height < 1.95 and 0.45 < body.hip_height / body.height < 0.6


def test_canonical_axes(body):
    j = JOINT_INDEX
    assert body.joints[j["left_wrist"], 0] > 0.5 and body.joints[j["right_wrist"], 0] < -0.5
    assert body.joints[j["head"], 1] > body.joints[j["pelvis"], 1]
    for side in ("left", "right"):                         # toes ahead of the heels: faces +Z
        assert body.joints[j[f"{side}_foot"], 2] > body.joints[j[f"{side}_ankle"], 2] + 0.05
        assert body.vertices[body.weights[:, j[f"{side}_foot"]] > 0.5, 2].max() > \
            body.vertices[body.weights[:, j[f"{side}_ankle"]] > 0.5, 2].min() + 0.15
    # T-pose: arms horizontal, within 3 cm from shoulder to wrist.
    for side in ("left", "right"):
        heights = body.joints[[j[f"{side}_shoulder"], j[f"{side}_elbow"], j[f"{side}_wrist"]], 1]
        assert np.ptp(heights) < 0.03


def test_weights_nonnegative_rows_sum_to_one(body):
    assert body.weights.min() >= 0.0
    np.testing.assert_allclose(body.weights.sum(axis=1), 1.0, atol=1e-5)
    assert (body.weights.max(axis=0) > 0.3).all()          # every joint drives some vertices


def test_identity_gives_the_tpose(body):
    identity = np.tile(np.array([1, 0, 0, 0], np.float32), (2, NUM_JOINTS, 1))
    vertices, joints = bodies.pose_body(body, identity, np.tile(body.joints[0], (2, 1)))
    np.testing.assert_allclose(vertices, np.broadcast_to(body.vertices, vertices.shape), atol=1e-6)
    np.testing.assert_allclose(joints, np.broadcast_to(body.joints, joints.shape), atol=1e-6)


def test_pose_matches_anny_own_posing(body):
    rng = np.random.default_rng(0)
    for _ in range(3):
        rotations = _random_rotations(rng, ())
        root = rng.uniform(-1, 1, 3).astype(np.float32)
        vertices, joints = bodies.pose_body(body, rotations, root)
        anny_vertices, anny_joints = _anny_posed(body, rotations, root)
        np.testing.assert_allclose(joints, anny_joints, atol=1e-3)
        # LBS from the T-pose vs anny's LBS from its A-pose: equal where one joint rules.
        distance = np.linalg.norm(vertices - anny_vertices, axis=1)
        assert distance.mean() < 2e-3 and np.percentile(distance, 99) < 0.02


def test_batched_pose_equals_per_frame(body):
    rng = np.random.default_rng(1)
    rotations = _random_rotations(rng, (2, 3))
    root = rng.uniform(-1, 1, (2, 3, 3)).astype(np.float32)
    vertices, joints = bodies.pose_body(body, rotations, root)
    assert vertices.shape == (2, 3, 13718, 3) and joints.shape == (2, 3, NUM_JOINTS, 3)
    one_vertices, one_joints = bodies.pose_body(body, rotations[1, 2], root[1, 2])
    np.testing.assert_allclose(vertices[1, 2], one_vertices, atol=1e-5)
    np.testing.assert_allclose(joints[1, 2], one_joints, atol=1e-6)


def test_cache_round_trip(body, tmp_path):
    path = tmp_path / "body.npz"
    bodies.save_body(body, path)
    loaded = bodies.load_body(path)
    assert loaded.name == body.name and loaded.phenotype == body.phenotype
    for name in ("vertices", "faces", "joints", "weights"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(body, name))


def test_seeds_are_deterministic_and_splits_disjoint():
    assert bodies.phenotype_from_seed(3) == bodies.phenotype_from_seed(3)
    assert bodies.phenotype_from_seed(3) != bodies.phenotype_from_seed(4)
    train, val = bodies.sampled_body_seeds(5, "train"), bodies.sampled_body_seeds(5, "val")
    assert not set(train) & set(val)


def test_test_bodies_span_the_protocol(tmp_path_factory):
    phenotypes = bodies.TEST_TARGET_PHENOTYPES
    assert {p["gender"] for p in phenotypes.values()} == {0.0, 1.0}
    slim = [p for name, p in phenotypes.items() if "slim_short" in name]
    heavy = [p for name, p in phenotypes.items() if "heavy_tall" in name]
    assert len(slim) == len(heavy) == 2
    assert max(p["weight"] for p in slim) < min(p["weight"] for p in heavy)
    assert max(p["height"] for p in slim) < min(p["height"] for p in heavy)
    assert not set(phenotypes) & set(bodies.TEST_SOURCE_PHENOTYPES)


def _square_body():
    """A 1 m square in the z = 0 plane, every vertex bound to the pelvis."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    weights = np.zeros((4, NUM_JOINTS), np.float32)
    weights[:, 0] = 1
    joints = np.zeros((NUM_JOINTS, 3), np.float32)
    joints[:, 1] = np.linspace(0, 1, NUM_JOINTS)
    return bodies.Body("square", {}, vertices, np.array([[0, 1, 2], [0, 2, 3]], np.int32),
                       joints, weights)


def test_posed_clouds_lie_on_the_posed_surface():
    """Fresh area-uniform clouds of a posed body (a square bound to the pelvis, shifted),
    reproducible from the seed, and its posed joints."""
    body = _square_body()
    rotations = np.tile(np.array([1, 0, 0, 0], np.float32), (3, NUM_JOINTS, 1))
    root = np.array([[0, 0, 0], [0, 0, 1], [2, 0, 0]], np.float32)   # T-pose, shifted
    clouds, joints = bodies.posed_clouds(body, rotations, root, 100, np.random.default_rng(0))
    assert clouds.shape == (3, 100, 3) and clouds.dtype == np.float32
    np.testing.assert_allclose(joints[:, 0], root, atol=1e-6)
    local = clouds - (root - body.joints[0])[:, None]
    assert np.all((local[..., :2] >= -1e-6) & (local[..., :2] <= 1 + 1e-6))
    np.testing.assert_allclose(local[..., 2], 0, atol=1e-6)
    again, _ = bodies.posed_clouds(body, rotations, root, 100, np.random.default_rng(0))
    np.testing.assert_array_equal(clouds, again)


def test_body_command_writes_a_t_pose_target(tmp_path, capsys):
    """``python -m training.data body``: anny's T-pose with the project's settings, as a
    TARGET file (issue 41: making one took copying a private setting)."""
    from minretarget.formats.mesh import read_points
    from minretarget.validation import body_problems
    from training.data.__main__ import main
    main(["body", "--out", str(tmp_path / "kid.obj"), "--age", "0.25", "--body-cache",
          str(tmp_path / "cache")])
    assert "a T-pose body 1.2" in capsys.readouterr().out
    points, faces = read_points(tmp_path / "kid.obj")
    assert faces is not None and 1.1 < np.ptp(points[:, 1]) < 1.35
    assert body_problems(points, "kid.obj", tpose=True) == []


def test_the_shipped_bodies_are_the_listed_phenotypes(tmp_path):
    """minretarget/data/bodies.npz is what ``python -m training.data bodies`` writes: exactly,
    but for rounding. Torch's CPU kernels differ by machine (1e-18 m on points 1e-19 m from
    zero), and anny splits each quad of its mesh along the shorter diagonal, so a square quad
    may be split along the other one: the same quads (each two consecutive triangles' four
    corners), split either way."""
    from minretarget.bodies import BODIES
    from training.data.sample import build_bodies
    arrays = build_bodies(cache_dir=tmp_path)
    with np.load(BODIES, allow_pickle=False) as shipped:
        for key, array in arrays.items():
            if key == "vertices":
                np.testing.assert_allclose(shipped[key], array, rtol=0, atol=1e-7, err_msg=key)
            elif key == "faces":
                assert shipped[key].shape == array.shape
                differ = np.nonzero((shipped[key] != array).any(axis=1))[0]
                assert len(differ) <= 0.01 * len(array)
                for row in np.unique(differ // 2 * 2):
                    assert (set(shipped[key][row:row + 2].ravel())
                            == set(array[row:row + 2].ravel())), f"faces {row}, {row + 1}"
            else:
                np.testing.assert_array_equal(shipped[key], array, err_msg=key)
