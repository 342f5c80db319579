"""The single-view depth camera (training/data/depth_camera.py): occlusion, back faces, exact
depths, subsampling and the benchmark's camera placement, on hand-made meshes."""
import math

import numpy as np
import pytest

from minretarget.kinematics import quaternion_to_matrix
from training.data.depth_camera import (AXIAL_NOISE, LATERAL_NOISE_PIXELS, body_axes,
                                        look_at, render, sensor_noise, view_cameras,
                                        visible_points)


def square(z, half, facing=+1):
    """A square of side 2 * half in the plane z, its normal +Z (facing=+1) or -Z: 4 vertices,
    2 triangles wound counter-clockwise seen from the side it faces."""
    vertices = np.array([[-half, -half, z], [half, -half, z], [half, half, z],
                         [-half, half, z]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]]) if facing > 0 else np.array([[0, 2, 1],
                                                                          [0, 3, 2]])
    return vertices, faces


def cube(half=0.5):
    """The closed cube [-half, half]^3, wound outward."""
    vertices = np.array([[x, y, z] for x in (-half, half) for y in (-half, half)
                         for z in (-half, half)], np.float64)
    index = {tuple(np.sign(v).astype(int)): i for i, v in enumerate(vertices)}
    faces = []
    for axis in range(3):
        for side in (-1, 1):
            # the face's corners counter-clockwise seen from outside (along side * axis)
            u, v = (axis + 1) % 3, (axis + 2) % 3
            corners = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                key = [0, 0, 0]
                key[axis], key[u], key[v] = side, a, b * side
                corners.append(index[tuple(key)])
            faces += [[corners[0], corners[1], corners[2]], [corners[0], corners[2], corners[3]]]
    return vertices, np.array(faces)


def merged(*meshes):
    vertices, faces, start = [], [], 0
    for v, f in meshes:
        vertices.append(v)
        faces.append(f + start)
        start += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def signed_volume(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6


CAMERA = look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0])      # on +Z, looking down -Z


def test_the_nearer_square_hides_the_farther_one():
    front = square(1.0, 0.5)
    back = square(0.0, 0.5)
    _, points, depth = render(*merged(back, front), CAMERA)
    assert len(points) > 5_000
    np.testing.assert_allclose(points[:, 2], 1.0, atol=1e-9)       # every one on the front
    np.testing.assert_allclose(depth, 2.0, atol=1e-9)
    assert np.abs(points[:, :2]).max() <= 0.5 + 1e-9
    # alone, the back square is seen, as large as its distance makes it
    _, alone, _ = render(*back, CAMERA)
    np.testing.assert_allclose(alone[:, 2], 0.0, atol=1e-9)
    side = CAMERA.focal * 1.0 / 3.0                                   # pixels across it
    assert abs(len(alone) - side ** 2) < 4 * side + 4
    side = CAMERA.focal * 1.0 / 2.0
    assert abs(len(points) - side ** 2) < 4 * side + 4


def test_a_smaller_front_square_leaves_the_rim_of_the_back_one():
    front, back = square(1.0, 0.25), square(0.0, 0.5)
    _, points, _ = render(*merged(front, back), CAMERA)
    on_back = np.abs(points[:, 2]) < 1e-9
    assert on_back.any() and (~on_back).any()
    # no back point lies where the front square covers it: its ray from (0, 0, 3) would
    # cross the front one (at z = 1, 2/3 of the way)
    shadow = np.abs(points[on_back][:, :2] * 2.0 / 3.0).max(axis=1) < 0.25 - 0.01
    assert not shadow.any()


def test_back_faces_are_culled():
    away = square(0.0, 0.5, facing=-1)
    pixels, points, depth = render(*away, CAMERA)
    assert len(pixels) == len(points) == len(depth) == 0
    # the same square seen from behind is front-facing
    _, points, _ = render(*away, look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0]))
    assert len(points) > 4_000


