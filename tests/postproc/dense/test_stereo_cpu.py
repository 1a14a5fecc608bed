"""CPU stereo on rendered views of the simulated wreck, against the renderer's true depth."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from postproc.dense.stereo_cpu import (
    CpuStereoOptions,
    StereoView,
    consistent_depth,
    consistent_depth_support,
    depth_map,
    depth_support_map,
    nan_median_first_axis,
    normals_from_depth,
    pair_depth,
    rectifying_rotations,
)
from shared.calibration.cameras import PinholeRadtan
from sim.render import Renderer, WaterModel
from sim.scene import WreckScene

from .conftest import hull_poses

PINHOLE = PinholeRadtan(
    width=256, height=192, fx=150.0, fy=150.0, cx=127.5, cy=95.5, k1=0.0, k2=0.0, p1=0.0, p2=0.0
)


@pytest.fixture(scope="module")
def rendered(coarse_scene: WreckScene) -> tuple[list[StereoView], list[np.ndarray]]:
    """Five undistorted views 0.3 m apart along the hull (underwater image model, noise)."""
    renderer = Renderer(coarse_scene, PINHOLE, WaterModel())
    views, depths = [], []
    for k, pose in enumerate(hull_poses(5)):
        frame = renderer.render(pose, rng=np.random.default_rng(10 + k))
        views.append(
            StereoView(
                image=frame.image_rgb,
                K=PINHOLE.intrinsic_matrix,
                cam_from_world=np.linalg.inv(pose),
            )
        )
        depths.append(frame.depth_m)
    return views, depths


def test_rectification_puts_the_baseline_on_x() -> None:
    ref = np.eye(4)
    src = np.eye(4)
    src[:3, 3] = (-0.3, -0.4, 0.0)  # source centre at (0.3, 0.4, 0) in the reference frame
    rect_ref, rect_src, baseline = rectifying_rotations(ref, src)
    assert baseline == pytest.approx(0.5)
    np.testing.assert_allclose(
        rect_ref @ np.array([0.3, 0.4, 0.0]) / 0.5, [1.0, 0.0, 0.0], atol=1e-12
    )
    np.testing.assert_allclose(rect_ref @ rect_ref.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rect_src, rect_ref, atol=1e-12)  # same orientation
    with pytest.raises(ValueError, match="no baseline"):
        rectifying_rotations(ref, ref)
    forward = np.eye(4)
    forward[2, 3] = -1.0
    with pytest.raises(ValueError, match="optical axes"):
        rectifying_rotations(ref, forward)


def test_pair_depth_matches_the_renderer(
    rendered: tuple[list[StereoView], list[np.ndarray]],
) -> None:
    views, depths = rendered
    # Reference 1, source 3: 0.6 m baseline at about 2.6 m (13 degrees).
    depth = pair_depth(views[1], views[3], (1.5, 5.0))
    valid = depth > 0
    err = np.abs(depth[valid] - depths[1][valid])
    # Measured: 87 % of pixels, median error 1.1 cm, 90th percentile 2.6 cm at 150 px focal.
    assert valid.mean() > 0.75
    assert np.median(err) < 0.02
    assert np.percentile(err, 90) < 0.05


def test_vertical_baseline_works_too(coarse_scene: WreckScene) -> None:
    renderer = Renderer(coarse_scene, PINHOLE, WaterModel.clear())
    poses = [hull_poses(1)[0].copy() for _ in range(2)]
    poses[1][2, 3] += 0.5  # the second camera 0.5 m higher
    frames = [renderer.render(p) for p in poses]
    views = [
        StereoView(image=f.image_rgb, K=PINHOLE.intrinsic_matrix, cam_from_world=np.linalg.inv(p))
        for f, p in zip(frames, poses, strict=True)
    ]
    depth = pair_depth(views[0], views[1], (1.5, 5.0))
    valid = depth > 0
    assert valid.mean() > 0.4
    assert np.median(np.abs(depth[valid] - frames[0].depth_m[valid])) < 0.02


def test_multi_view_depth_and_normals(rendered: tuple[list[StereoView], list[np.ndarray]]) -> None:
    views, depths = rendered
    depth, normals = depth_map(views[2], [views[0], views[4], views[1], views[3]], (1.5, 5.0))
    valid = depth > 0
    err = np.abs(depth[valid] - depths[2][valid])
    # Measured: 94 % of pixels kept, 99.6 % of them within 5 cm, median error 1.1 cm;
    # the median normal is 10 degrees off (finite differences of a noisy depth).
    assert valid.mean() > 0.85
    assert np.mean(err < 0.05) > 0.98
    assert np.median(err) < 0.015
    # The hull side (world normal +y) in the camera frame, facing the camera.
    pose = np.linalg.inv(views[2].cam_from_world)
    expected = pose[:3, :3].T @ np.array([0.0, 1.0, 0.0])
    cosines = normals[valid] @ expected
    assert np.median(cosines) > 0.95
    assert np.all(np.linalg.norm(normals[valid], axis=1) > 0.99)
    assert np.all(normals[~valid] == 0)


def test_no_sources_gives_an_empty_map(rendered: tuple[list[StereoView], list[np.ndarray]]) -> None:
    views, _ = rendered
    depth, normals = depth_map(views[0], [], (1.5, 5.0))
    assert not depth.any() and not normals.any()


def test_consistency_vote() -> None:
    a = np.full((2, 2), 2.0, np.float32)
    b = a.copy()
    b[0, 0] = 2.5  # disagrees
    c = np.zeros_like(a)  # no depth
    out = consistent_depth([a, b, c], CpuStereoOptions(min_consistent=2, consistency_rel=0.01))
    assert out[0, 0] == 0.0 and out[1, 1] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="no depth maps"):
        consistent_depth([])


def test_one_pair_suffices_by_default_unless_pairs_disagree() -> None:
    # A far pixel only one pair matched keeps its depth (fusion re-checks it across
    # images); two pairs far apart from each other agree with neither's median.
    a = np.array([[2.0, 2.0, 0.0]], np.float32)
    b = np.array([[0.0, 3.0, 0.0]], np.float32)
    out = consistent_depth([a, b])
    assert out[0, 0] == pytest.approx(2.0) and out[0, 1] == 0.0 and out[0, 2] == 0.0
    strict = consistent_depth([a, b], CpuStereoOptions(min_consistent=2))
    assert not strict.any()


def test_support_counts_the_pairs_that_agree_to_the_tolerance() -> None:
    # Pixel 0: three pairs within 1 cm of 2 m; pixel 1: three pairs within 2 % of 6 m but
    # 6 cm apart; pixel 2: one pair; pixel 3: no depth.
    a = np.array([[2.00, 6.00, 3.0, 0.0]], np.float32)
    b = np.array([[2.01, 6.06, 0.0, 0.0]], np.float32)
    c = np.array([[1.99, 5.94, 0.0, 0.0]], np.float32)
    options = CpuStereoOptions(support_tolerance_m=0.02)
    depth, support = consistent_depth_support([a, b, c], options)
    np.testing.assert_allclose(depth, [[2.0, 6.0, 3.0, 0.0]], rtol=1e-5)
    np.testing.assert_array_equal(depth, consistent_depth([a, b, c], options))
    # At 6 m only the middle depth is within 2 cm of the mean kept.
    np.testing.assert_array_equal(support, [[3, 1, 1, 0]])
    _, loose = consistent_depth_support([a, b, c], CpuStereoOptions(support_tolerance_m=0.1))
    np.testing.assert_array_equal(loose, [[3, 3, 1, 0]])


def test_multi_view_support(rendered: tuple[list[StereoView], list[np.ndarray]]) -> None:
    views, depths = rendered
    depth, _, support = depth_support_map(
        views[2], [views[0], views[4], views[1], views[3]], (1.5, 5.0)
    )
    # Support only where a depth is kept (a depth whose pairs straddle it has none).
    assert not np.any((support > 0) & (depth == 0))
    assert support.max() <= 4
    err = np.abs(depth - depths[2])
    # Measured at 2.5 m: 99.6 % of the pixels three or more pairs support are within 5 cm;
    # 81-84 % of those two or more support within 2 cm against 64 % of the depths no pair
    # supports within the tolerance (their pairs straddle the mean).
    strong = support >= 3
    assert strong.mean() > 0.3
    assert np.mean(err[strong] < 0.05) > 0.99
    unsupported = (support == 0) & (depth > 0)
    assert np.mean(err[support >= 2] < 0.02) > np.mean(err[unsupported] < 0.02) + 0.1


def test_normals_of_a_tilted_plane() -> None:
    K = PINHOLE.intrinsic_matrix
    vv, uu = np.mgrid[0:192, 0:256].astype(float)
    # Plane n . p = d with n = (0, -0.6, -0.8) (facing the camera), d = -2.
    n = np.array([0.0, -0.6, -0.8])
    rays = np.stack(((uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)), axis=2)
    depth = (-2.0 / (rays @ n)).astype(np.float32)
    normals = normals_from_depth(depth, K, step_px=2)
    inner = normals[4:-4, 4:-4].reshape(-1, 3)
    np.testing.assert_allclose(inner, np.broadcast_to(n, inner.shape), atol=1e-3)
    assert np.all(normals[:2] == 0)


def test_nan_median_matches_numpy() -> None:
    rng = np.random.default_rng(5)
    for layers in (1, 2, 3, 6):
        stack = rng.uniform(1.0, 9.0, (layers, 40, 50)).astype(np.float32)
        stack[rng.random(stack.shape) < 0.4] = np.nan
        stack[:, 0, 0] = np.nan  # no finite value at all
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = np.nanmedian(stack, axis=0)
        got = nan_median_first_axis(stack)
        assert got.dtype == np.float32 and np.isnan(got[0, 0])
        np.testing.assert_allclose(got, expected, rtol=1e-6, equal_nan=True)
