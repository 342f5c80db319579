"""Clothed source bodies (training/data/garments.py): on a body of tubes, the skirt lies on its
cone and follows the pelvis, not the legs; the coat's shell stands off the torso; nothing
under a garment is sampled; the cloud is area-uniform, seeded and sized as asked."""
import numpy as np
import pytest

from minretarget.conventions import JOINT_INDEX, NUM_JOINTS
from training.data.garments import (BODY, CONE, COAT_OFFSET, FLOOR_CLEARANCE, SHELL,
                                    clothed_cloud, clothed_clouds, clothed_surface, cone_length,
                                    face_segments, fit_coat, fit_skirt, sample_surface_points,
                                    vertex_normals)

JOINTS = {  # a T-pose skeleton, metres: facing +Z, its left on +X, the pelvis 1 m up
    "pelvis": (0, 1.0, 0), "left_hip": (0.1, 0.95, 0), "right_hip": (-0.1, 0.95, 0),
    "spine1": (0, 1.08, 0), "left_knee": (0.1, 0.55, 0), "right_knee": (-0.1, 0.55, 0),
    "spine2": (0, 1.2, 0), "left_ankle": (0.1, 0.1, 0), "right_ankle": (-0.1, 0.1, 0),
    "spine3": (0, 1.32, 0), "left_foot": (0.1, 0.03, 0.1), "right_foot": (-0.1, 0.03, 0.1),
    "neck": (0, 1.5, 0), "left_collar": (0.08, 1.45, 0), "right_collar": (-0.08, 1.45, 0),
    "head": (0, 1.6, 0), "left_shoulder": (0.18, 1.45, 0), "right_shoulder": (-0.18, 1.45, 0),
    "left_elbow": (0.45, 1.45, 0), "right_elbow": (-0.45, 1.45, 0),
    "left_wrist": (0.7, 1.45, 0), "right_wrist": (-0.7, 1.45, 0)}
TORSO_RADIUS, THIGH_RADIUS, ARM_RADIUS = 0.14, 0.07, 0.045
# (start, end, radius, segment): open tubes, each skinned wholly to its segment's joint.
TUBES = [((0, 0.9, 0), (0, 1.05, 0), 0.15, "pelvis"),
         ((0, 1.05, 0), (0, 1.15, 0), TORSO_RADIUS, "spine1"),
         ((0, 1.15, 0), (0, 1.3, 0), TORSO_RADIUS, "spine2"),
         ((0, 1.3, 0), (0, 1.48, 0), TORSO_RADIUS, "spine3"),
         ((0, 1.5, 0), (0, 1.75, 0), 0.08, "head"),
         *[(hip, knee, THIGH_RADIUS, side + "_hip") for side, hip, knee in
           (("left", (0.1, 0.95, 0), (0.1, 0.55, 0)), ("right", (-0.1, 0.95, 0), (-0.1, 0.55, 0)))],
         *[(knee, (x, 0.0, 0), 0.05, side + "_knee") for side, knee, x in
           (("left", (0.1, 0.55, 0), 0.1), ("right", (-0.1, 0.55, 0), -0.1))],
         *[((sign * 0.16, 1.45, 0), (sign * 0.45, 1.45, 0), ARM_RADIUS, side + "_shoulder")
           for side, sign in (("left", 1), ("right", -1))],
         *[((sign * 0.45, 1.45, 0), (sign * 0.72, 1.45, 0), 0.035, side + "_elbow")
           for side, sign in (("left", 1), ("right", -1))]]


