"""The glTF 2.0 binary writer, checked against the specification's rules by parsing the
chunks ourselves, by glTF node math (scipy's quaternions, not ours), and by trimesh."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from minretarget.conventions import JOINT_NAMES, NUM_JOINTS, PARENTS
from minretarget.formats.glb import (ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, FLOAT, UNSIGNED_BYTE,
                                     accessor_array, glb_bytes, read_glb, top_weights,
                                     write_glb)
from minretarget.kinematics import forward_kinematics, skinning_transforms
from minretarget.skin import linear_blend_skinning

trimesh = pytest.importorskip("trimesh")


def rigged_target(frames=6, seed=0, max_influences=4):
    """A small mesh with a skeleton, weights (at most ``max_influences`` per vertex), and
    a random motion: (points, faces, weights, tpose, rotations, root)."""
    rng = np.random.default_rng(seed)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    points = (mesh.vertices * [0.3, 0.9, 0.2] + [0, 0.9, 0]).astype(np.float32)
    tpose = rng.normal(0, 0.3, (NUM_JOINTS, 3)).astype(np.float32)
    weights = np.zeros((len(points), NUM_JOINTS))
    for v in range(len(points)):
        joints = rng.choice(NUM_JOINTS, max_influences, replace=False)
        weights[v, joints] = rng.random(max_influences) + 0.05
    weights = (weights / weights.sum(axis=1, keepdims=True)).astype(np.float32)
    q = rng.normal(size=(frames, NUM_JOINTS, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    root = rng.normal(0, 1, (frames, 3)).astype(np.float32)
    return points, mesh.faces, weights, tpose, q.astype(np.float32), root


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    target = rigged_target()
    path = tmp_path_factory.mktemp("glb") / "result.glb"
    write_glb(path, *target, fps=30)
    gltf, binary = read_glb(path)
    return path, target, gltf, binary


def node_world_matrices(gltf, binary, frame):
    """(nodes, 4, 4) world matrices of the joint nodes at key ``frame``, by glTF's rules:
    local = T * R * S from the node (or the animation sampler), world = parent world @ local."""
    animated = {}
    for channel in gltf["animations"][0]["channels"]:
        sampler = gltf["animations"][0]["samplers"][channel["sampler"]]
        animated[channel["target"]["node"], channel["target"]["path"]] = \
            accessor_array(gltf, binary, sampler["output"])[frame]
    parent = {child: index for index, node in enumerate(gltf["nodes"])
              for child in node.get("children", [])}
    world = {}
    for index in range(NUM_JOINTS):                     # parents come first, as in PARENTS
        node = gltf["nodes"][index]
        local = np.eye(4)
        local[:3, 3] = animated.get((index, "translation"), node.get("translation", [0, 0, 0]))
        xyzw = animated.get((index, "rotation"), node.get("rotation", [0, 0, 0, 1]))
        local[:3, :3] = Rotation.from_quat(xyzw).as_matrix()
        world[index] = world[parent[index]] @ local if index in parent else local
    return np.stack([world[j] for j in range(NUM_JOINTS)])


def test_container_layout(written):
    path, _, gltf, binary = written
    data = path.read_bytes()
    assert data[:4] == b"glTF" and int.from_bytes(data[4:8], "little") == 2
    assert int.from_bytes(data[8:12], "little") == len(data)
    json_length = int.from_bytes(data[12:16], "little")
    assert json_length % 4 == 0 and data[16:20] == b"JSON"
    assert data[20 + json_length + 4:20 + json_length + 8] == b"BIN\0"
    assert gltf["asset"]["version"] == "2.0"
    assert gltf["buffers"] == [{"byteLength": gltf["buffers"][0]["byteLength"]}]
    assert len(binary) >= gltf["buffers"][0]["byteLength"] > len(binary) - 4
    for view in gltf["bufferViews"]:
        assert view["byteOffset"] % 4 == 0 and "byteStride" not in view
        assert view["byteOffset"] + view["byteLength"] <= gltf["buffers"][0]["byteLength"]
    for accessor in gltf["accessors"]:
        assert accessor["count"] > 0
        array = accessor_array(gltf, binary, gltf["accessors"].index(accessor))
        assert np.isfinite(array).all()
        if "min" in accessor:
            np.testing.assert_array_equal(accessor["min"], array.min(axis=0))
            np.testing.assert_array_equal(accessor["max"], array.max(axis=0))


def test_mesh_skin_and_weights(written):
    _, (points, faces, weights, tpose, *_), gltf, binary = written
    primitive = gltf["meshes"][0]["primitives"][0]
    attributes = primitive["attributes"]
    assert "min" in gltf["accessors"][attributes["POSITION"]]        # required by the spec
    np.testing.assert_array_equal(accessor_array(gltf, binary, attributes["POSITION"]), points)
    np.testing.assert_array_equal(
        accessor_array(gltf, binary, primitive["indices"]).reshape(-1, 3), faces)
    normals = accessor_array(gltf, binary, attributes["NORMAL"])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-6)
    views = {gltf["accessors"][a]["bufferView"]: name for name, a in attributes.items()}
    for view, name in views.items():
        assert gltf["bufferViews"][view]["target"] == ARRAY_BUFFER, name
    assert gltf["bufferViews"][gltf["accessors"][primitive["indices"]]["bufferView"]][
        "target"] == ELEMENT_ARRAY_BUFFER
    joints_accessor = gltf["accessors"][attributes["JOINTS_0"]]
    assert joints_accessor["componentType"] == UNSIGNED_BYTE
    assert gltf["accessors"][attributes["WEIGHTS_0"]]["componentType"] == FLOAT
    joints = accessor_array(gltf, binary, attributes["JOINTS_0"])
    stored = accessor_array(gltf, binary, attributes["WEIGHTS_0"])
    np.testing.assert_allclose(stored.sum(axis=1), 1, atol=1e-6)
    dense = np.zeros_like(weights)
    np.put_along_axis(dense, joints.astype(np.int64), stored, axis=1)  # zero slots: joint 0
    np.testing.assert_allclose(dense, weights, atol=1e-6)             # <= 4 influences: exact
    skin = gltf["skins"][0]
    assert skin["joints"] == list(range(NUM_JOINTS)) and len(skin["joints"]) == 22
    assert [gltf["nodes"][j]["name"] for j in skin["joints"]] == list(JOINT_NAMES)
    inverse_bind = accessor_array(gltf, binary, skin["inverseBindMatrices"])
    inverse_bind = inverse_bind.reshape(NUM_JOINTS, 4, 4).transpose(0, 2, 1)   # column-major
    np.testing.assert_allclose(inverse_bind[:, :3, 3], -tpose, atol=1e-7)
    mesh_node = [n for n in gltf["nodes"] if "mesh" in n]
    assert len(mesh_node) == 1 and mesh_node[0]["skin"] == 0
    assert gltf["nodes"].index(mesh_node[0]) in gltf["scenes"][0]["nodes"]   # a root node


def test_top_weights_renormalise_the_four_largest():
    weights = np.array([[0.05, 0.1, 0.15, 0.2, 0.5] + [0.0] * 17,
                        [1.0] + [0.0] * 21], np.float32)
    joints, top = top_weights(weights)
    assert sorted(joints[0]) == [1, 2, 3, 4]
    np.testing.assert_allclose(top[0], np.array([0.5, 0.2, 0.15, 0.1]) / 0.95, rtol=1e-6)
    np.testing.assert_array_equal(joints[1], [0, 0, 0, 0])
    np.testing.assert_array_equal(top[1], [1, 0, 0, 0])


def test_one_animation_with_rotation_and_translation_channels(written):
    _, (*_, rotations, root), gltf, binary = written
    assert len(gltf["animations"]) == 1
    animation = gltf["animations"][0]
    paths = sorted((c["target"]["node"], c["target"]["path"]) for c in animation["channels"])
    assert paths == sorted([(j, "rotation") for j in range(NUM_JOINTS)] + [(0, "translation")])
    sampler = animation["samplers"][0]
    times = accessor_array(gltf, binary, sampler["input"])[:, 0]
    np.testing.assert_allclose(times, np.arange(len(rotations)) / 30, atol=1e-7)
    assert gltf["accessors"][sampler["input"]]["min"] == [0.0]              # required
    for channel in animation["channels"]:
        output = accessor_array(gltf, binary, animation["samplers"][channel["sampler"]]["output"])
        if channel["target"]["path"] == "rotation":
            np.testing.assert_allclose(np.linalg.norm(output, axis=1), 1, atol=1e-6)
            assert (np.sum(output[1:] * output[:-1], axis=1) >= 0).all()   # short-way slerp


def test_node_math_reproduces_our_forward_kinematics_and_skinning(written):
    _, (points, _, weights, tpose, rotations, root), gltf, binary = written
    joints, global_rotations = forward_kinematics(rotations, root, tpose)
    attributes = gltf["meshes"][0]["primitives"][0]["attributes"]
    joint_index = accessor_array(gltf, binary, attributes["JOINTS_0"]).astype(np.int64)
    joint_weight = accessor_array(gltf, binary, attributes["WEIGHTS_0"])
    inverse_bind = accessor_array(gltf, binary, gltf["skins"][0]["inverseBindMatrices"])
    inverse_bind = inverse_bind.reshape(NUM_JOINTS, 4, 4).transpose(0, 2, 1)
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)
    for frame in range(len(rotations)):
        world = node_world_matrices(gltf, binary, frame)
        np.testing.assert_allclose(world[:, :3, 3], joints[frame], atol=1e-5)
        np.testing.assert_allclose(world[:, :3, :3], global_rotations[frame], atol=1e-5)
        # glTF skinning: sum_k w_k * world[j_k] @ inverse_bind[j_k] @ x.
        joint_matrices = world @ inverse_bind                                  # (J, 4, 4)
        skinned = np.einsum("vk,vkab,vb->va", joint_weight, joint_matrices[joint_index],
                            homogeneous)[:, :3]
        transforms = skinning_transforms(joints[frame], global_rotations[frame], tpose)
        np.testing.assert_allclose(skinned, linear_blend_skinning(points, weights, transforms),
                                   atol=1e-5)


def test_node_hierarchy_is_the_skeleton(written):
    _, (*_, tpose, _, _), gltf, _ = written
    for j, parent in enumerate(PARENTS):
        if parent >= 0:
            assert j in gltf["nodes"][parent]["children"]
            np.testing.assert_allclose(gltf["nodes"][j]["translation"], tpose[j] - tpose[parent],
                                       atol=1e-7)
        assert "rotation" not in gltf["nodes"][j]                          # identity T-pose


def test_trimesh_loads_it(written):
    path, (points, faces, *_), _, _ = written
    scene = trimesh.load(path)
    meshes = list(scene.geometry.values())
    assert len(meshes) == 1 and len(meshes[0].faces) == len(faces)


def test_point_cloud_target_and_bad_input(tmp_path):
    points, _, weights, tpose, rotations, root = rigged_target(frames=2)
    for faces in (None, np.zeros((0, 3), int)):     # glTF has no empty index list
        (tmp_path / "cloud.glb").write_bytes(glb_bytes(points, faces, weights, tpose,
                                                       rotations, root, fps=25))
        gltf, _ = read_glb(tmp_path / "cloud.glb")
        primitive = gltf["meshes"][0]["primitives"][0]
        assert primitive["mode"] == 0 and "indices" not in primitive
        assert "NORMAL" not in primitive["attributes"]
    with pytest.raises(ValueError, match="at least one frame"):
        glb_bytes(points, None, weights, tpose, rotations[:0], root[:0], fps=25)

