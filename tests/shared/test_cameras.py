"""Camera models against OpenCV: projection, exact undistortion, scaling, registry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.calibration.cameras import (
    CAMERA_MODELS,
    CameraModel,
    PinholeEquidistant,
    PinholeRadtan,
)

# Realistic lenses: an EuRoC-like radtan camera and a GoPro/OAK-like fisheye.
RADTAN = PinholeRadtan(
    752, 480, 458.654, 457.296, 367.215, 248.375, -0.2834, 0.0740, 1.9e-4, 1.8e-5
)
FISHEYE = PinholeEquidistant(
    1920, 1080, 870.0, 868.5, 958.3, 541.7, 0.0312, -0.0121, 0.0043, -0.0009
)
# OpenCV flags a fisheye point as failed when eps is below what doubles can reach (1e-16).
TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-14)


def _random_points(rng: np.random.Generator, camera: CameraModel, count: int) -> np.ndarray:
    """Points in front of the camera whose projections fall inside the image."""
    pixels = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(count, 2))
    rays = camera.unproject(pixels)
    return rays * rng.uniform(0.3, 20.0, size=(count, 1))


def _pixel_grid(camera: CameraModel, step: int) -> np.ndarray:
    """Every `step`-th pixel plus the four extreme corner pixels."""
    us = np.unique(np.r_[np.arange(0, camera.width, step), camera.width - 1])
    vs = np.unique(np.r_[np.arange(0, camera.height, step), camera.height - 1])
    grid = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
    return grid.astype(np.float64)


def test_radtan_project_matches_opencv() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform([-2, -1.5, 0.5], [2, 1.5, 8], size=(2000, 3))
    expected, _ = cv2.projectPoints(
        points, np.zeros(3), np.zeros(3), RADTAN.intrinsic_matrix, RADTAN.opencv_distortion
    )
    np.testing.assert_allclose(RADTAN.project(points), expected[:, 0], atol=1e-9)


def test_fisheye_project_matches_opencv() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform([-3, -2, 0.2], [3, 2, 6], size=(2000, 3))
    expected, _ = cv2.fisheye.projectPoints(
        points[:, None, :],
        np.zeros(3),
        np.zeros(3),
        FISHEYE.intrinsic_matrix,
        FISHEYE.opencv_distortion,
    )
    np.testing.assert_allclose(FISHEYE.project(points), expected[:, 0], atol=1e-9)


@pytest.mark.parametrize("camera", [RADTAN, FISHEYE])
def test_points_behind_camera_project_to_nan(camera: CameraModel) -> None:
    points = np.array([[0.1, 0.2, -1.0], [0.0, 0.0, 0.0], [0.3, -0.1, 2.0]])
    pixels = camera.project(points)
    assert np.isnan(pixels[:2]).all()
    assert np.isfinite(pixels[2]).all()


def test_radtan_unproject_matches_opencv_over_whole_image() -> None:
    pixels = _pixel_grid(RADTAN, 8)
    expected = cv2.undistortPoints(
        pixels[:, None, :], RADTAN.intrinsic_matrix, RADTAN.opencv_distortion, criteria=TIGHT
    )[:, 0]
    rays = RADTAN.unproject(pixels)
    np.testing.assert_array_equal(rays[:, 2], 1.0)
    np.testing.assert_allclose(rays[:, :2], expected, atol=1e-9)


def test_fisheye_unproject_matches_opencv_over_whole_image() -> None:
    pixels = _pixel_grid(FISHEYE, 16)
    expected = cv2.fisheye.undistortPoints(
        pixels[:, None, :], FISHEYE.intrinsic_matrix, FISHEYE.opencv_distortion, criteria=TIGHT
    )[:, 0]
    rays = FISHEYE.unproject(pixels)
    np.testing.assert_allclose(rays[:, :2], expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("camera", [RADTAN, FISHEYE])
def test_unproject_then_project_is_exact_in_every_pixel(camera: CameraModel) -> None:
    pixels = _pixel_grid(camera, 3)
    rays = camera.unproject(pixels)
    assert np.isfinite(rays).all()
    # 1e-10 in normalised coordinates is ~1e-7 px at these focal lengths.
    np.testing.assert_allclose(camera.project(rays), pixels, atol=1e-7)
    distorted = (pixels - camera.intrinsic_matrix[:2, 2]) / np.diag(camera.intrinsic_matrix)[:2]
    np.testing.assert_allclose(camera.distort(camera.undistort(distorted)), distorted, atol=1e-12)


@pytest.mark.parametrize("camera", [RADTAN, FISHEYE])
def test_distort_undistort_round_trip(camera: CameraModel) -> None:
    rng = np.random.default_rng(3)
    points = _random_points(rng, camera, 500)
    xy = points[:, :2] / points[:, 2:]
    np.testing.assert_allclose(camera.undistort(camera.distort(xy)), xy, atol=1e-10)


def test_opencv_undistort_agrees_through_our_distort() -> None:
    rng = np.random.default_rng(4)
    xy = rng.uniform(-0.6, 0.6, size=(300, 2))
    distorted = RADTAN.distort(xy)
    expected = cv2.undistortPoints(
        distorted[:, None, :], np.eye(3), RADTAN.opencv_distortion, criteria=TIGHT
    )[:, 0]
    np.testing.assert_allclose(RADTAN.undistort(distorted), expected, atol=1e-10)


def test_fisheye_beyond_ninety_degrees_unprojects_to_nan() -> None:
    # theta_d = pi/2 * 1.2 has no root below 90 degrees for a distortion-free fisheye.
    camera = PinholeEquidistant(100, 100, 10.0, 10.0, 50.0, 50.0)
    rays = camera.unproject(np.array([[50.0 + 10.0 * np.pi / 2 * 1.2, 50.0], [55.0, 50.0]]))
    assert np.isnan(rays[0]).all()
    assert np.isfinite(rays[1]).all()


def test_radtan_beyond_the_fold_unprojects_to_nan() -> None:
    # Strong barrel distortion: the distorted radius peaks at r^2 = 1/(3*0.4); pixels past
    # the peak have no preimage.
    camera = PinholeRadtan(100, 100, 10.0, 10.0, 50.0, 50.0, k1=-0.4)
    r_max = np.sqrt(1.0 / 1.2)
    rd_max = r_max * (1.0 - 0.4 * r_max**2)
    rays = camera.unproject(np.array([[50.0 + 10.0 * rd_max * 1.05, 50.0], [52.0, 50.0]]))
    assert np.isnan(rays[0]).all()
    assert np.isfinite(rays[1]).all()
    np.testing.assert_allclose(camera.project(rays[1:]), [[52.0, 50.0]], atol=1e-9)


@given(
    k1=st.floats(-0.35, 0.1),
    k2=st.floats(-0.05, 0.12),
    p1=st.floats(-2e-3, 2e-3),
    p2=st.floats(-2e-3, 2e-3),
    u=st.floats(0.0, 639.0),
    v=st.floats(0.0, 479.0),
)
@settings(max_examples=200, deadline=None, derandomize=True, database=None)
def test_radtan_round_trip_property(
    k1: float, k2: float, p1: float, p2: float, u: float, v: float
) -> None:
    camera = PinholeRadtan(640, 480, 500.0, 500.0, 320.0, 240.0, k1, k2, p1, p2)
    ray = camera.unproject(np.array([[u, v]]))
    if np.isnan(ray).any():
        # Only where the model really folds: the Jacobian of distort vanishes somewhere
        # between the centre and this pixel, so no monotone preimage exists.
        xy_d = np.array([[(u - 320.0) / 500.0, (v - 240.0) / 500.0]])
        radii = np.linspace(0.0, 1.0, 2001)[:, None] * (xy_d * 3.0)
        assert np.any(np.diff(np.hypot(*camera.distort(radii).T)) <= 0)
        return
    np.testing.assert_allclose(camera.project(ray), [[u, v]], atol=1e-7)


@given(
    k1=st.floats(-0.05, 0.1),
    k2=st.floats(-0.05, 0.05),
    k3=st.floats(-0.02, 0.02),
    k4=st.floats(-0.01, 0.01),
    x=st.floats(-1.5, 1.5),
    y=st.floats(-1.5, 1.5),
)
@settings(max_examples=200, deadline=None, derandomize=True, database=None)
def test_fisheye_round_trip_property(
    k1: float, k2: float, k3: float, k4: float, x: float, y: float
) -> None:
    camera = PinholeEquidistant(1000, 1000, 400.0, 400.0, 500.0, 500.0, k1, k2, k3, k4)
    xy = np.array([[x, y]])
    np.testing.assert_allclose(camera.undistort(camera.distort(xy)), xy, atol=1e-10)


@pytest.mark.parametrize("camera", [RADTAN, FISHEYE])
@pytest.mark.parametrize("factor", [0.5, 0.25])
def test_scaled_matches_cv2_resize(camera: CameraModel, factor: float) -> None:
    # A small bright blob; its intensity centroid must land where the scaled camera
    # projects the same ray after cv2.resize with area averaging.
    rng = np.random.default_rng(5)
    center = rng.uniform([200, 150], [camera.width - 200, camera.height - 150])
    vv, uu = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    image = np.exp(-((uu - center[0]) ** 2 + (vv - center[1]) ** 2) / (2 * 6.0**2))
    small_camera = camera.scaled(factor)
    small = cv2.resize(
        image, (small_camera.width, small_camera.height), interpolation=cv2.INTER_AREA
    )
    sv, su = np.mgrid[0 : small.shape[0], 0 : small.shape[1]]
    centroid = np.array([(small * su).sum(), (small * sv).sum()]) / small.sum()
    ray = camera.unproject(center[None])
    np.testing.assert_allclose(small_camera.project(ray)[0], centroid, atol=0.02)
    assert small_camera.width == round(camera.width * factor)
    assert small_camera.kalibr_model == camera.kalibr_model
    np.testing.assert_array_equal(small_camera.opencv_distortion, camera.opencv_distortion)


def test_scaled_rejects_non_positive_factor() -> None:
    with pytest.raises(ValueError, match="positive"):
        RADTAN.scaled(0.0)


def test_shape_errors_are_reported() -> None:
    with pytest.raises(ValueError, match=r"\(N,3\)"):
        RADTAN.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(N,2\)"):
        FISHEYE.unproject(np.zeros((4, 3)))


def test_registry_and_protocol() -> None:
    assert CAMERA_MODELS[("pinhole", "radtan")] is PinholeRadtan
    assert CAMERA_MODELS[("pinhole", "equidistant")] is PinholeEquidistant
    for key, cls in CAMERA_MODELS.items():
        camera = cls.from_kalibr((640, 480), [500.0, 501.0, 320.0, 240.0], [0.1, 0.01, 0.0, 0.0])
        assert isinstance(camera, CameraModel)
        assert camera.kalibr_model == key
        np.testing.assert_array_equal(
            camera.intrinsic_matrix, [[500.0, 0, 320.0], [0, 501.0, 240.0], [0, 0, 1]]
        )
    assert RADTAN.opencv_distortion.shape == (5,)
    assert RADTAN.opencv_distortion[4] == 0.0
    assert FISHEYE.opencv_distortion.shape == (4,)
    with pytest.raises(ValueError, match="4 distortion coefficients"):
        PinholeRadtan.from_kalibr((640, 480), [1.0, 1.0, 0.0, 0.0], [0.1])
    with pytest.raises(ValueError, match="4 distortion coefficients"):
        PinholeEquidistant.from_kalibr((640, 480), [1.0, 1.0, 0.0, 0.0], [0.1, 0.2])
