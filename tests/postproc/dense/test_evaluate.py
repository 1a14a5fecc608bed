"""Evaluation: exact point-to-triangle distances, visibility, accuracy and completeness."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.dense.evaluate import (
    distance_to_mesh,
    distance_to_surface,
    evaluate,
    point_triangle_distance,
    sample_surface,
    visibility,
    visibility_counts,
)


def brute_force_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Minimum over a fine barycentric grid of the triangle (slow, obviously right)."""
    s, t = np.meshgrid(np.linspace(0, 1, 401), np.linspace(0, 1, 401))
    keep = s + t <= 1
    q = a + np.outer(s[keep], b - a) + np.outer(t[keep], c - a)
    return float(np.linalg.norm(q - p, axis=1).min())


def test_point_triangle_distance_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(3, 3))
    points = rng.normal(scale=1.5, size=(40, 3))
    n = len(points)
    got = point_triangle_distance(points, np.tile(tri[0], (n, 1)), np.tile(tri[1], (n, 1)),
                                  np.tile(tri[2], (n, 1)))  # fmt: skip
    expected = [brute_force_distance(p, *tri) for p in points]
    np.testing.assert_allclose(got, expected, atol=0.01)


def square_mesh(size: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.array([[0, 0, 0], [size, 0, 0], [size, size, 0], [0, size, 0]], float)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]])


def test_distance_to_mesh_and_far_triangles() -> None:
    vertices, triangles = square_mesh()
    far = np.array([[100, 100, 100], [101, 100, 100], [100, 101, 100]], float)
    vertices = np.concatenate([vertices, far])
    triangles = np.concatenate([triangles, [[4, 5, 6]]])
    points = np.array([[1.0, 1.0, 0.03], [0.5, 1.5, -0.2], [3.0, 1.0, 0.0]])
    d = distance_to_mesh(points, vertices, triangles)
    np.testing.assert_allclose(d, [0.03, 0.2, 1.0], atol=1e-9)
    assert distance_to_mesh(np.zeros((0, 3)), vertices, triangles).shape == (0,)
    assert np.isinf(distance_to_mesh(np.array([[50.0, 50, 50]]), *square_mesh()))[0]


def test_distance_to_surface_of_a_fine_mesh() -> None:
    """A wavy 1 m sheet of 2 cm triangles: the distance from points near it is that over
    every triangle (checked against all of them), and the large square gives its plane."""
    x, y = np.meshgrid(np.linspace(0, 1, 51), np.linspace(0, 1, 51))
    z = 0.05 * np.sin(6 * x) * np.cos(4 * y)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    i = np.arange(50)[:, None] * 51 + np.arange(50)[None]
    quads = i.ravel()
    triangles = np.concatenate([
        np.column_stack([quads, quads + 1, quads + 52]),
        np.column_stack([quads, quads + 52, quads + 51]),
    ])  # fmt: skip
    rng = np.random.default_rng(3)
    points = np.column_stack(
        [rng.uniform(0, 1, 300), rng.uniform(0, 1, 300), rng.normal(0, 0.04, 300)]
    )
    got = distance_to_surface(points, vertices, triangles)
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    every = [point_triangle_distance(np.tile(p, (len(a), 1)), a, b, c).min() for p in points]
    np.testing.assert_allclose(got, every, atol=1e-12)
    d = distance_to_surface(np.array([[1.0, 1.0, 0.03], [0.5, 1.5, -0.2]]), *square_mesh())
    np.testing.assert_allclose(d, [0.03, 0.2], atol=1e-12)
    assert distance_to_surface(np.zeros((0, 3)), vertices, triangles).shape == (0,)


def test_sampling_density() -> None:
    points, tri = sample_surface(*square_mesh(), 0.05)
    assert len(points) == pytest.approx(2 * 800, rel=0.01)  # 4 m^2 / 0.0025
    assert np.all(points[:, 2] == 0) and set(tri.tolist()) == {0, 1}
    assert points[:, :2].min() >= 0 and points[:, :2].max() <= 2


