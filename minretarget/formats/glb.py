"""glTF 2.0 binary (``.glb``) of a rigged, animated target, written from the specification.

What the file holds (glTF: metres, +Y up, right-handed: exactly the canonical frame, so no
conversion; the T-pose faces +Z, glTF's "front"):
    nodes 0..21   the 22 joints, named and nested as ``minretarget.conventions``; each node's
                  translation is its T-pose offset from its parent (the pelvis: its T-pose
                  position) and its rotation the identity. Our local rotations are expressed
                  in these world-aligned frames, so they are the nodes' glTF rotations as they
                  are, and the root translation is the pelvis node's translation.
    node 22       the target mesh (or point cloud), at the scene root, skinned by skin 0.
    mesh 0        POSITION (T-pose, with min/max), NORMAL (area-weighted, meshes only),
                  JOINTS_0 (unsigned byte) and WEIGHTS_0 (float): each vertex's 4 largest
                  skinning weights renormalised to sum to 1 (unused slots: joint 0, weight 0);
                  indices (unsigned int) for triangles, or POINTS mode without faces.
    skin 0        the 22 joint nodes; inverse bind matrices undo each joint's T-pose position.
    animation 0   per joint a LINEAR rotation channel (quaternions stored (x, y, z, w), the
                  glTF order, with signs made continuous so that interpolation takes the short
                  way), and a LINEAR translation channel on the pelvis; key times k / fps.
Layout: one buffer, one bufferView per accessor, each starting on a 4-byte boundary, tightly
packed (no byteStride); the JSON chunk is padded with spaces and the BIN chunk with zeros.
"""
import json
import struct

import numpy as np

from .. import __version__
from ..atomic import atomic_write
from ..conventions import JOINT_NAMES, NUM_JOINTS, PARENTS
from ..validation import as_float32_array

GLB_MAGIC, GLB_VERSION = 0x46546C67, 2                  # b"glTF", container version 2
JSON_CHUNK, BIN_CHUNK = 0x4E4F534A, 0x004E4942           # b"JSON", b"BIN\0"
FLOAT, UNSIGNED_BYTE, UNSIGNED_INT = 5126, 5121, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
TRIANGLES, POINTS = 4, 0
_COMPONENT_DTYPES = {FLOAT: np.float32, UNSIGNED_BYTE: np.uint8, UNSIGNED_INT: np.uint32,
                     5120: np.int8, 5122: np.int16, 5123: np.uint16}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_MESH_NODE = NUM_JOINTS