def tube(start, end, radius, sectors=48, rings=16):
    """An open cylinder from ``start`` to ``end``: (rings * sectors, 3) vertices and its
    triangles, wound outward (normals away from its axis)."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    axis = (end - start) / np.linalg.norm(end - start)
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    angle = np.linspace(0, 2 * np.pi, sectors, endpoint=False)
    along = np.linspace(0, 1, rings)
    vertices = (start + along[:, None, None] * (end - start)
                + radius * (np.cos(angle)[None, :, None] * u + np.sin(angle)[None, :, None] * v))
    ring, sector = np.meshgrid(np.arange(rings - 1), np.arange(sectors), indexing="ij")
    a, b = ring * sectors + sector, ring * sectors + (sector + 1) % sectors
    faces = np.concatenate([np.stack([a, b, a + sectors], -1).reshape(-1, 3),
                            np.stack([b, b + sectors, a + sectors], -1).reshape(-1, 3)])
    vertices = vertices.reshape(-1, 3)
    # wound outward: each face's normal points away from the axis
    corners = vertices[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    centre = corners.mean(axis=1)
    radial = centre - start - ((centre - start) @ axis)[:, None] * axis
    assert (np.einsum("fi,fi->f", normal, radial) > 0).all()
    return vertices, faces


def tube_body():
    """(vertices (V, 3), faces (F, 3), joints (J, 3), weights (V, J) one-hot) of the tubes."""
    vertices, faces, weights = [], [], []
    for start, end, radius, segment in TUBES:
        v, f = tube(start, end, radius)
        faces.append(f + sum(len(x) for x in vertices))
        vertices.append(v)
        w = np.zeros((len(v), NUM_JOINTS))
        w[:, JOINT_INDEX[segment]] = 1.0
        weights.append(w)
    joints = np.zeros((NUM_JOINTS, 3))
    for name, position in JOINTS.items():
        joints[JOINT_INDEX[name]] = position
    return np.concatenate(vertices), np.concatenate(faces), joints, np.concatenate(weights)


VERTICES, FACES, TPOSE_JOINTS, WEIGHTS = tube_body()
SEGMENTS = face_segments(WEIGHTS, FACES)
SKIRT = fit_skirt(VERTICES, TPOSE_JOINTS, WEIGHTS)
COAT = fit_coat(VERTICES, TPOSE_JOINTS, WEIGHTS)


def turn_and_move(points, angle, shift):
    """Points turned about +Y by ``angle`` radians (about the origin), then moved by shift."""
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return points @ rotation.T + np.asarray(shift)


def frame_of(joints):
    """The pelvis, and its left and forward axes, computed here from the hips."""
    left = joints[JOINT_INDEX["left_hip"]] - joints[JOINT_INDEX["right_hip"]]
    left[1] = 0
    left /= np.linalg.norm(left)
    return joints[JOINT_INDEX["pelvis"]], left, np.cross(left, [0.0, 1.0, 0.0])


def cone_coordinates(points, joints, cone):
    """Per point: its depth below the cone's top ring and its elliptic radius there (1 on the
    cone's surface), the frame computed independently of the module."""
    origin, left, forward = frame_of(joints)
    local = points - origin
    depth = cone.top - local[:, 1]
    a = cone.radii[0] + cone.flare * depth
    b = cone.radii[1] + cone.flare * depth
    return depth, np.hypot((local @ left) / a, (local @ forward) / b), np.minimum(a, b)


def swing_left_leg(vertices, joints, angle):
    """The left leg (thigh and shin, and its joints below the hip) turned forward by
    ``angle`` radians about the left hip's left-right axis."""
    hip = np.asarray(JOINTS["left_hip"])
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])       # -Y (down) towards +Z
    leg = np.isin(np.argmax(WEIGHTS, 1), [JOINT_INDEX["left_hip"], JOINT_INDEX["left_knee"]])
    vertices, joints = vertices.copy(), joints.copy()
    vertices[leg] = (vertices[leg] - hip) @ rotation.T + hip
    below = [JOINT_INDEX[n] for n in ("left_knee", "left_ankle", "left_foot")]
    joints[below] = (joints[below] - hip) @ rotation.T + hip
    return vertices, joints


def test_the_fitted_garments_have_the_bodys_size():
    # top ring at the waist (spine1, 8 cm above the pelvis), hem a quarter down the shin
    assert SKIRT.cone.top == pytest.approx(0.08)
    assert SKIRT.cone.length == pytest.approx(0.08 + 0.45 + 0.25 * 0.45)
    # the widest lower-body vertex in that band: the pelvis tube (0.15) or a thigh's outside
    assert SKIRT.cone.radii[0] == pytest.approx(0.17 + 0.03, abs=1e-6)
    assert SKIRT.cone.radii[1] == pytest.approx(0.15 + 0.03, abs=1e-6)
    assert COAT.cone.length == pytest.approx(0.08 + 0.05 + 0.2)        # mid-thigh
    assert COAT.offset == COAT_OFFSET


