"""Intrinsics on rendered AprilGrid views (known camera); the real photos are in tests/real."""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import pytest

from postproc.calibrate.frame_selection import FrameSelectionOptions, select_frames
from postproc.calibrate.intrinsics import (
    IntrinsicsOptions,
    calibrate_intrinsics,
    reprojection_errors_px,
)
from postproc.calibrate.stage import detect_grid
from shared.calibration.aprilgrid_detection import DetectionOptions
from shared.errors import StageError
from sim.calibration import TARGET, board_views, equidistant_camera


def _relative_errors(estimate, truth):
    return {
        name: abs(getattr(estimate, name) - getattr(truth, name)) / getattr(truth, name)
        for name in ("fx", "fy", "cx", "cy")
    }


def test_radtan_intrinsics_within_half_a_percent(radtan_views, radtan_grid_views):
    camera, _, _ = radtan_views
    size = (camera.width, camera.height)
    assert len(radtan_grid_views) >= 15
    chosen = select_frames(radtan_grid_views, size, FrameSelectionOptions())
    result = calibrate_intrinsics([radtan_grid_views[i] for i in chosen], size)
    for name, error in _relative_errors(result.camera, camera).items():
        assert error < 0.005, f"{name} off by {100 * error:.3f} %"
    np.testing.assert_allclose(
        result.camera.opencv_distortion[:2], camera.opencv_distortion[:2], atol=0.01
    )
    assert result.rms_px < 0.3
    assert np.all(result.std_intrinsics < 0.5)


def test_residuals_are_those_of_the_shared_camera_model(radtan_views, radtan_grid_views):
    camera, _, _ = radtan_views
    size = (camera.width, camera.height)
    result = calibrate_intrinsics(radtan_grid_views[:8], size)
    # Reprojecting with the returned poses and the shared model gives the reported RMS.
    errors = np.concatenate(
        [
            reprojection_errors_px(result.camera, pose, radtan_grid_views[i])
            for pose, i in zip(result.cam_from_target, result.views_used, strict=True)
        ]
    )
    assert np.sqrt(np.mean(errors**2)) == pytest.approx(result.rms_px, rel=1e-9)


def test_a_bad_view_is_dropped(radtan_views, radtan_grid_views):
    camera, _, _ = radtan_views
    size = (camera.width, camera.height)
    views = list(radtan_grid_views[:10])
    bad = views[4]
    shuffled = bad.image_points_px.copy()
    shuffled[::3] += 6.0  # a third of the corners 8 px off
    views[4] = type(bad)(
        index=bad.index,
        stamp_ns=bad.stamp_ns,
        image_points_px=shuffled,
        object_points_m=bad.object_points_m,
        sharpness=bad.sharpness,
    )
    result = calibrate_intrinsics(views, size)
    assert result.views_dropped == [4]
    assert 4 not in result.views_used
    assert _relative_errors(result.camera, camera)["fx"] < 0.005


@pytest.mark.slow
def test_equidistant_intrinsics_within_half_a_percent():
    camera = equidistant_camera(640, 480)
    images, _ = board_views(camera, 14, seed=3, distance_m=(0.28, 0.5))
    views = [
        view
        for index, image in enumerate(images)
        if (
            view := detect_grid(
                image, TARGET, index=index, stamp_ns=index, detection=DetectionOptions(), min_tags=4
            )
        )
        is not None
    ]
    size = (camera.width, camera.height)
    result = calibrate_intrinsics(views, size, IntrinsicsOptions(model="pinhole-equidistant"))
    for name, error in _relative_errors(result.camera, camera).items():
        assert error < 0.005, f"{name} off by {100 * error:.3f} %"
    assert result.rms_px < 0.6


def test_option_errors(radtan_grid_views):
    size = (320, 240)
    with pytest.raises(StageError, match="unknown camera model 'pinhole-fov'"):
        # A model the Literal type refuses, on purpose: the stage must reject it.
        options = IntrinsicsOptions(model=cast(Any, "pinhole-fov"))
        calibrate_intrinsics(radtan_grid_views, size, options)
    with pytest.raises(StageError, match="2 view"):
        calibrate_intrinsics(radtan_grid_views[:2], size)
    with pytest.raises(StageError, match="fix_aspect_ratio is not available"):
        calibrate_intrinsics(
            radtan_grid_views,
            size,
            IntrinsicsOptions(model="pinhole-equidistant", fix_aspect_ratio=True),
        )


def test_degenerate_views_fail_cleanly(radtan_grid_views):
    # Every view identical: the focal length is not observable; OpenCV gives up or diverges.
    same = [radtan_grid_views[0]] * 4
    flat = type(same[0])(
        index=0,
        stamp_ns=0,
        image_points_px=np.zeros_like(same[0].image_points_px),
        object_points_m=same[0].object_points_m,
        sharpness=1.0,
    )
    with pytest.raises(StageError, match="intrinsics"):
        calibrate_intrinsics([flat] * 4, (320, 240))
