"""AprilGrid detection: real photos of a Kalibr grid, synthetic distorted renders, id handling."""

from __future__ import annotations

import numpy as np
import pytest

from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.aprilgrid_detection import (
    TagDetection,
    detect_tags,
    group_by_target,
    homography_residuals_px,
    line_fit_residuals_px,
    to_gray,
)
from shared.calibration.cameras import PinholeEquidistant
from shared.geometry import invert_pose, look_at
from sim.targets import PlacedTarget, default_camera, render_view


def _corner_errors(camera, grid, world_from_cam, image):
    cam_from_target = invert_pose(world_from_cam)
    ids, points = grid.all_corner_points()
    truth = {
        int(i): camera.project(p @ cam_from_target[:3, :3].T + cam_from_target[:3, 3])
        for i, p in zip(ids, points, strict=True)
    }
    detections = detect_tags(image)
    errors = [np.linalg.norm(d.corners_px - truth[d.tag_id], axis=1) for d in detections]
    return len(detections), np.concatenate(errors) if errors else np.zeros(0)


@pytest.mark.parametrize(
    "camera",
    [
        default_camera(),
        PinholeEquidistant(960, 540, 430.0, 430.0, 479.5, 269.5, 0.02, -0.01, 0.004, -0.001),
    ],
    ids=["radtan", "equidistant"],
)
def test_synthetic_distorted_renders_within_half_a_pixel(camera):
    rng = np.random.default_rng(11)
    grid = AprilGridTarget(tag_rows=4, tag_cols=5, tag_size_m=0.088, tag_spacing_ratio=0.3)
    centre = np.array([0.27, 0.2, 0.0])
    all_errors = []
    found = 0
    for _ in range(6):
        eye = centre + np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), 0.0])
        eye[2] = rng.uniform(0.7, 1.3)
        world_from_cam = look_at(eye, centre + rng.normal(0, 0.15, 3), np.array([0, 1.0, 0]))
        image = render_view(camera, world_from_cam, [PlacedTarget(grid, np.eye(4))], rng=rng)
        count, errors = _corner_errors(camera, grid, world_from_cam, image)
        found += count
        all_errors.append(errors)
    errors = np.concatenate(all_errors)
    assert found >= 0.6 * 6 * 20
    assert np.median(errors) < 0.15
    assert np.mean(errors < 0.5) > 0.98


def test_group_by_target_splits_grids_and_rejects_foreign_ids():
    a = AprilGridTarget(tag_rows=2, tag_cols=2, tag_size_m=0.1, tag_spacing_ratio=0.3)
    b = AprilGridTarget(
        tag_rows=1, tag_cols=3, tag_size_m=0.1, tag_spacing_ratio=0.3, tag_id_offset=10
    )
    corners = np.zeros((4, 2))
    detections = [TagDetection(i, corners + i) for i in (0, 3, 7, 10, 12, 99)]
    observations, foreign = group_by_target(detections, [a, b])
    assert foreign == [7, 99]
    assert [o.target_index for o in observations] == [0, 1]
    np.testing.assert_array_equal(observations[1].tag_ids, [10, 12])
    np.testing.assert_allclose(observations[1].object_points_m[1], b.corner_points()[12])
    assert observations[0].corner_count == 8
    only, _ = group_by_target(detections, [a, b], min_tags=3)
    assert only == []


def test_group_by_target_raises_on_overlapping_ids():
    a = AprilGridTarget(tag_rows=2, tag_cols=2, tag_size_m=0.1, tag_spacing_ratio=0.3)
    with pytest.raises(ValueError, match="tagIdOffset"):
        group_by_target([], [a, a])


def test_blank_image_and_colour_input():
    assert detect_tags(np.full((100, 120), 128, np.uint8)) == []
    assert to_gray(np.zeros((5, 6, 3), np.uint8)).shape == (5, 6)
    assert to_gray(np.zeros((5, 6, 4), np.uint8)).shape == (5, 6)
    with pytest.raises(ValueError, match="8-bit"):
        to_gray(np.zeros((5, 6), np.float32))
    with pytest.raises(ValueError, match="image"):
        to_gray(np.zeros((5, 6, 2), np.uint8))


def test_quality_helpers_need_enough_corners():
    grid = AprilGridTarget(tag_rows=2, tag_cols=2, tag_size_m=0.1, tag_spacing_ratio=0.3)
    one = [TagDetection(0, np.array([[0.0, 10], [10, 10], [10, 0], [0, 0]]))]
    assert homography_residuals_px(one, grid).size == 0
    assert line_fit_residuals_px(one, grid).size == 0