def test_visibility_with_an_occluder() -> None:
    K = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    pose = np.eye(4)  # camera at the origin looking along +z
    depth = np.full((100, 100), 2.0, np.float32)
    depth[:, :50] = 1.0  # an occluder in front of the left half
    points = np.array([[0.5, 0.0, 2.0], [-0.5, 0.0, 2.0], [0.0, 0.0, -2.0], [5.0, 0.0, 2.0]])
    counts = visibility_counts(points, [K, K], [pose, pose], [depth, depth])
    np.testing.assert_array_equal(counts, [2, 0, 0, 0])
    near = visibility_counts(points, [K], [pose], [depth], max_range_m=2.0)
    np.testing.assert_array_equal(near, [0, 0, 0, 0])  # the visible point is 2.06 m away


def test_accuracy_and_completeness() -> None:
    rng = np.random.default_rng(1)
    vertices, triangles = square_mesh()
    truth, _ = sample_surface(vertices, triangles, 0.01)
    # Reconstruct the left half only, 80 % of points within 1 cm, 20 % 8 cm off.
    recon = rng.uniform(0, 1, (20000, 3)) * [1.0, 2.0, 0.0]
    recon[:, 2] = np.where(rng.random(20000) < 0.8, rng.uniform(-0.01, 0.01, 20000), 0.08)
    scores = evaluate(recon, vertices, triangles, truth, thresholds_m=(0.02, 0.1))
    assert scores[0].accuracy == pytest.approx(0.8, abs=0.02)
    assert scores[1].accuracy == 1.0
    assert scores[0].completeness == pytest.approx(0.5, abs=0.03)
    # At 10 cm a strip 10 cm wide beyond the reconstructed half counts as complete too.
    assert scores[1].completeness == pytest.approx(0.55, abs=0.03)
    assert scores[1].f1 == pytest.approx(2 * 0.55 / 1.55, abs=0.02)
    empty = evaluate(np.zeros((0, 3)), vertices, triangles, truth)
    assert all(s.accuracy == 0 and s.completeness == 0 and s.f1 == 0 for s in empty)


def test_visibility_ranges_of_the_nearest_cameras() -> None:
    K = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    depth = np.full((100, 100), np.inf, np.float32)
    point = np.array([[0.0, 0.0, 4.0]])
    poses, depths = [], []
    for z in (0.0, 1.0, 2.0, 3.0):  # cameras on the optical axis, 4, 3, 2 and 1 m away
        pose = np.eye(4)
        pose[2, 3] = -z
        poses.append(pose)
        d = depth.copy()
        d[50, 50] = 4.0 - z
        depths.append(d)
    occluded = depths[1].copy()
    occluded[50, 50] = 1.0  # something 1 m in front of the camera 3 m away hides the point
    counts, ranges = visibility(point, [K] * 4, poses, [depths[0], occluded, *depths[2:]])
    assert counts.tolist() == [3]
    np.testing.assert_allclose(ranges[0], [1.0, 2.0, 4.0])
    counts, ranges = visibility(point, [K] * 2, poses[:2], depths[:2], nearest=3)
    assert counts.tolist() == [2] and ranges[0, 2] == np.inf
    np.testing.assert_allclose(ranges[0, :2], [3.0, 4.0])


