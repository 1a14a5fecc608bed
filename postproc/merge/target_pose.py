"""A target's pose in the camera from all its detected corners at once.

The corners go through the camera model first (distortion removed exactly
by `CameraModel.unproject`), so the PnP itself runs on normalised image
coordinates with an identity camera matrix and no distortion: any model the
camera module knows (radtan, equidistant) is handled the same way. IPPE
gives both planar solutions; the one with the lower reprojection error (in
pixels, through the full camera model) is refined by Levenberg-Marquardt.

Covariance: the 6x6 of `T_C_m` in the `averaging` convention (rotation
first, rad and m, perturbation in the camera frame), from the Gauss-Newton
normal equations of the pixel residuals, scaled by the residual variance
(or by a given corner sigma).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.merge.averaging import MAD_TO_SIGMA
from shared.calibration.cameras import CameraModel
from shared.geometry import make_pose, so3_exp

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class TargetPoseEstimate:
    """`T_C_m` (4, 4) from PnP, with its quality.

    reprojection_rms_px / reprojection_max_px: corner residuals through the camera model.
    corner_count: corners used. covariance: (6, 6) of `T_C_m` (rotation first, rad, m).
    """

    cam_from_target: FloatArray
    reprojection_rms_px: float
    reprojection_max_px: float
    corner_count: int
    covariance: FloatArray


def _reprojection(
    camera: CameraModel, cam_from_target: FloatArray, object_points: FloatArray
) -> FloatArray:
    points_cam = object_points @ cam_from_target[:3, :3].T + cam_from_target[:3, 3]
    return camera.project(points_cam)


def estimate_target_pose(
    camera: CameraModel,
    object_points_m: npt.ArrayLike,
    image_points_px: npt.ArrayLike,
    *,
    corner_sigma_px: float | None = None,
    outlier_factor: float = 5.0,
    min_outlier_px: float = 1.0,
) -> TargetPoseEstimate | None:
    """PnP of a planar target (all points z = 0 in the target frame).

    object_points_m: (N, 3) corners in the target frame (metres), N >= 4.
    image_points_px: (N, 2) matching distorted pixels.
    corner_sigma_px: corner noise for the covariance; None estimates it from
        the residuals (with at least 1/10 px, so a perfect fit is not certain).
    outlier_factor / min_outlier_px: after the first fit, corners whose residual
        exceeds max(outlier_factor robust sigmas, min_outlier_px) are dropped and
        the pose refined again (`corner_count` tells how many were kept).
    Returns None when no pose is found (points that do not undistort, a
    degenerate layout, the target behind the camera). Raises ValueError for
    mismatched shapes or fewer than 4 points.
    """
    import cv2

    obj = np.asarray(object_points_m, dtype=np.float64).reshape(-1, 3)
    img = np.asarray(image_points_px, dtype=np.float64).reshape(-1, 2)
    if obj.shape[0] != img.shape[0]:
        raise ValueError(
            f"estimate_target_pose: {obj.shape[0]} object points but {img.shape[0]} image points"
        )
    if obj.shape[0] < 4:
        raise ValueError(f"estimate_target_pose: need at least 4 points, got {obj.shape[0]}")
    if np.any(np.abs(obj[:, 2]) > 1e-9):
        raise ValueError("estimate_target_pose: object points must be planar (z = 0)")
    normalised = camera.unproject(img)[:, :2]
    valid = np.all(np.isfinite(normalised), axis=1)
    if np.count_nonzero(valid) < 4:
        return None
    obj_v = obj[valid]
    img_v = img[valid]
    xy = normalised[valid]
    identity = np.eye(3)
    try:
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj_v, xy, identity, None, flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error:
        return None
    best: tuple[float, FloatArray, FloatArray] | None = None
    for i in range(int(count)):
        rvec0 = np.asarray(rvecs[i], dtype=np.float64).reshape(3, 1)
        tvec0 = np.asarray(tvecs[i], dtype=np.float64).reshape(3, 1)
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj_v, xy, identity, None, rvec0, tvec0)
        except cv2.error:
            continue
        pose = make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        residual = _reprojection(camera, pose, obj_v) - img_v
        if not np.all(np.isfinite(residual)):
            continue
        error = float(np.sum(residual**2))
        if best is None or error < best[0]:
            best = (error, pose, residual)
    if best is None:
        return None
    _, pose, residual = best
    # One round of corner rejection: a corner refined onto the wrong feature is
    # off by a cell or more, far beyond the noise of the others.
    distances = np.linalg.norm(residual, axis=1)
    limit = max(outlier_factor * MAD_TO_SIGMA * float(np.median(distances)), min_outlier_px)
    keep = distances <= limit
    if 4 <= np.count_nonzero(keep) < len(keep):
        obj_v, img_v, xy = obj_v[keep], img_v[keep], xy[keep]
        rvec = cv2.Rodrigues(pose[:3, :3])[0]
        rvec, tvec = cv2.solvePnPRefineLM(
            obj_v, xy, identity, None, rvec, pose[:3, 3].reshape(3, 1).copy()
        )
        pose = make_pose(cv2.Rodrigues(rvec)[0], np.asarray(tvec).reshape(3))
        residual = _reprojection(camera, pose, obj_v) - img_v
    if np.any(obj_v @ pose[:3, :3].T[:, 2] + pose[2, 3] <= 0):
        return None
    distances = np.linalg.norm(residual, axis=1)
    n = obj_v.shape[0]
    covariance = _pose_covariance(camera, pose, obj_v, residual, corner_sigma_px)
    return TargetPoseEstimate(
        cam_from_target=pose,
        reprojection_rms_px=float(np.sqrt(np.mean(distances**2))),
        reprojection_max_px=float(distances.max()),
        corner_count=n,
        covariance=covariance,
    )


def _pose_covariance(
    camera: CameraModel,
    pose: FloatArray,
    obj: FloatArray,
    residual: FloatArray,
    corner_sigma_px: float | None,
) -> FloatArray:
    """(J^T J)^-1 sigma^2 with J the pixel Jacobian for `[δθ, δt]` (central differences)."""
    n = obj.shape[0]
    if corner_sigma_px is None:
        dof = max(2 * n - 6, 1)
        sigma2 = max(float(np.sum(residual**2)) / dof, 0.1**2)
    else:
        sigma2 = corner_sigma_px**2
    step = 1e-6
    J = np.zeros((2 * n, 6))
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = step
        plus = make_pose(so3_exp(delta[:3]) @ pose[:3, :3], pose[:3, 3] + delta[3:])
        minus = make_pose(so3_exp(-delta[:3]) @ pose[:3, :3], pose[:3, 3] - delta[3:])
        diff = _reprojection(camera, plus, obj) - _reprojection(camera, minus, obj)
        J[:, k] = diff.reshape(-1) / (2 * step)
    try:
        covariance = np.linalg.inv(J.T @ J) * sigma2
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)
    symmetric: FloatArray = 0.5 * (covariance + covariance.T)
    return symmetric