@pytest.mark.parametrize("angle, shift", [(0.0, (0, 0, 0)), (2.3, (1.5, 0.2, -2.0))])
def test_skirt_points_lie_on_the_cone_and_nothing_under_it_is_sampled(angle, shift):
    vertices = turn_and_move(VERTICES, angle, shift)
    joints = turn_and_move(TPOSE_JOINTS, angle, shift)
    points, part = clothed_cloud(vertices, FACES, joints, SKIRT, SEGMENTS, 20_000,
                                 np.random.default_rng(1))
    points = points.astype(np.float64)
    on = part == CONE
    depth, radius, smallest = cone_coordinates(points[on], joints, SKIRT.cone)
    assert np.abs(radius - 1).max() * smallest.max() < 1e-3          # on the surface, < 1 mm
    assert depth.min() > -1e-6 and depth.max() < SKIRT.cone.length + 1e-6
    assert depth.min() < 0.02 and depth.max() > SKIRT.cone.length - 0.02   # all of its length
    # no body point inside the skirt (its volume shrunk by 5 mm): the thighs are gone ...
    depth, radius, smallest = cone_coordinates(points[part == BODY], joints, SKIRT.cone)
    inside = (depth > 0.005) & (depth < SKIRT.cone.length - 0.005) & (radius * smallest
                                                                      < smallest - 0.005)
    assert not inside.any()
    # ... the shins below the hem and the torso above the waist are not
    assert (depth > SKIRT.cone.length + 0.02).sum() > 1000
    assert (depth < -0.05).sum() > 1000


def test_the_skirt_turns_and_moves_with_the_pelvis():
    still = clothed_surface(VERTICES, FACES, TPOSE_JOINTS, SKIRT, SEGMENTS)
    for angle, shift in ((0.7, (0, 0, 0)), (0.0, (1.5, 0.2, -2.0)), (-2.0, (-0.3, 0.1, 0.8))):
        moved = clothed_surface(turn_and_move(VERTICES, angle, shift), FACES,
                                turn_and_move(TPOSE_JOINTS, angle, shift), SKIRT, SEGMENTS)
        np.testing.assert_allclose(moved.vertices[len(VERTICES):],
                                   turn_and_move(still.vertices[len(VERTICES):], angle, shift),
                                   atol=1e-9)
        np.testing.assert_array_equal(moved.hidden, still.hidden)
        # and it did turn: its vertices are not the unturned ones moved
        if angle:
            assert np.abs(moved.vertices[len(VERTICES):]
                          - still.vertices[len(VERTICES):] - shift).max() > 0.01


def test_the_skirt_does_not_follow_the_legs():
    still = clothed_surface(VERTICES, FACES, TPOSE_JOINTS, SKIRT, SEGMENTS)
    vertices, joints = swing_left_leg(VERTICES, TPOSE_JOINTS, np.radians(50))
    kicked = clothed_surface(vertices, FACES, joints, SKIRT, SEGMENTS)
    np.testing.assert_array_equal(kicked.vertices[len(VERTICES):],
                                  still.vertices[len(VERTICES):])      # the same skirt
    # the thigh now leaves the cone at the front: more of the leg is seen
    assert kicked.hidden.sum() < still.hidden.sum() - 50
    points, part = clothed_cloud(vertices, FACES, joints, SKIRT, SEGMENTS, 20_000,
                                 np.random.default_rng(2))
    depth, radius, _ = cone_coordinates(points[part == BODY].astype(np.float64), joints,
                                        SKIRT.cone)
    front = points[part == BODY][:, 2]
    assert ((depth > 0.05) & (depth < SKIRT.cone.length) & (radius > 1) & (front > 0.2)).sum() > 20