class _Buffer:
    """Collects the binary chunk and the bufferViews and accessors that describe it."""

    def __init__(self):
        self.data = bytearray()
        self.buffer_views, self.accessors = [], []

    def add(self, array, kind, target=None, bounds=False):
        """Append a (count, n) or (count,) array as one accessor; returns its index."""
        array = np.ascontiguousarray(array)
        self.data.extend(b"\0" * (-len(self.data) % 4))
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.data.extend(array.tobytes())
        self.buffer_views.append(view)
        component = {np.dtype(v): k for k, v in _COMPONENT_DTYPES.items()}[array.dtype]
        accessor = {"bufferView": len(self.buffer_views) - 1, "componentType": component,
                    "count": int(array.shape[0]), "type": kind}
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            accessor["min"] = [float(v) for v in flat.min(axis=0)]
            accessor["max"] = [float(v) for v in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def vertex_normals(points, faces):
    """(V, 3) points, (F, 3) triangles -> (V, 3) float32 unit normals, area-weighted; a vertex
    on no triangle (or only degenerate ones) gets +Y, since glTF wants unit normals."""
    corners = points[faces]                                                  # (F, 3, 3)
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(points, dtype=np.float64)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(length > 0, normals / np.where(length > 0, length, 1), [0.0, 1.0, 0.0])
    return normals.astype(np.float32)


def top_weights(skin_weights, count=4):
    """(V, J) skinning weights -> (V, count) uint8 joints and (V, count) float32 weights: the
    ``count`` largest, renormalised to sum to 1; slots of weight zero point at joint 0."""
    order = np.argsort(-skin_weights, axis=1, kind="stable")[:, :count]      # (V, count)
    weights = np.take_along_axis(skin_weights, order, axis=1).astype(np.float64)
    weights /= weights.sum(axis=1, keepdims=True)
    joints = np.where(weights > 0, order, 0)
    return joints.astype(np.uint8), weights.astype(np.float32)


def continuous_quaternions(quaternions):
    """(T, ..., 4) quaternions -> the same rotations with each frame's sign chosen nearest
    the previous frame's, float64, normalised."""
    q = np.array(quaternions, dtype=np.float64)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    for t in range(1, len(q)):
        flip = np.sum(q[t] * q[t - 1], axis=-1) < 0
        q[t][flip] *= -1
    return q


def glb_bytes(points, faces, skin_weights, tpose_joints, rotations, root, fps):
    """Encode the rigged, animated target as a ``.glb`` (module docstring).

    Args:
        points: (V, 3) T-pose target points, metres, canonical axes.
        faces: (F, 3) int triangles, or None for a point cloud.
        skin_weights: (V, J) skinning weights (rows >= 0, summing to 1).
        tpose_joints: (J, 3) T-pose joints, metres.
        rotations: (T, J, 4) local quaternions (w, x, y, z), T >= 1.
        root: (T, 3) pelvis positions, metres.
        fps: frames per second of the animation.
    Returns:
        bytes of the GLB file.
    """
    points = as_float32_array(points, "points", (None, 3))
    skin_weights = as_float32_array(skin_weights, "skin_weights", (len(points), NUM_JOINTS))
    tpose_joints = as_float32_array(tpose_joints, "tpose_joints", (NUM_JOINTS, 3))
    rotations = as_float32_array(rotations, "rotations", (None, NUM_JOINTS, 4))
    root = as_float32_array(root, "root", (len(rotations), 3))
    if len(rotations) == 0 or not fps > 0:
        raise ValueError(f"a glTF animation needs at least one frame and fps > 0, got "
                         f"{len(rotations)} frames at {fps} fps")
    buffer = _Buffer()
    attributes = {"POSITION": buffer.add(points, "VEC3", ARRAY_BUFFER, bounds=True)}
    primitive = {"attributes": attributes, "mode": POINTS}
    if faces is not None and len(faces):     # glTF allows no empty index list: no faces, points
        faces = np.asarray(faces, dtype=np.int64)
        attributes["NORMAL"] = buffer.add(vertex_normals(points, faces), "VEC3", ARRAY_BUFFER)
        primitive["indices"] = buffer.add(faces.reshape(-1).astype(np.uint32), "SCALAR",
                                          ELEMENT_ARRAY_BUFFER)
        primitive["mode"] = TRIANGLES
    joints, weights = top_weights(skin_weights)
    attributes["JOINTS_0"] = buffer.add(joints, "VEC4", ARRAY_BUFFER)
    attributes["WEIGHTS_0"] = buffer.add(weights, "VEC4", ARRAY_BUFFER)

    # Inverse bind matrices: translation by -t[j], stored column-major (the translation last).
    inverse_bind = np.tile(np.eye(4, dtype=np.float32), (NUM_JOINTS, 1, 1))  # (J, 4, 4)
    inverse_bind[:, :3, 3] = -tpose_joints
    inverse_bind = np.swapaxes(inverse_bind, 1, 2).reshape(NUM_JOINTS, 16)   # column-major
    skin = {"joints": list(range(NUM_JOINTS)), "skeleton": 0,
            "inverseBindMatrices": buffer.add(inverse_bind, "MAT4")}

    nodes = []
    for j, name in enumerate(JOINT_NAMES):
        parent = PARENTS[j]
        offset = tpose_joints[j] - (tpose_joints[parent] if parent >= 0 else 0)
        node = {"name": name, "translation": [float(v) for v in offset]}
        children = [c for c in range(NUM_JOINTS) if PARENTS[c] == j]
        if children:
            node["children"] = children
        nodes.append(node)
    nodes.append({"name": "target", "mesh": 0, "skin": 0})

    times = (np.arange(len(rotations)) / float(fps)).astype(np.float32)
    time_accessor = buffer.add(times, "SCALAR", bounds=True)
    xyzw = continuous_quaternions(rotations)[..., [1, 2, 3, 0]].astype(np.float32)
    samplers, channels = [], []
    for j in range(NUM_JOINTS):
        samplers.append({"input": time_accessor, "interpolation": "LINEAR",
                         "output": buffer.add(xyzw[:, j], "VEC4")})
        channels.append({"sampler": j, "target": {"node": j, "path": "rotation"}})
    samplers.append({"input": time_accessor, "interpolation": "LINEAR",
                     "output": buffer.add(root, "VEC3")})
    channels.append({"sampler": NUM_JOINTS, "target": {"node": 0, "path": "translation"}})

    gltf = {
        "asset": {"version": "2.0", "generator": f"minretarget {__version__}"},
        "scene": 0, "scenes": [{"name": "retargeted", "nodes": [0, _MESH_NODE]}],
        "nodes": nodes, "meshes": [{"name": "target", "primitives": [primitive]}],
        "skins": [skin],
        "animations": [{"name": "retargeted", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": len(buffer.data)}],
        "bufferViews": buffer.buffer_views, "accessors": buffer.accessors,
    }
    return _pack(gltf, bytes(buffer.data))


def _pack(gltf, binary):
    """The GLB container: 12-byte header, JSON chunk, BIN chunk, each 4-byte aligned."""
    text = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    length = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([struct.pack("<III", GLB_MAGIC, GLB_VERSION, length),
                     struct.pack("<II", len(text), JSON_CHUNK), text,
                     struct.pack("<II", len(binary), BIN_CHUNK), binary])


def write_glb(path, *args, **kwargs):
    """Write ``glb_bytes(*args, **kwargs)`` to ``path`` atomically."""
    data = glb_bytes(*args, **kwargs)
    with atomic_write(path) as file:
        file.write(data)


# ----------------------------------------------------------------------------- reading

def read_glb(path):
    """Split a ``.glb`` file into its glTF JSON (dict) and its BIN chunk (bytes).

    Raises ValueError naming the file for a bad header, length or chunk layout.
    """
    with open(path, "rb") as file:
        data = file.read()
    if len(data) < 20:
        raise ValueError(f"{path}: too short for a GLB file ({len(data)} bytes)")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != GLB_VERSION or length != len(data):
        raise ValueError(f"{path}: bad GLB header (magic {magic:#x}, version {version}, "
                         f"length {length} for {len(data)} bytes)")
    chunks, offset = [], 12
    while offset < length:
        if offset + 8 > length:
            raise ValueError(f"{path}: truncated chunk header at byte {offset}")
        size, kind = struct.unpack_from("<II", data, offset)
        if size % 4 or offset + 8 + size > length:
            raise ValueError(f"{path}: chunk at byte {offset} has bad length {size}")
        chunks.append((kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
    if not chunks or chunks[0][0] != JSON_CHUNK:
        raise ValueError(f"{path}: the first chunk must be JSON")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == BIN_CHUNK else b""
    return json.loads(chunks[0][1].decode("utf-8")), binary


def accessor_array(gltf, binary, index):
    """The data of accessor ``index`` as a (count, components) array (MAT4: 16 components,
    column-major as stored); tightly packed or strided bufferViews."""
    accessor = gltf["accessors"][index]
    view = gltf["bufferViews"][accessor["bufferView"]]
    dtype = np.dtype(_COMPONENT_DTYPES[accessor["componentType"]])
    components = _TYPE_SIZES[accessor["type"]]
    stride = view.get("byteStride", dtype.itemsize * components)
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    return np.ndarray((accessor["count"], components), dtype, buffer=binary, offset=start,
                      strides=(stride, dtype.itemsize)).copy()
