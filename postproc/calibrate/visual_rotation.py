"""Camera orientations and relative rotations from images: AprilGrid poses, tracked features.

No file I/O (OpenCV on images in memory). Both paths use the calibrated camera model of
`shared.calibration.cameras` to remove the distortion (`unproject`), then work on
normalised image coordinates, so radtan and equidistant lenses are handled alike.

- `target_from_cam`: pose of the camera from one view of the grid (PnP on the
  undistorted corners, iterative refinement). Accurate to a few hundredths of a degree
  when the grid fills part of the image.
- `rotation_from_features`: `cam_prev_from_cam_cur` between two frames from KLT tracks
  and the essential matrix (RANSAC, then `recoverPose`), for stretches where no grid is
  seen. Less accurate, and biased when the camera barely moves; the robust fit in
  `camera_imu` down-weights the bad pairs.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt

from postproc.calibrate.options import FeatureRotationOptions as FeatureRotationOptions
from shared.calibration.cameras import CameraModel

FloatArray = npt.NDArray[np.float64]


def target_from_cam(
    camera: CameraModel, object_points_m: FloatArray, image_points_px: FloatArray
) -> FloatArray | None:
    """(4,4) `target_from_cam` from (N,3) target corners and their (N,2) pixels; None if
    PnP fails or fewer than 4 corners can be undistorted."""
    import cv2

    rays = camera.unproject(image_points_px)
    ok = np.all(np.isfinite(rays), axis=1)
    if ok.sum() < 4:
        return None
    found, rvec, tvec = cv2.solvePnP(
        object_points_m[ok].astype(np.float64),
        rays[ok, :2].astype(np.float64),
        np.eye(3),
        None,
        flags=cv2.SOLVEPNP_IPPE,
    )
    if not found:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(
        object_points_m[ok].astype(np.float64),
        rays[ok, :2].astype(np.float64),
        np.eye(3),
        None,
        rvec,
        tvec,
    )
    cam_from_target = np.eye(4)
    cam_from_target[:3, :3] = cv2.Rodrigues(rvec)[0]
    cam_from_target[:3, 3] = np.asarray(tvec).ravel()
    if cam_from_target[2, 3] <= 0:
        return None
    pose = cast(FloatArray, np.linalg.inv(cam_from_target))
    return pose


def rotation_from_features(
    camera: CameraModel,
    previous: npt.NDArray[np.uint8],
    current: npt.NDArray[np.uint8],
    options: FeatureRotationOptions | None = None,
) -> FloatArray | None:
    """(3,3) `cam_prev_from_cam_cur` from two grey frames, or None when tracking fails."""
    import cv2

    options = options or FeatureRotationOptions()
    corners = cv2.goodFeaturesToTrack(
        previous, options.max_features, 0.01, options.min_distance_px, blockSize=7
    )
    if corners is None or len(corners) < options.min_inliers:
        return None
    # The stubs do not allow None for nextPts, which OpenCV documents as optional.
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(previous, current, corners, None)  # type: ignore[call-overload]
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(current, previous, tracked, None)  # type: ignore[call-overload]
    good = (status.ravel() == 1) & (status_back.ravel() == 1)
    good &= np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < 0.5
    if good.sum() < options.min_inliers:
        return None
    rays_prev = camera.unproject(corners.reshape(-1, 2)[good].astype(np.float64))[:, :2]
    rays_cur = camera.unproject(tracked.reshape(-1, 2)[good].astype(np.float64))[:, :2]
    ok = np.all(np.isfinite(rays_prev), axis=1) & np.all(np.isfinite(rays_cur), axis=1)
    if ok.sum() < options.min_inliers:
        return None
    focal = float(camera.intrinsic_matrix[0, 0])
    prev_ok, cur_ok = rays_prev[ok], rays_cur[ok]
    threshold = options.ransac_threshold_px / focal
    homography, h_mask = cv2.findHomography(prev_ok, cur_ok, cv2.RANSAC, threshold, maxIters=2000)
    h_inliers = 0 if homography is None else int(h_mask.sum())
    if homography is not None and h_inliers >= options.min_inliers:
        # Hardly any translation (or a far scene): the homography is the rotation itself,
        # and the essential matrix is degenerate. Accept that model when it explains the
        # tracks to within `pure_rotation_px`.
        pure = _homography_rotation(homography)
        inlier = h_mask.ravel() > 0
        moved = np.column_stack((prev_ok[inlier], np.ones(int(inlier.sum())))) @ pure.T
        residual_px = focal * np.linalg.norm(moved[:, :2] / moved[:, 2:3] - cur_ok[inlier], axis=1)
        if float(np.median(residual_px)) <= options.pure_rotation_px:
            result_pure: FloatArray = pure.T
            return result_pure
    essential_rotation, e_inliers = _essential_rotation(prev_ok, cur_ok, threshold, options)
    if essential_rotation is None:
        return None
    if homography is not None and h_inliers >= options.homography_inlier_ratio * e_inliers:
        # A flat scene: the essential matrix's rotation trades off against its
        # translation, while the homography H = R + t n^T / d fixes R up to a discrete
        # choice among its decompositions, settled by the essential matrix's rotation.
        candidates = _homography_candidates(homography, h_mask, prev_ok, cur_ok)
        rotation = min(candidates, key=lambda r: _angle(r @ essential_rotation.T))
    else:
        rotation = essential_rotation
    # Both models give x_cur ~ R x_prev: R is cam_cur_from_cam_prev.
    result: FloatArray = rotation.T
    return result


def _angle(rotation: FloatArray) -> float:
    return float(np.arccos(np.clip(0.5 * (np.trace(rotation) - 1.0), -1.0, 1.0)))


def _essential_rotation(
    rays_prev: FloatArray, rays_cur: FloatArray, threshold: float, options: FeatureRotationOptions
) -> tuple[FloatArray | None, int]:
    """(R = cam_cur_from_cam_prev from the essential matrix, its inlier count) or (None, 0)."""
    import cv2

    essential, mask = cv2.findEssentialMat(
        rays_prev, rays_cur, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=threshold
    )
    if essential is None or essential.shape[1:] != (3,) or int(mask.sum()) < options.min_inliers:
        return None, 0
    # Degenerate configurations give several solutions stacked; RANSAC ranks the first best.
    # Of the two rotations an essential matrix allows, the other is the true one turned
    # half a turn about the baseline; between video frames the small one is right. (No
    # cheirality test: with a tiny baseline the triangulated depths are meaningless.)
    first, second, _ = cv2.decomposeEssentialMat(essential[:3])
    rotation = min(
        (np.asarray(first, dtype=np.float64), np.asarray(second, dtype=np.float64)), key=_angle
    )
    return rotation, int(mask.sum())


def _homography_rotation(homography: FloatArray) -> FloatArray:
    """The rotation nearest a homography between normalised views (exact when H = R)."""
    from shared.geometry import project_to_so3

    # H = R + t n^T / d is defined up to scale; its middle singular value is 1 at the
    # true scale (the standard normalisation before decomposing it).
    scale = float(np.linalg.svd(homography, compute_uv=False)[1])
    return project_to_so3(np.asarray(homography, dtype=np.float64) / scale)


def _homography_candidates(
    homography: FloatArray, mask: FloatArray, rays_prev: FloatArray, rays_cur: FloatArray
) -> list[FloatArray]:
    """Rotations a homography allows: its decompositions with the inlier points in front
    of both cameras."""
    import cv2

    count, rotations, _translations, normals = cv2.decomposeHomographyMat(homography, np.eye(3))
    inlier = mask.ravel() > 0
    visible = cv2.filterHomographyDecompByVisibleRefpoints(
        rotations,
        normals,
        rays_prev[inlier].reshape(-1, 1, 2).astype(np.float32),
        rays_cur[inlier].reshape(-1, 1, 2).astype(np.float32),
    )
    chosen = [int(i) for i in np.asarray(visible).ravel()] if visible is not None else range(count)
    return [np.asarray(rotations[i], dtype=np.float64) for i in chosen]