def test_the_coat_shell_stands_off_the_torso_and_replaces_it():
    points, part = clothed_cloud(VERTICES, FACES, TPOSE_JOINTS, COAT, SEGMENTS, 30_000,
                                 np.random.default_rng(3))
    points = points.astype(np.float64)
    shell = points[part == SHELL]
    torso = shell[(np.abs(shell[:, 0]) < 0.1) & (shell[:, 1] > 1.08) & (shell[:, 1] < 1.45)]
    distance = np.hypot(torso[:, 0], torso[:, 2])
    assert len(torso) > 1000
    np.testing.assert_allclose(distance, TORSO_RADIUS + COAT_OFFSET, atol=2e-3)
    arm = shell[(np.abs(shell[:, 0]) > 0.25) & (np.abs(shell[:, 0]) < 0.42)]
    assert len(arm) > 100
    np.testing.assert_allclose(np.hypot(arm[:, 1] - 1.45, arm[:, 2]), ARM_RADIUS + COAT_OFFSET,
                               atol=2e-3)
    # the bare torso and upper arms are gone; the forearms, head and shins are seen
    body = points[part == BODY]
    on_torso = (np.abs(np.hypot(body[:, 0], body[:, 2]) - TORSO_RADIUS) < 2e-3) & (
        body[:, 1] > 1.06) & (body[:, 1] < 1.47)
    assert not on_torso.any()
    on_arm = (np.abs(np.hypot(body[:, 1] - 1.45, body[:, 2]) - ARM_RADIUS) < 2e-3) & (
        np.abs(body[:, 0]) > 0.17) & (np.abs(body[:, 0]) < 0.44)
    assert not on_arm.any()
    assert (np.abs(body[:, 0]) > 0.46).sum() > 100 and (body[:, 1] > 1.5).sum() > 100
    # the tube: on its cone, over the hips to mid-thigh, the thighs inside it hidden
    depth, radius, smallest = cone_coordinates(points[part == CONE], TPOSE_JOINTS, COAT.cone)
    assert np.abs(radius - 1).max() * smallest.max() < 1e-3
    depth, radius, smallest = cone_coordinates(body, TPOSE_JOINTS, COAT.cone)
    assert not ((depth > 0.005) & (depth < COAT.cone.length - 0.005)
                & (radius * smallest < smallest - 0.005)).any()
    assert ((depth > COAT.cone.length + 0.02) & (body[:, 1] > 0.56)).sum() > 100  # lower thighs


def test_the_cloud_is_area_uniform_over_body_and_garment():
    surface = clothed_surface(VERTICES, FACES, TPOSE_JOINTS, COAT, SEGMENTS)
    corners = surface.vertices[surface.faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1)
    count = 40_000
    _, part = clothed_cloud(VERTICES, FACES, TPOSE_JOINTS, COAT, SEGMENTS, count,
                            np.random.default_rng(4))
    for which in (BODY, SHELL, CONE):
        share = area[surface.part == which].sum() / area.sum()
        sigma = np.sqrt(share * (1 - share) / count)
        assert abs((part == which).mean() - share) < 4 * sigma
    # and within the faces: the points' barycentric spread is uniform in one big triangle
    triangle = np.array([[0.0, 0, 0], [2, 0, 0], [0, 1, 0]])
    points, face = sample_surface_points(triangle, np.array([[0, 1, 2]]), count,
                                         np.random.default_rng(5))
    assert (face == 0).all()
    left = points[:, 0] < 2.0 - np.sqrt(2)        # x = 2 - sqrt 2 cuts its area in half
    assert abs(left.mean() - 0.5) < 4 * np.sqrt(0.25 / count)


def test_counts_dtypes_and_seeds():
    one = clothed_cloud(VERTICES, FACES, TPOSE_JOINTS, SKIRT, SEGMENTS, 2048,
                        np.random.default_rng(7))
    again = clothed_cloud(VERTICES, FACES, TPOSE_JOINTS, SKIRT, SEGMENTS, 2048,
                          np.random.default_rng(7))
    other = clothed_cloud(VERTICES, FACES, TPOSE_JOINTS, SKIRT, SEGMENTS, 2048,
                          np.random.default_rng(8))
    assert one[0].shape == (2048, 3) and one[0].dtype == np.float32 and one[1].shape == (2048,)
    np.testing.assert_array_equal(one[0], again[0])
    np.testing.assert_array_equal(one[1], again[1])
    assert not np.array_equal(one[0], other[0])
    # a sequence: one generator through the frames, a fresh sample each frame
    vertices = np.stack([turn_and_move(VERTICES, a, (a, 0, 0)) for a in (0.0, 0.3, 0.6)])
    joints = np.stack([turn_and_move(TPOSE_JOINTS, a, (a, 0, 0)) for a in (0.0, 0.3, 0.6)])
    clouds, parts = clothed_clouds(vertices, FACES, joints, COAT, SEGMENTS, 512,
                                   np.random.default_rng(9))
    assert clouds.shape == (3, 512, 3) and parts.shape == (3, 512)
    rng = np.random.default_rng(9)
    for t in range(3):
        points, part = clothed_cloud(vertices[t], FACES, joints[t], COAT, SEGMENTS, 512, rng)
        np.testing.assert_array_equal(clouds[t], points)
        np.testing.assert_array_equal(parts[t], part)
    with pytest.raises(ValueError):
        clothed_clouds(vertices, FACES, joints[:2], COAT, SEGMENTS, 512, rng)


