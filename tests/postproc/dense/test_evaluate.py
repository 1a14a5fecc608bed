"""Evaluation: exact point-to-triangle distances, visibility, accuracy and completeness."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.dense.evaluate import (
    distance_to_mesh,
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
