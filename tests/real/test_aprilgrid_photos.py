"""The real AprilGrid photos (../shared/data/aprilgrid) through the stages that read them:
tag detection (merge targets) and intrinsics (calibrate)."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from postproc.calibrate.intrinsics import IntrinsicsOptions, calibrate_intrinsics
from postproc.calibrate.stage import detect_grid
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.aprilgrid_detection import (
    DetectionOptions,
    detect_tags,
    homography_residuals_px,
    line_fit_residuals_px,
)
from shared.calibration.cameras import CameraModel, PinholeRadtan

# The photos show a 6x6 Kalibr grid (ids 0..35) on a monitor; the size does not matter here.
PHOTO_GRID = AprilGridTarget(tag_rows=6, tag_cols=6, tag_size_m=0.088, tag_spacing_ratio=0.3)


@pytest.fixture(scope="module")
def photos(shared_data):
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


def _radtan(camera: CameraModel) -> PinholeRadtan:
    assert isinstance(camera, PinholeRadtan)  # the default model
    return camera


@pytest.fixture(scope="module")
def photo_views(shared_data):
    views = []
    for index, name in enumerate(("000.jpg", "001.jpg")):
        image = cv2.imread(str(shared_data / "aprilgrid" / name), cv2.IMREAD_GRAYSCALE)
        assert image is not None
        # cv2 stubs type the image loosely; IMREAD_GRAYSCALE reads it as uint8.
        view = detect_grid(
            cast("npt.NDArray[np.uint8]", image),
            PHOTO_GRID,
            index=index,
            stamp_ns=index,
            detection=DetectionOptions(),
            min_tags=4,
        )
        assert view is not None
        views.append(view)
    assert image is not None
    return views, (image.shape[1], image.shape[0])


def test_two_real_photos_give_a_plausible_focal_length(photo_views):
    """Two views of a monitor (phone camera, 3072x4080 portrait): f only, pp fixed, no distortion.

    Measured: f = 2900 px (1-sigma 12 px), RMS 1.28 px; each photo alone gives 2992 and
    2854 px. A 4:3 phone main camera of about 25-27 mm equivalent focal length has
    f = 2850-3100 px at this resolution. The RMS above 1 px is what a flat-screen target
    and an unmodelled distortion leave.
    """
    views, size = photo_views
    assert all(v.corner_count == 144 for v in views)
    simple = IntrinsicsOptions(
        fix_principal_point=True, fix_aspect_ratio=True, zero_distortion=True, min_views=1
    )
    joint = calibrate_intrinsics(views, size, simple)
    camera = _radtan(joint.camera)
    assert 2600.0 < camera.fx < 3300.0
    assert camera.fx == camera.fy
    assert (camera.cx, camera.cy) == ((size[0] - 1) / 2, (size[1] - 1) / 2)
    assert joint.rms_px < 2.0
    singles = [_radtan(calibrate_intrinsics([v], size, simple).camera).fx for v in views]
    # Each photo alone agrees with the joint estimate to within 5 %.
    for single in singles:
        assert abs(single - camera.fx) / camera.fx < 0.05
