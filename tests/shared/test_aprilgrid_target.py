"""AprilGrid geometry in Kalibr's convention, tag patterns, and the rendered texture."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.calibration.aprilgrid import (
    OPENCV_CORNER_ORDER,
    AprilGridTarget,
    render_target_texture,
    tag36h11_bits,
    texture_margin_m,
    texture_pixel_from_target,
)

# First codes of the 36h11 family as Kalibr's createTargetPDF.py lists them.
KALIBR_36H11_CODES = {0: 0xD5D628584, 1: 0xD97F18B49, 2: 0xDD280910E, 5: 0xF31DAB3AC}


def _detector() -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.markerBorderBits = 2  # Kalibr tags: two black rings around the code
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return cv2.aruco.ArucoDetector(dictionary, params)


def test_corner_points_follow_kalibr_grid_points() -> None:
    target = AprilGridTarget(tag_rows=3, tag_cols=4, tag_size_m=0.05, tag_spacing_ratio=0.3)
    ids, points = target.all_corner_points()
    assert ids.tolist() == list(range(12))
    assert points.shape == (12, 4, 3)
    assert np.all(points[:, :, 2] == 0.0)
    # Kalibr's createGridPoints: grid point (r, c) of a (2 rows x 2 cols per tag) grid is
    # x = (c // 2) * (1 + spacing) * size + (c % 2) * size, likewise y; tag t uses points
    # base, base + 1, base + cols + 1, base + cols with base = (t // tagCols) * 2 * cols
    # + (t % tagCols) * 2 and cols = 2 * tagCols.
    cols, rows = 2 * target.tag_cols, 2 * target.tag_rows
    grid = np.zeros((rows * cols, 2))
    for r in range(rows):
        for c in range(cols):
            grid[r * cols + c] = [
                (c // 2) * 1.3 * 0.05 + (c % 2) * 0.05,
                (r // 2) * 1.3 * 0.05 + (r % 2) * 0.05,
            ]
    for tag in range(12):
        base = (tag // target.tag_cols) * cols * 2 + (tag % target.tag_cols) * 2
        expected = grid[[base, base + 1, base + cols + 1, base + cols]]
        np.testing.assert_allclose(points[tag, :, :2], expected, atol=1e-15)
    assert target.extent_m == pytest.approx((4 * 0.05 + 3 * 0.015, 3 * 0.05 + 2 * 0.015))


def test_id_offset_and_dict_view() -> None:
    target = AprilGridTarget(2, 2, 0.1, 0.25, tag_id_offset=40)
    assert target.tag_ids() == [40, 41, 42, 43]
    corners = target.corner_points()
    assert sorted(corners) == [40, 41, 42, 43]
    np.testing.assert_allclose(corners[43][0], [0.125, 0.125, 0.0])
    np.testing.assert_allclose(corners[41][2], [0.225, 0.1, 0.0])
    assert target.tag_origin_m(42) == pytest.approx((0.0, 0.125))
    with pytest.raises(ValueError, match="not on this grid"):
        target.tag_origin_m(44)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"tag_rows": 0}, "at least 1x1"),
        ({"tag_size_m": 0.0}, "tag_size_m"),
        ({"tag_spacing_ratio": -0.1}, "tag_spacing_ratio"),
        ({"tag_id_offset": 580}, "outside the 36h11 family"),
    ],
)
def test_invalid_targets_are_rejected(kwargs: dict[str, float], message: str) -> None:
    base: dict[str, float] = {
        "tag_rows": 2,
        "tag_cols": 4,
        "tag_size_m": 0.1,
        "tag_spacing_ratio": 0.3,
    }
    base.update(kwargs)
    with pytest.raises(ValueError, match=message):
        AprilGridTarget(**base)  # type: ignore[arg-type]


@pytest.mark.parametrize("tag_id", sorted(KALIBR_36H11_CODES))
def test_tag_bits_match_kalibr_print_rule(tag_id: int) -> None:
    bits = tag36h11_bits(tag_id)
    assert bits.shape == (10, 10)
    assert bits.dtype == bool
    # Two black rings around the code.
    ring = np.ones((10, 10), dtype=bool)
    ring[2:8, 2:8] = False
    assert not bits[ring].any()
    # Kalibr's PDF: cell (i, j) is white when bit 6*i + j (LSB first) of the code is set,
    # then the 6x6 matrix is rotated by 180 degrees; row 0 is drawn at the top.
    code = KALIBR_36H11_CODES[tag_id]
    kalibr = np.array([[(code >> (6 * i + j)) & 1 for j in range(6)] for i in range(6)], bool)
    printed = np.rot90(kalibr, 2)
    np.testing.assert_array_equal(np.rot90(bits[2:8, 2:8], 2), printed)
    with pytest.raises(ValueError, match="36h11"):
        tag36h11_bits(587)


def test_rendered_texture_detects_with_kalibr_ids_and_corners() -> None:
    target = AprilGridTarget(3, 4, 0.088, 0.3, tag_id_offset=7)
    pixels_per_m = 70 / 0.088 + 0.37  # ~7 px per cell, not aligned with the cells
    image = render_target_texture(target, pixels_per_m)
    assert image.dtype == np.uint8
    margin = texture_margin_m(target)
    width_m, height_m = target.extent_m
    assert image.shape == (
        int(np.ceil((height_m + 2 * margin) * pixels_per_m)),
        int(np.ceil((width_m + 2 * margin) * pixels_per_m)),
    )
    assert image[0, 0] == 255 and image.min() == 0

    corners, ids, _ = _detector().detectMarkers(image)
    assert ids is not None
    assert sorted(ids.ravel().tolist()) == target.tag_ids()
    detected = np.concatenate([c[0] for c in corners]).astype(np.float32)
    # Kalibr refines each tag corner with cornerSubPix (the corner squares make them
    # X-junctions); the reordered refined corners must sit on the expected positions.
    refined = cv2.cornerSubPix(
        image, detected.copy(), (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS | 1, 100, 1e-4)
    ).reshape(-1, 4, 2)
    expected_corners = target.corner_points()
    for tag_id, raw, fine in zip(ids.ravel(), detected.reshape(-1, 4, 2), refined, strict=True):
        expected = texture_pixel_from_target(
            target, pixels_per_m, expected_corners[int(tag_id)][:, :2]
        )
        reordered = fine[list(OPENCV_CORNER_ORDER)]
        np.testing.assert_allclose(reordered, expected, atol=0.5)
        # The raw aruco corners already identify the corners (each is nearest its own).
        distances = np.linalg.norm(raw[list(OPENCV_CORNER_ORDER)][:, None] - expected, axis=2)
        assert np.argmin(distances, axis=1).tolist() == [0, 1, 2, 3]


def test_texture_is_exact_area_coverage() -> None:
    # Compare with a brute-force 32x supersampled rendering of Kalibr's layout.
    target = AprilGridTarget(1, 2, 0.1, 0.25, tag_id_offset=3)
    ppm = 71.3
    image = render_target_texture(target, ppm).astype(np.float64)
    height, width = image.shape
    ss = 32
    u = (np.arange(width * ss) + 0.5) / ss - 0.5
    v = (np.arange(height * ss) + 0.5) / ss - 0.5
    margin = texture_margin_m(target)
    x = (u + 0.5) / ppm - margin
    y = target.extent_m[1] + margin - (v + 0.5) / ppm
    xx, yy = np.meshgrid(x, y)
    ink = np.zeros(xx.shape, dtype=bool)
    size, gap = 0.1, 0.025
    for tag_id, corners in target.corner_points().items():
        x0, y0 = corners[0, :2]
        printed_white = np.rot90(tag36h11_bits(tag_id), 2)
        inside = (xx >= x0) & (xx < x0 + size) & (yy >= y0) & (yy < y0 + size)
        col = np.clip(((xx - x0) / (size / 10)).astype(int), 0, 9)
        row = np.clip(((y0 + size - yy) / (size / 10)).astype(int), 0, 9)
        ink |= inside & ~printed_white[row, col]
    for k_row in range(2):
        for k_col in range(3):
            sx, sy = k_col * (size + gap) - gap, k_row * (size + gap) - gap
            ink |= (xx >= sx) & (xx < sx + gap) & (yy >= sy) & (yy < sy + gap)
    reference = 255.0 * (1.0 - ink.reshape(height, ss, width, ss).mean(axis=(1, 3)))
    # Supersampling error is at most ~255/32 per edge in a pixel.
    assert np.abs(reference - image).mean() < 1.5
    assert np.abs(reference - image).max() < 12.0


def test_render_rejects_bad_resolution() -> None:
    with pytest.raises(ValueError, match="pixels_per_m"):
        render_target_texture(AprilGridTarget(1, 1, 0.1, 0.3), 0.0)


def test_real_photo_confirms_corner_order(shared_data: Path) -> None:
    # A photo of a 6x6 Kalibr grid (88 mm tags, spacing 0.3) shown on a monitor: only the
    # Kalibr corner order makes all 144 corners fit one plane homography.
    image = cv2.imread(str(shared_data / "aprilgrid" / "000.jpg"), cv2.IMREAD_GRAYSCALE)
    assert image is not None
    image = cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    corners, ids, _ = _detector().detectMarkers(image)
    target = AprilGridTarget(6, 6, 0.088, 0.3)
    assert ids is not None and sorted(ids.ravel().tolist()) == target.tag_ids()
    expected = target.corner_points()
    object_points = np.concatenate([expected[int(i)][:, :2] for i in ids.ravel()])

    def residual_px(order: tuple[int, ...]) -> float:
        image_points = np.concatenate([c[0][list(order)] for c in corners])
        homography, _ = cv2.findHomography(object_points, image_points, 0)
        projected = cv2.perspectiveTransform(object_points[None], homography)[0]
        return float(np.abs(projected - image_points).max())

    assert residual_px(OPENCV_CORNER_ORDER) < 10.0
    for wrong in [(0, 1, 2, 3), (3, 2, 1, 0), (2, 3, 0, 1), (1, 2, 3, 0)]:
        assert residual_px(wrong) > 50.0
    # Tag 0 is bottom-left on the page, tag 5 bottom-right, tag 30 top-left.
    centres = {int(i): c[0].mean(axis=0) for i, c in zip(ids.ravel(), corners, strict=True)}
    assert centres[0][0] < centres[5][0] and centres[0][1] > centres[30][1]