def test_a_cube_from_the_front_shows_its_front_face_only():
    vertices, faces = cube()
    assert signed_volume(vertices, faces) == pytest.approx(1.0)      # wound outward
    pixels, points, depth = render(vertices, faces, CAMERA)
    assert len(points) > 5_000
    np.testing.assert_allclose(points[:, 2], 0.5, atol=1e-9)
    assert np.abs(points[:, :2]).max() <= 0.5 + 1e-9
    assert len(np.unique(pixels)) == len(pixels)                      # one point a pixel
    # from its +X side, the +X face only; from a corner, three faces
    _, points, _ = render(vertices, faces, look_at([3.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    np.testing.assert_allclose(points[:, 0], 0.5, atol=1e-9)
    _, points, _ = render(vertices, faces, look_at([2.0, 1.5, 2.0], [0.0, 0.0, 0.0]))
    on = np.isclose(np.abs(points), 0.5, atol=1e-9) & (points > 0)
    assert on.any(axis=1).all() and on.any(axis=0).all()


def test_points_lie_on_the_seen_triangle_of_a_tilted_plane():
    rng = np.random.default_rng(0)
    vertices = np.array([[-0.6, -0.5, -0.2], [0.7, -0.4, 0.3], [0.1, 0.6, -0.1]])
    faces = np.array([[0, 1, 2]])
    camera = look_at([0.3, 0.2, 2.5], [0.0, 0.0, 0.0])
    _, points, depth = render(vertices, faces, camera)
    assert len(points) > 1_000
    normal = np.cross(vertices[1] - vertices[0], vertices[2] - vertices[0])
    np.testing.assert_allclose((points - vertices[0]) @ normal, 0.0, atol=1e-9)
    np.testing.assert_allclose((points - camera.position) @ camera.rotation[2], depth)
    # the ray from the camera through each point reaches the pixel centre it came from
    local = (points - camera.position) @ camera.rotation.T
    columns = camera.focal * local[:, 0] / local[:, 2] + camera.width / 2 - 0.5
    np.testing.assert_allclose(columns, np.round(columns), atol=1e-6)
    # visible_points: a seeded subset, or all in a random order
    few = visible_points(vertices, faces, camera, 256, np.random.default_rng(1))
    assert few.shape == (256, 3) and few.dtype == np.float32
    np.testing.assert_array_equal(few, visible_points(vertices, faces, camera, 256,
                                                      np.random.default_rng(1)))
    every = visible_points(vertices, faces, camera, 10 ** 6, rng)
    assert len(every) == len(points)
    np.testing.assert_allclose(np.sort(every[:, 0]), np.sort(points[:, 0]).astype(np.float32))


def test_nothing_behind_the_camera_or_beyond_its_range():
    vertices, faces = square(4.0, 0.5)                 # behind a camera at z = 3 looking -Z
    assert len(render(vertices, faces, CAMERA)[0]) == 0
    vertices, faces = square(-10.0, 3.0)               # 13 m away: past the far plane
    assert len(render(vertices, faces, CAMERA)[0]) == 0


@pytest.mark.parametrize("distance", [1.0, 2.5, 4.0])
def test_sensor_noise_is_the_model_s_along_the_ray_and_across_it(distance):
    """Points of a plane facing a camera at ``distance``: the noise moves each along its own
    ray by the axial model's deviation at that depth, and across the image by 0.8 pixels."""
    camera = look_at([0.3, 1.2, distance], [0.3, 1.2, 0.0])       # looking down -Z
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(0.1, 0.5, 20_000), rng.uniform(1.0, 1.4, 20_000),
                              np.zeros(20_000)])
    noisy = sensor_noise(points, camera, np.random.default_rng(1)).astype(np.float64)
    base, growth, offset = AXIAL_NOISE
    rays = points - camera.position
    depth = rays @ camera.rotation[2]
    along = (noisy - camera.position) @ camera.rotation[2] - depth
    assert np.std(along) == pytest.approx(base + growth * (distance - offset) ** 2, rel=0.05)
    assert abs(np.mean(along)) < 3 * np.std(along) / np.sqrt(len(along))
    # across: the pixel each lands on moves by 0.8 pixels' deviation, at its own depth
    pixels = lambda p: ((p - camera.position) @ camera.rotation[:2].T  # noqa: E731
                        / ((p - camera.position) @ camera.rotation[2])[:, None] * camera.focal)
    moved = pixels(noisy) - pixels(points)
    assert np.std(moved, axis=0) == pytest.approx([LATERAL_NOISE_PIXELS] * 2, rel=0.05)
    assert sensor_noise(points[:0], camera, np.random.default_rng(1)).shape == (0, 3)


def test_view_cameras_stand_in_front_beside_and_behind_the_body():
    turned = np.array([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0])   # +Z -> +X
    forward, left = body_axes(turned)
    np.testing.assert_allclose(forward, [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(left, [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(quaternion_to_matrix(turned.astype(np.float32))[:, 2],
                               [1, 0, 0], atol=1e-6)
    root = np.array([1.0, 0.9, -2.0])
    cameras = view_cameras(turned, root, 1.2)
    expected = {"front": [3.5, 1.2, -2.0], "side": [1.0, 1.2, -4.5], "back": [-1.5, 1.2, -2.0]}
    for name, camera in cameras.items():
        np.testing.assert_allclose(camera.position, expected[name], atol=1e-6)
        towards = np.array([1.0, 1.2, -2.0]) - camera.position
        np.testing.assert_allclose(camera.rotation[2], towards / np.linalg.norm(towards))
        np.testing.assert_allclose(camera.rotation[1], [0, -1, 0], atol=1e-12)  # upright
        np.testing.assert_allclose(camera.rotation @ camera.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(camera.rotation) == pytest.approx(1.0)


# ----------------------------------------------------------------------------- the benchmark

def test_single_view_streams_hold_the_last_result_over_lost_frames(tiny_weights, tiny_stream):
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import single_view
    from minretarget.retargeter import Retargeter

    target, sources, _ = tiny_stream
    retargeter = Retargeter(tiny_weights, warn=False)
    retargeter.set_target(target)
    clouds = [sources[0], sources[1], sources[2][:10], sources[3][:0], sources[4]]
    joints, vertices, seen_joints, seen, _, _ = single_view.run_stream(retargeter, clouds)
    np.testing.assert_array_equal(seen, [True, True, False, False, True])
    np.testing.assert_array_equal(joints[2], joints[1])
    np.testing.assert_array_equal(vertices[3], vertices[1])
    np.testing.assert_array_equal(seen_joints[3], seen_joints[1])
    # the held frames were skipped, not fed: the last frame is the stream's third step
    retargeter.reset()
    for cloud in (sources[0], sources[1], sources[4]):
        last = retargeter.step(cloud)
    np.testing.assert_allclose(joints[4], last.joints, atol=1e-6)
    with pytest.raises(ValueError, match="frame 0"):
        single_view.run_stream(retargeter, [sources[0][:5]] + clouds)
    # told a camera inside the body (step refuses it): held too
    told = Retargeter(tiny_weights, "fitted", warn=False)
    told.set_target(target)
    cameras = np.stack([cloud.mean(axis=0) + (0.0, 0.0, 2.5) for cloud in sources[:3]])
    cameras[1] = sources[1].mean(axis=0) + (0.0, 0.0, 0.1)
    joints, _, _, seen, _, _ = single_view.run_stream(told, sources[:3], cameras)
    np.testing.assert_array_equal(seen, [True, False, True])
    np.testing.assert_array_equal(joints[1], joints[0])
