"""Whole-grid PnP through the camera model: accuracy, covariance, corner rejection, raises."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.merge.averaging import pose_residuals
from postproc.merge.target_pose import estimate_target_pose
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.cameras import CameraModel, PinholeEquidistant
from shared.geometry import invert_pose, look_at, pose_difference
from sim.targets import default_camera

GRID = AprilGridTarget(tag_rows=4, tag_cols=5, tag_size_m=0.088, tag_spacing_ratio=0.3)
CAMERAS: dict[str, CameraModel] = {
    "radtan": default_camera(),
    "equidistant": PinholeEquidistant(
        960, 540, 430.0, 430.0, 479.5, 269.5, 0.02, -0.01, 0.004, -0.001
    ),
}


def _view(rng):
    _, points = GRID.all_corner_points()
    centre = np.array([0.27, 0.2, 0.0])
    eye = centre + np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.8, 2.0)])
    cam_from_target = invert_pose(look_at(eye, centre, np.array([0, 1.0, 0])))
    return points.reshape(-1, 3), cam_from_target


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_pose_accuracy_and_covariance(name):
    camera = CAMERAS[name]
    rng = np.random.default_rng(21)
    sigma_px = 0.3
    residuals, covs = [], []
    for _ in range(40):
        obj, truth = _view(rng)
        pixels = camera.project(obj @ truth[:3, :3].T + truth[:3, 3])
        assert np.all(np.isfinite(pixels))
        estimate = estimate_target_pose(camera, obj, pixels + rng.normal(0, sigma_px, pixels.shape))
        assert estimate is not None
        rot, trans = pose_difference(estimate.cam_from_target, truth)
        assert np.rad2deg(rot) < 1.0 and trans < 0.01
        assert estimate.reprojection_rms_px == pytest.approx(sigma_px * np.sqrt(2), rel=0.25)
        residuals.append(pose_residuals(estimate.cam_from_target[None], truth)[0])
        covs.append(estimate.covariance)
    errors = np.array(residuals)
    ratio = np.mean(errors**2, axis=0) / np.mean([np.diag(c) for c in covs], axis=0)
    assert np.all((ratio > 0.4) & (ratio < 2.5)), ratio


def test_noise_free_corners_give_the_exact_pose():
    camera = CAMERAS["radtan"]
    obj, truth = _view(np.random.default_rng(3))
    pixels = camera.project(obj @ truth[:3, :3].T + truth[:3, 3])
    estimate = estimate_target_pose(camera, obj, pixels)
    assert estimate is not None
    rot, trans = pose_difference(estimate.cam_from_target, truth)
    assert rot < 1e-7 and trans < 1e-8
    assert estimate.corner_count == 80


def test_a_corner_on_the_wrong_feature_is_dropped():
    camera = CAMERAS["radtan"]
    rng = np.random.default_rng(4)
    obj, truth = _view(rng)
    pixels = camera.project(obj @ truth[:3, :3].T + truth[:3, 3]) + rng.normal(0, 0.1, (80, 2))
    pixels[5] += [3.5, -3.0]
    estimate = estimate_target_pose(camera, obj, pixels)
    assert estimate is not None
    assert estimate.corner_count == 79
    assert estimate.reprojection_max_px < 0.6
    kept_all = estimate_target_pose(camera, obj, pixels, min_outlier_px=np.inf)
    assert kept_all is not None
    assert kept_all.corner_count == 80
    assert (
        pose_difference(estimate.cam_from_target, truth)[1]
        < pose_difference(kept_all.cam_from_target, truth)[1]
    )


def test_unprojectable_points_give_none():
    camera = CAMERAS["radtan"]
    obj, _ = _view(np.random.default_rng(5))
    assert estimate_target_pose(camera, obj, np.full((80, 2), np.nan)) is None


def test_raise_paths():
    camera = CAMERAS["radtan"]
    obj, _ = _view(np.random.default_rng(6))
    with pytest.raises(ValueError, match="object points but"):
        estimate_target_pose(camera, obj, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="at least 4"):
        estimate_target_pose(camera, obj[:3], np.zeros((3, 2)))
    bent = obj.copy()
    bent[0, 2] = 0.01
    with pytest.raises(ValueError, match="planar"):
        estimate_target_pose(camera, bent, np.zeros((80, 2)))
