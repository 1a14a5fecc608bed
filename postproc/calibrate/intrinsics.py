"""Camera intrinsics from AprilGrid views: pinhole-radtan or pinhole-equidistant.

Pure math, no I/O. The fits are OpenCV's: `cv2.calibrateCameraExtended` (Zhang's
homography initialisation, then Levenberg-Marquardt over intrinsics and every view's
pose) for radtan with k3 fixed at zero (Kalibr's radtan has 4 coefficients), and
`cv2.fisheye.calibrate` for equidistant (the same Kannala-Brandt model as Kalibr's).
Residuals are recomputed through `shared.calibration.cameras`, so the numbers reported
are those of the model the rest of wreckmap uses.

Robustness: after a first fit, views whose RMS reprojection error exceeds
`max(outlier_view_factor * median, outlier_view_min_px)` (a bad detection, a moving
target, a rolling-shutter smear) are dropped and the fit repeated once.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.calibrate.frame_selection import GridView
from postproc.calibrate.options import CameraModelName as CameraModelName
from postproc.calibrate.options import IntrinsicsOptions as IntrinsicsOptions
from shared.calibration.cameras import CameraModel, PinholeEquidistant, PinholeRadtan
from shared.errors import StageError

FloatArray = npt.NDArray[np.float64]

#: Camera models by their names on the command line.
CAMERA_MODEL_NAMES: tuple[str, ...] = typing.get_args(CameraModelName)


@dataclass(frozen=True)
class IntrinsicsResult:
    """The calibrated camera and how well it fits.

    camera: the model; rms_px: RMS reprojection error over all corners of the views used
    (pixels); view_rms_px: (V,) per view; cam_from_target: (V,4,4) poses of the target;
    views_used: indices into the views given; views_dropped: outlier views;
    std_intrinsics: 1-sigma of [fx, fy, cx, cy] (pixels) from the fit's covariance (NaN
    when OpenCV does not give it); corner_count: corners in the views used.
    """

    camera: CameraModel
    rms_px: float
    view_rms_px: FloatArray
    cam_from_target: FloatArray
    views_used: list[int]
    views_dropped: list[int]
    std_intrinsics: FloatArray
    corner_count: int


def _pose(rvec: FloatArray, tvec: FloatArray) -> FloatArray:
    import cv2

    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    pose[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return pose


def reprojection_errors_px(
    camera: CameraModel, cam_from_target: FloatArray, view: GridView
) -> FloatArray:
    """(N,) distances (pixels) between the corners found and those the model projects."""
    points = view.object_points_m @ cam_from_target[:3, :3].T + cam_from_target[:3, 3]
    projected = camera.project(points)
    errors: FloatArray = np.linalg.norm(projected - view.image_points_px, axis=1)
    return np.where(np.isfinite(errors), errors, np.inf)


def _camera_from_opencv(
    model: type[PinholeRadtan] | type[PinholeEquidistant],
    image_size: tuple[int, int],
    matrix: FloatArray,
    distortion: FloatArray,
) -> CameraModel:
    """The camera from OpenCV's 3x3 matrix and its first 4 distortion coefficients."""
    K = np.asarray(matrix, dtype=np.float64)
    coeffs = np.asarray(distortion, dtype=np.float64).ravel()[:4]
    intrinsics = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    return model.from_kalibr(image_size, intrinsics, [float(c) for c in coeffs])


