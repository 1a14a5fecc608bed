"""AprilGrid detection: real photos of a Kalibr grid, synthetic distorted renders, id handling."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.merge.detect import (
    DetectionOptions,
    TagDetection,
    detect_tags,
    group_by_target,
    homography_residuals_px,
    line_fit_residuals_px,
    to_gray,
)
from postproc.merge.synthetic import PlacedTarget, default_camera, look_at, render_view
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.cameras import PinholeEquidistant
from shared.geometry import invert_pose

# The photos show a 6x6 Kalibr grid (ids 0..35) on a monitor; the size does not matter here.
PHOTO_GRID = AprilGridTarget(tag_rows=6, tag_cols=6, tag_size_m=0.088, tag_spacing_ratio=0.3)


@pytest.fixture(scope="module")
def photos(shared_data):
    import cv2

    images = {}
    for name in ("000.jpg", "001.jpg"):
        image = cv2.imread(str(shared_data / "aprilgrid" / name), cv2.IMREAD_GRAYSCALE)
        assert image is not None, name
        images[name] = image
    return images


@pytest.fixture(scope="module")
def photo_detections(photos):
    return {name: detect_tags(image) for name, image in photos.items()}


@pytest.mark.parametrize("name", ["000.jpg", "001.jpg"])
def test_real_photos_all_tags_and_subpixel_corners(photos, photo_detections, name):
    image = photos[name]
    refined = photo_detections[name]
    assert [d.tag_id for d in refined] == list(range(36))
    raw = detect_tags(image, DetectionOptions(subpix=False))
    lines_refined = line_fit_residuals_px(refined, PHOTO_GRID)
    lines_raw = line_fit_residuals_px(raw, PHOTO_GRID)
    assert len(lines_refined) == 24 * 12  # 24 lines of 12 corners
    # A 12 MP phone photo of a monitor: corners on grid lines to well under a pixel.
    assert np.median(lines_refined) < 0.5
    assert np.sqrt(np.mean(lines_refined**2)) < 0.75
    assert np.median(lines_refined) < 0.6 * np.median(lines_raw)
    homography = homography_residuals_px(refined, PHOTO_GRID)
    # Lens distortion and screen curvature make a smooth part of this residual.
    assert np.sqrt(np.mean(homography**2)) < 1.5
    assert np.sqrt(np.mean(homography**2)) < np.sqrt(
        np.mean(homography_residuals_px(raw, PHOTO_GRID) ** 2)
    )


def test_real_photo_corner_order_is_kalibrs(photo_detections):
    # In 000.jpg the grid is upright: corner 0 bottom-left, 1 bottom-right, 2 top-right.
    tag = next(d for d in photo_detections["000.jpg"] if d.tag_id == 0)
    c = tag.corners_px
    assert c[1, 0] > c[0, 0] and c[2, 0] > c[3, 0]  # x grows to the right
    assert c[3, 1] < c[0, 1] and c[2, 1] < c[1, 1]  # y (image) grows downwards
    tag7 = next(d for d in photo_detections["000.jpg"] if d.tag_id == 6)
    assert tag7.corners_px[0, 1] < c[3, 1]  # row 1 sits above row 0 on the page


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
