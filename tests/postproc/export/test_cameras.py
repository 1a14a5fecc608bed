"""Camera math of the exports: the projection, and pose accuracies against Monte Carlo."""

from __future__ import annotations

import numpy as np

from postproc.export.cameras import ExportCamera, pose_accuracy, project

from .conftest import HEIGHT, PARAMS, WIDTH


def camera_with(points: np.ndarray, pixels: np.ndarray, cam_from_world: np.ndarray) -> ExportCamera:
    return ExportCamera(
        name="a.png", camera_id=1, model="OPENCV", params=tuple(PARAMS), width=WIDTH,
        height=HEIGHT, cam_from_world=cam_from_world, points_m=points, pixels=pixels,
    )  # fmt: skip


def test_projection_matches_pycolmap() -> None:
    import pycolmap

    rng = np.random.default_rng(3)
    points = np.column_stack((rng.uniform(-1, 1, (50, 2)), rng.uniform(1.5, 4, 50)))
    camera = pycolmap.Camera.create_from_model_name(1, "OPENCV", 1.0, WIDTH, HEIGHT)
    camera.params = np.array(PARAMS)  # type: ignore[assignment]  # pycolmap stubs: a Sequence; an array is taken
    ours = project(camera_with(points, points[:, :2], np.eye(4)), points, np.eye(4))
    np.testing.assert_allclose(ours, np.asarray(camera.img_from_cam(points)), atol=1e-9)


def test_pose_accuracy_matches_the_scatter_of_resection() -> None:
    """Predicted one-sigma camera-centre error against the spread of 300 OpenCV
    resections from pixels with 0.5 px noise (points known)."""
    import cv2

    rng = np.random.default_rng(11)
    n = 40
    points = np.column_stack((rng.uniform(-1.2, 1.2, (n, 2)), rng.uniform(2.0, 4.0, n)))
    truth = np.eye(4)
    clean = project(camera_with(points, np.zeros((n, 2)), truth), points, truth)
    noisy = clean + rng.normal(0, 0.5, clean.shape)
    predicted = pose_accuracy(camera_with(points, noisy, truth))
    assert predicted is not None
    K = np.array([[PARAMS[0], 0, PARAMS[2] - 0.5], [0, PARAMS[1], PARAMS[3] - 0.5], [0, 0, 1]])
    dist = np.array(PARAMS[4:])
    centres = []
    for _ in range(300):
        observed = clean + rng.normal(0, 0.5, clean.shape) - 0.5  # OpenCV: centres at 0
        ok, rvec, tvec = cv2.solvePnP(points, observed, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        assert ok
        R, _ = cv2.Rodrigues(rvec)
        centres.append(-R.T @ tvec.ravel())
    spread = np.std(np.array(centres), axis=0)
    np.testing.assert_allclose(predicted.position_sigma_m, spread, rtol=0.3)


def test_too_few_points_give_no_accuracy() -> None:
    points = np.array([[0.0, 0.0, 2.0]] * 5)
    assert pose_accuracy(camera_with(points, np.zeros((5, 2)), np.eye(4))) is None