def _fit_radtan(
    views: list[GridView], image_size: tuple[int, int], options: IntrinsicsOptions
) -> tuple[CameraModel, list[FloatArray], FloatArray]:
    import cv2

    width, height = image_size
    objects = [v.object_points_m.astype(np.float32) for v in views]
    images = [v.image_points_px.astype(np.float32) for v in views]
    focal = options.initial_focal_px or float(width)
    matrix = np.array(
        [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )
    flags = cv2.CALIB_FIX_K3
    if options.fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_USE_INTRINSIC_GUESS
    if options.fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
        if options.initial_focal_px is not None:
            flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    if options.zero_distortion:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_ZERO_TANGENT_DIST
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        output = cv2.calibrateCameraExtended(
            objects, images, (width, height), matrix, np.zeros(5), flags=flags, criteria=criteria
        )
    except cv2.error as error:
        raise StageError(f"intrinsics: OpenCV calibration failed ({error.err})") from None
    _, K, dist, rvecs, tvecs, std_intrinsics = output[:6]
    # OpenCV's calibration outputs are float64.
    camera = _camera_from_opencv(
        PinholeRadtan, (width, height), typing.cast(FloatArray, K), typing.cast(FloatArray, dist)
    )
    poses = [
        _pose(typing.cast(FloatArray, r), typing.cast(FloatArray, t))
        for r, t in zip(rvecs, tvecs, strict=True)
    ]
    return camera, poses, np.asarray(std_intrinsics, dtype=np.float64).ravel()[:4]


def _fit_equidistant(
    views: list[GridView], image_size: tuple[int, int], options: IntrinsicsOptions
) -> tuple[CameraModel, list[FloatArray], FloatArray]:
    import cv2

    width, height = image_size
    objects = [v.object_points_m.reshape(1, -1, 3).astype(np.float64) for v in views]
    images = [v.image_points_px.reshape(1, -1, 2).astype(np.float64) for v in views]
    # OpenCV's own start (focal = max side / pi) suits a 180-degree lens; a guess from
    # the image width converges for the narrower fisheyes divers use as well.
    focal = options.initial_focal_px or 0.4 * float(width)
    matrix = np.array(
        [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS
    if options.fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if options.zero_distortion:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4
    if options.fix_aspect_ratio:
        raise StageError("intrinsics: fix_aspect_ratio is not available for pinhole-equidistant")
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
            objects, images, (width, height), matrix, np.zeros(4), flags=flags, criteria=criteria
        )
    except cv2.error as error:
        raise StageError(f"intrinsics: OpenCV fisheye calibration failed ({error.err})") from None
    # OpenCV's calibration outputs are float64.
    camera = _camera_from_opencv(
        PinholeEquidistant, (width, height), typing.cast(FloatArray, K), typing.cast(FloatArray, D)
    )
    poses = [
        _pose(typing.cast(FloatArray, r), typing.cast(FloatArray, t))
        for r, t in zip(rvecs, tvecs, strict=True)
    ]
    return camera, poses, np.full(4, np.nan)


_FITS = {"pinhole-radtan": _fit_radtan, "pinhole-equidistant": _fit_equidistant}


def calibrate_intrinsics(
    views: list[GridView], image_size: tuple[int, int], options: IntrinsicsOptions | None = None
) -> IntrinsicsResult:
    """Fit `options.model` to the views' corners; image_size is (width, height) in pixels.

    Raises StageError for an unknown model, too few views, or a fit that fails.
    """
    options = options or IntrinsicsOptions()
    fit = _FITS.get(options.model)
    if fit is None:
        raise StageError(
            f"intrinsics: unknown camera model {options.model!r} "
            f"(known: {', '.join(CAMERA_MODEL_NAMES)})"
        )
    if len(views) < options.min_views:
        raise StageError(
            f"intrinsics: {len(views)} view(s) of the target (need {options.min_views}; "
            "film the grid from more positions)"
        )
    used = list(range(len(views)))
    dropped: list[int] = []
    for _round in range(2):
        camera, poses, std = fit([views[i] for i in used], image_size, options)
        errors = [
            reprojection_errors_px(camera, pose, views[i])
            for pose, i in zip(poses, used, strict=True)
        ]
        view_rms = np.array([float(np.sqrt(np.mean(e**2))) for e in errors])
        threshold = max(
            options.outlier_view_factor * float(np.median(view_rms)), options.outlier_view_min_px
        )
        bad = [i for i, rms in zip(used, view_rms, strict=True) if not rms <= threshold]
        if _round == 1 or not bad or len(used) - len(bad) < options.min_views:
            break
        dropped = bad
        used = [i for i in used if i not in bad]
    all_errors = np.concatenate(errors)
    rms = float(np.sqrt(np.mean(all_errors**2)))
    if not np.isfinite(rms):
        raise StageError("intrinsics: the fitted model cannot project every corner (fit diverged)")
    return IntrinsicsResult(
        camera=camera,
        rms_px=rms,
        view_rms_px=view_rms,
        cam_from_target=np.array(poses),
        views_used=used,
        views_dropped=dropped,
        std_intrinsics=std,
        corner_count=len(all_errors),
    )