def test_the_hem_stays_off_the_floor():
    # everything above the knees sunk by 0.55 m, the shins and feet kept (a crude deep
    # crouch): the waist 0.53 m above the floor, less than the skirt's length
    vertices, joints = VERTICES.copy(), TPOSE_JOINTS.copy()
    vertices[vertices[:, 1] > 0.6, 1] -= 0.55
    joints[joints[:, 1] > 0.6, 1] -= 0.55
    surface = clothed_surface(vertices, FACES, joints, SKIRT, SEGMENTS)
    cone = surface.vertices[len(vertices):]
    floor = vertices[:, 1].min()
    assert cone[:, 1].min() == pytest.approx(floor + FLOOR_CLEARANCE)
    assert surface.cone_length < SKIRT.cone.length - 0.1
    origin = joints[JOINT_INDEX["pelvis"]]
    assert cone_length(SKIRT.cone, origin, None) == SKIRT.cone.length
    assert cone_length(SKIRT.cone, origin, floor - 5.0) == SKIRT.cone.length


def test_vertex_normals_point_out_and_segments_follow_the_weights():
    v, f = tube((0, 0, 0), (0, 1, 0), 0.3)
    normals = vertex_normals(v, f)
    radial = v * [1, 0, 1]
    # radial (the open ends' rings lean by the lopsided triangles there: 2e-4)
    np.testing.assert_allclose(np.einsum("vi,vi->v", normals, radial / 0.3), 1.0, atol=1e-3)
    middle = (v[:, 1] > 0.01) & (v[:, 1] < 0.99)
    np.testing.assert_allclose(np.einsum("vi,vi->v", normals, radial / 0.3)[middle], 1.0,
                               atol=1e-9)
    # vertices 0 and 1 mostly on joint 3, vertex 2 wholly on 5, vertex 3 wholly on 3: the
    # face (0, 1, 2) sums 1.1 on joint 3 and 1.9 on 5 (a vote of its corners would say 3)
    weights = np.zeros((4, NUM_JOINTS))
    weights[[0, 1], 3] = 0.55
    weights[[0, 1], 5] = 0.45
    weights[2, 5] = 1.0
    weights[3, 3] = 1.0
    np.testing.assert_array_equal(face_segments(weights, np.array([[0, 1, 2], [0, 1, 3]])),
                                  [5, 3])


def test_undressed_cuts_the_covered_body_away_and_adds_nothing():
    vertices, joints = swing_left_leg(VERTICES, TPOSE_JOINTS, np.radians(20))
    for garment in (SKIRT, COAT):
        dressed = clothed_surface(vertices, FACES, joints, garment, SEGMENTS)
        cut = clothed_surface(vertices, FACES, joints, garment, SEGMENTS, dressed=False)
        np.testing.assert_array_equal(cut.hidden, dressed.hidden)
        assert (cut.part == BODY).all() and len(cut.vertices) == len(VERTICES)
        np.testing.assert_array_equal(cut.faces, FACES[~dressed.hidden])
        np.testing.assert_array_equal(cut.faces, dressed.faces[dressed.part == BODY])
        points, part = clothed_cloud(vertices, FACES, joints, garment, SEGMENTS, 4096,
                                     np.random.default_rng(11), dressed=False)
        assert (part == BODY).all()
        depth, radius, smallest = cone_coordinates(points.astype(np.float64), joints,
                                                   garment.cone)
        assert not ((depth > 0.005) & (depth < garment.cone.length - 0.005)
                    & (radius * smallest < smallest - 0.005)).any()
