"""The numpy z-buffer against analytic depth: a tilted plane (clipped at the near plane),
a box (nearest face wins), occlusion by a nearer triangle, range culling, poses."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.dense.zbuffer import MeshRasteriser, rasterise_depth, scaled_intrinsics

K = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
W, H = 160, 120


def pixel_rays() -> tuple[np.ndarray, np.ndarray]:
    """Normalised x, y (H, W) of every pixel centre."""
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def quad(corners: list[list[float]]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(corners, float), np.array([[0, 1, 2], [0, 2, 3]])


def test_tilted_plane_crossing_the_near_plane() -> None:
    # z = 2 + 0.5 x; its left edge (x = -5) lies behind the camera (z = -0.5), so one
    # triangle has one vertex behind and the other two: both clipping cases.
    vertices, faces = quad([[-5, -5, -0.5], [5, -5, 4.5], [5, 5, 4.5], [-5, 5, -0.5]])
    depth = rasterise_depth(vertices, faces, K, W, H)
    x, _ = pixel_rays()
    expected = 2.0 / (1.0 - 0.5 * x)  # the ray (x, y, 1) z meets the plane at this z
    assert depth.dtype == np.float32 and depth.shape == (H, W)
    np.testing.assert_allclose(depth, expected, rtol=1e-6)


def box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])  # fmt: skip
    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    return corners, faces


def test_box_shows_its_front_face_only() -> None:
    vertices, faces = box(np.array([-0.5, -0.25, 3.0]), np.array([0.5, 0.25, 4.0]))
    depth = rasterise_depth(vertices, faces, K, W, H)
    x, y = pixel_rays()
    # The front face z = 3 spans |x| <= 0.5/3, |y| <= 0.25/3; nothing else is nearer.
    inside = (np.abs(x) < 0.5 / 3 - 1e-9) & (np.abs(y) < 0.25 / 3 - 1e-9)
    outside = (np.abs(x) > 0.5 / 3 + 1e-9) | (np.abs(y) > 0.25 / 3 + 1e-9)
    assert inside.sum() > 100
    np.testing.assert_allclose(depth[inside], 3.0, rtol=1e-6)
    assert np.all(np.isinf(depth[outside]))


def test_nearer_triangle_occludes_in_any_order() -> None:
    wall_v, wall_f = quad([[-10, -10, 4], [10, -10, 4], [10, 10, 4], [-10, 10, 4]])
    near_v = np.array([[-0.2, -0.2, 1.0], [0.3, -0.2, 1.0], [-0.2, 0.3, 1.0]])
    vertices = np.concatenate([wall_v, near_v])
    x, y = pixel_rays()
    covered = (x > -0.2 + 1e-9) & (y > -0.2 + 1e-9) & (x + y < 0.1 - 1e-9)
    around = (x < -0.2 - 1e-9) | (y < -0.2 - 1e-9) | (x + y > 0.1 + 1e-9)
    for faces in (np.concatenate([wall_f, [[4, 5, 6]]]), np.concatenate([[[4, 6, 5]], wall_f])):
        depth = rasterise_depth(vertices, faces, K, W, H)
        np.testing.assert_allclose(depth[covered], 1.0, rtol=1e-6)
        np.testing.assert_allclose(depth[around], 4.0, rtol=1e-6)
        assert covered.sum() > 50 and around.sum() > 1000


def test_behind_and_beyond_range() -> None:
    vertices, faces = quad([[-1, -1, -2], [1, -1, -2], [1, 1, -2], [-1, 1, -2]])
    assert np.all(np.isinf(rasterise_depth(vertices, faces, K, W, H)))
    far_v, far_f = quad([[-1, -1, 12], [1, -1, 12], [1, 1, 12], [-1, 1, 12]])
    # Its bounding spheres (radius 1.5 m) lie wholly beyond 8 m: skipped.
    assert np.all(np.isinf(rasterise_depth(far_v, far_f, K, W, H, max_range_m=8.0)))
    assert np.isfinite(rasterise_depth(far_v, far_f, K, W, H)).any()
    # A large floor whose corners are all far away but which passes 2 m below the camera
    # is kept by the range cull (a bounding sphere, not the corners, decides).
    floor_v, floor_f = quad([[-20, 2, -20], [20, 2, -20], [20, 2, 20], [-20, 2, 20]])
    depth = rasterise_depth(floor_v, floor_f, K, W, H, max_range_m=8.0)
    _, y = pixel_rays()
    below = y > 0.3
    np.testing.assert_allclose(depth[below], 2.0 / y[below], rtol=1e-6)


def test_posed_camera_matches_camera_frame_vertices() -> None:
    rng = np.random.default_rng(5)
    vertices = rng.uniform(-1, 1, (30, 3)) + np.array([0, 0, 3.0])
    faces = rng.integers(0, 30, (20, 3))
    angle = 0.3
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3], cam_from_world[:3, 3] = R, [0.2, -0.1, 0.5]
    world = (vertices - cam_from_world[:3, 3]) @ R  # so that cam_from_world maps it back
    got = MeshRasteriser(world, faces).depth_map(cam_from_world, K, W, H)
    np.testing.assert_allclose(got, rasterise_depth(vertices, faces, K, W, H), rtol=1e-6)
    assert np.isfinite(got).sum() > 100


def test_scaled_intrinsics_keeps_pixel_centres() -> None:
    Kq = scaled_intrinsics(K, 0.25)
    point = np.array([0.3, -0.2, 2.0])
    full, quarter = K @ point / point[2], Kq @ point / point[2]
    # Full-resolution pixel edges -0.5 and W - 0.5 land on the quarter image's edges.
    np.testing.assert_allclose(quarter[:2], (full[:2] + 0.5) * 0.25 - 0.5)
    assert Kq[0, 0] == pytest.approx(25.0) and Kq[2, 2] == 1.0