def looking_down(x: float, y: float, height_m: float) -> np.ndarray:
    """cam_from_world of a camera at (x, y, height_m) looking straight down (-z)."""
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = np.column_stack([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    world_from_cam[:3, 3] = [x, y, height_m]
    return np.linalg.inv(world_from_cam)


def two_storeys() -> tuple[np.ndarray, np.ndarray]:
    """Two 2 m squares, one above the other (z = 0 and z = -1): from above, the lower one
    is hidden by the upper one wherever the camera stands over them."""
    top, faces = square_mesh()
    bottom = top + np.array([0, 0, -1.0])
    return np.concatenate([top, bottom]) - [1.0, 1.0, 0.0], np.concatenate([faces, faces + 4])


def test_seen_counts_hide_the_lower_storey() -> None:
    from postproc.dense.evaluate import seen_counts

    vertices, faces = two_storeys()
    K = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])
    cams = [looking_down(x, y, 3.0) for x in (-0.3, 0.3) for y in (-0.3, 0.3)]
    samples, tri = sample_surface(vertices, faces, 0.05, seed=2)
    upper = tri < 2
    counts = seen_counts(samples, vertices, faces, K, 80, 60, cams, max_range_m=10.0)
    assert np.all(counts[upper] == 4) and np.all(counts[~upper] == 0)
    # Out of range: nothing seen; a mask of the filmed pixels removes what lies outside it.
    assert not seen_counts(samples, vertices, faces, K, 80, 60, cams, max_range_m=2.9).any()
    filmed = np.ones((60, 80), bool)
    filmed[:, :40] = False  # the left half of every image was not filmed
    half = seen_counts(samples, vertices, faces, K, 80, 60, cams[:1], filmed=filmed)
    # Camera 0 stands at x = -0.3, u = 39.5 + 20 (x + 0.3): pixels u >= 40 hold x > -0.3.
    right = samples[:, 0] > -0.3 + 0.02
    left = samples[:, 0] < -0.3 - 0.02
    assert np.all(half[upper & right] == 1) and np.all(half[upper & left] == 0)
    assert np.all(half[~upper] == 0)
    assert len(seen_counts(np.zeros((0, 3)), vertices, faces, K, 80, 60, cams)) == 0


def test_undistorted_canvas() -> None:
    from postproc.dense.evaluate import undistorted_canvas
    from postproc.dense.zbuffer import scaled_intrinsics
    from shared.calibration.cameras import PinholeRadtan

    plain = PinholeRadtan(640, 360, 340.0, 340.0, 319.5, 179.5, 0.0, 0.0, 0.0, 0.0)
    K, w, h, filmed = undistorted_canvas(plain, 0.25)
    assert (w, h) == (160, 90) and filmed.all()
    np.testing.assert_allclose(K, scaled_intrinsics(plain.intrinsic_matrix, 0.25), atol=1e-6)
    barrel = PinholeRadtan(640, 360, 339.2, 339.2, 326.54, 176.62, -0.22, 0.05, 3e-4, -2e-4)
    K, w, h, filmed = undistorted_canvas(barrel, 0.25)
    # Barrel distortion: the real image sees more than its pinhole of the same focal
    # length, so the canvas is larger; the image's outline becomes a pincushion that
    # reaches the canvas corners, not the middles of its sides.
    assert w > 160 and h > 90
    corners = [filmed[:4, :4], filmed[:4, -4:], filmed[-4:, :4], filmed[-4:, -4:]]
    assert all(c.any() for c in corners) and filmed[h // 2, w // 2]
    assert not filmed[0, w // 2] and not filmed[-1, w // 2] and not filmed[h // 2, 0]
    # Every real pixel's ray lands on a filmed canvas pixel; rays just outside do not.
    rng = np.random.default_rng(1)
    pixels = rng.uniform([0, 0], [639, 359], (2000, 2))
    rays = barrel.unproject(pixels)
    uv = np.round((rays @ K.T)[:, :2]).astype(int)
    assert np.mean(filmed[uv[:, 1], uv[:, 0]]) > 0.99
    outside = barrel.unproject(np.array([[-8.0, 180.0], [648.0, 180.0], [320.0, -8.0]]))
    uv = np.round((outside @ K.T)[:, :2]).astype(int)
    assert not filmed[uv[:, 1], uv[:, 0]].any()


def test_one_sided_visibility() -> None:
    K = np.array([[10.0, 0, 1.5], [0, 10.0, 0.5], [0, 0, 1]])
    # Four pixels in a row: farther than the point, inf, NaN, nearer than the point.
    depth = np.array([[3.0, np.inf, np.nan, 1.0], [3.0, np.inf, np.nan, 1.0]], np.float32)
    points = np.array([[(u - 1.5) / 10 * 2.0, 0.0, 2.0] for u in range(4)])
    one, _ = visibility(points, [K], [np.eye(4)], [depth], nearest=0, one_sided=True)
    two, _ = visibility(points, [K], [np.eye(4)], [depth], nearest=0)
    np.testing.assert_array_equal(one, [1, 1, 0, 0])
    np.testing.assert_array_equal(two, [0, 0, 0, 0])
