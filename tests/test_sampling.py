"""Area-uniform surface sampling: distribution (chi-square), geometry, determinism, order."""
import numpy as np
import pytest
from scipy import stats

from minretarget.sampling import (points_from_barycentric, sample_point_clouds, sample_surface,
                                  triangle_areas)

# Five separate triangles in the z = 0 plane, areas 0.5 * s^2 for s = 0.2 .. 1.4.
_SIZES = np.array([0.2, 0.5, 0.8, 1.1, 1.4])
VERTICES = np.concatenate([[[3 * i, 0, 0], [3 * i + s, 0, 0], [3 * i, s, 0]]
                           for i, s in enumerate(_SIZES)]).astype(np.float32)
FACES = np.arange(15).reshape(5, 3)


def _face_of(points):
    """Index of the triangle a point of the test mesh lies in (they sit 3 m apart in x)."""
    return np.floor(points[..., 0] / 3).astype(int)


def test_triangle_areas():
    np.testing.assert_allclose(triangle_areas(VERTICES, FACES), 0.5 * _SIZES ** 2, rtol=1e-6)
    batch = np.stack([VERTICES, 2 * VERTICES])
    np.testing.assert_allclose(triangle_areas(batch, FACES)[1], 2.0 * _SIZES ** 2, rtol=1e-6)


def test_faces_drawn_in_proportion_to_area():
    rng = np.random.default_rng(0)
    face, _ = sample_surface(VERTICES, FACES, 20_000, rng)
    counts = np.bincount(face, minlength=5)
    expected = 20_000 * _SIZES ** 2 / (_SIZES ** 2).sum()
    assert stats.chisquare(counts, expected).pvalue > 0.01


def test_every_frame_drawn_by_its_own_areas():
    # Frame 1 shrinks the largest triangle to nothing: it must never be drawn there.
    frames = np.stack([VERTICES, VERTICES.copy()])
    frames[1, 14] = frames[1, 12]
    clouds = sample_point_clouds(frames, FACES, 20_000, np.random.default_rng(1))
    for t, sizes in enumerate((_SIZES, _SIZES * [1, 1, 1, 1, 0])):
        counts = np.bincount(_face_of(clouds[t]), minlength=5)
        assert counts[sizes == 0].sum() == 0
        live = sizes > 0
        expected = 20_000 * sizes[live] ** 2 / (sizes[live] ** 2).sum()
        assert stats.chisquare(counts[live], expected).pvalue > 0.01


def test_uniform_inside_a_triangle():
    # The four midpoint sub-triangles of a triangle have equal areas: equal counts.
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    points = sample_point_clouds(corners, [[0, 1, 2]], 20_000, np.random.default_rng(2))
    x, y = points[:, 0], points[:, 1]
    quarter = np.where(x > 0.5, 0, np.where(y > 0.5, 1, np.where(x + y < 0.5, 2, 3)))
    assert stats.chisquare(np.bincount(quarter, minlength=4)).pvalue > 0.01


def test_barycentric_points_lie_on_their_triangles():
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(40, 3)).astype(np.float32)
    faces = rng.integers(0, 40, size=(60, 3))
    face, barycentric = sample_surface(vertices, faces, 500, rng)
    assert face.shape == (500,) and barycentric.shape == (500, 3)
    assert barycentric.min() >= 0 and np.allclose(barycentric.sum(axis=1), 1, atol=1e-6)
    points = points_from_barycentric(vertices, faces, face, barycentric)
    corners = vertices[faces[face]]                                  # (Q, 3, 3)
    np.testing.assert_allclose(points, np.einsum("qca,qc->qa", corners, barycentric), atol=1e-6)
    # On the triangle's plane.
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("qa,qa->q", points - corners[:, 0], normal), 0, atol=1e-5)
    # The same (face, barycentric) follow the mesh when it moves: here a rigid translation.
    moved = points_from_barycentric(np.stack([vertices, vertices + 1]), faces, face, barycentric)
    np.testing.assert_allclose(moved[1] - moved[0], 1.0, atol=1e-5)


def test_determinism_by_seed():
    a = sample_point_clouds(VERTICES, FACES, 256, np.random.default_rng(7))
    b = sample_point_clouds(VERTICES, FACES, 256, np.random.default_rng(7))
    c = sample_point_clouds(VERTICES, FACES, 256, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    fa = sample_surface(VERTICES, FACES, 64, np.random.default_rng(7))
    fb = sample_surface(VERTICES, FACES, 64, np.random.default_rng(7))
    for x, y in zip(fa, fb):
        np.testing.assert_array_equal(x, y)


def test_fresh_sample_and_order_every_frame():
    frames = np.stack([VERTICES] * 3)
    clouds = sample_point_clouds(frames, FACES, 2000, np.random.default_rng(4))
    assert clouds.shape == (3, 2000, 3) and clouds.dtype == np.float32
    assert not np.array_equal(clouds[0], clouds[1]) and not np.array_equal(clouds[1], clouds[2])
    for cloud in clouds:
        # Random order: the triangle sequence is not sorted, and about as many runs of
        # "largest triangle or not" as an i.i.d. sequence (Wald-Wolfowitz runs test).
        face = _face_of(cloud)
        assert (np.diff(face) < 0).any()
        big = face == 4
        n1, n2 = big.sum(), (~big).sum()
        runs = 1 + (big[1:] != big[:-1]).sum()
        mean = 1 + 2 * n1 * n2 / (n1 + n2)
        var = 2 * n1 * n2 * (2 * n1 * n2 - n1 - n2) / ((n1 + n2) ** 2 * (n1 + n2 - 1))
        assert abs(runs - mean) / np.sqrt(var) < 4


def test_single_and_batched_shapes():
    rng = np.random.default_rng(5)
    assert sample_point_clouds(VERTICES, FACES, 10, rng).shape == (10, 3)
    batch = np.stack([[VERTICES] * 3] * 2)                          # (2, 3, V, 3)
    assert sample_point_clouds(batch, FACES, 10, rng).shape == (2, 3, 10, 3)


def test_bad_faces_raise():
    with pytest.raises(ValueError, match="faces"):
        sample_point_clouds(VERTICES, [[0, 1, 99]], 10, np.random.default_rng(0))
    with pytest.raises(ValueError, match="faces"):
        sample_point_clouds(VERTICES, np.zeros((3, 4), int), 10, np.random.default_rng(0))
