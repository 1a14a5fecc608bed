"""Does the video rotate as the gyro says? Time shift, focal scale, stabilisation test.

Pure math, no I/O. An imported GoPro clip comes with a calibration *guess*
(nominal field of view, zero time shift). Both can be far off: a HERO5 clip
on a Karma drone turned out 35 % longer in focal length than the Wide guess
(another lens mode or crop; the file does not say), and a GPMF stream may lead
or lag the video by tens of milliseconds. Neither hurts a near scene much, but
over a far scene the visual factors constrain almost only rotation, and a
rotation the images measure 35 % larger than the gyro tears the estimate
apart (the drone clip "flew" at 15-30 m/s).

Rotation is what images and gyro both see directly, so they are compared
frame to frame:

- visual: the rotation `R_now_prev` that best maps the previous frame's rays
  onto the current frame's (RANSAC on 3-point Kabsch fits); for a far scene
  or a turning camera this is the camera rotation (translation adds a little
  apparent rotation: noise here);
- gyro: the rotation vector integrated over the same interval, shifted by a
  candidate time offset (a small-angle sum: frame intervals turn by < 0.1 rad);
- time shift: the offset maximising the correlation of the two angular speeds;
- focal scale: for small rotations the image-measured angle scales as
  true focal / guessed focal, so the least-squares gain between the visual
  and gyro rotation vectors (pairs that turn by a few pixels or more) gives
  true focal = guessed focal * gain;
- rigidity: the share of the gyro rotation the scaled visual rotation leaves
  unexplained. A rigid camera-IMU pair with a fitting calibration leaves
  10-25 %. An electronically stabilised video (GoPro HyperSmooth, the MAX in
  HERO mode) rotates far less than the body and lags it, so most of the gyro
  rotation is unexplained (about 90 %): no rigid camera-IMU model holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from postproc.slam.types import FloatArray, ImuSamples, IntArray
from shared.geometry import so3_log


@dataclass(kw_only=True)
class GyroCheckOptions:
    """Settings of the gyro / image rotation comparison.

    probe_s: seconds of video tracked for the check before the main pass (the check
        runs only when the calibration is a guess, see `SlamOptions.gyro_check`).
    max_shift_s: time offsets searched, +-seconds (t_imu = t_cam + shift).
    shift_step_s: resolution of the offset search.
    min_rotation_px: pairs whose gyro rotation moves the image centre by at least this
        many pixels (at the guessed focal) take part in the gain and rigidity fits.
    min_pairs: fewer such pairs: too little rotation to say anything ("unknown").
    focal_scale_range: accepted focal corrections (outside: not a rigid camera-IMU pair).
    max_unexplained: above this share of unexplained gyro rotation the camera does not
        turn with the IMU (stabilised video, or a wrong axis convention).
    """

    probe_s: float = 20.0
    max_shift_s: float = 0.15
    shift_step_s: float = 0.002
    min_rotation_px: float = 4.0
    min_pairs: int = 5
    focal_scale_range: tuple[float, float] = (0.6, 1.7)
    max_unexplained: float = 0.5


@dataclass
class GyroCheck:
    """Outcome of `check_gyro_against_images`.

    verdict: "rigid" (the images turn with the gyro; shift and focal scale usable),
        "not rigid" (they do not: stabilised video or wrong axes) or "unknown"
        (too little rotation in the probe).
    time_shift_s: best t_imu - t_cam offset (Kalibr timeshift_cam_imu), seconds.
    focal_scale: true focal / guessed focal.
    unexplained: median |scaled visual - gyro| / median |gyro| over the turning pairs.
    correlation: correlation of the angular speeds at the best shift.
    pairs / turning_pairs: frame pairs compared / pairs turning enough to fit.
    """

    verdict: str
    time_shift_s: float
    focal_scale: float
    unexplained: float
    correlation: float
    pairs: int
    turning_pairs: int

    def as_stats(self) -> dict[str, float | int | str]:
        """Flat numbers for stats.json."""
        return {
            "gyro_check": self.verdict,
            "gyro_check_time_shift_s": self.time_shift_s,
            "gyro_check_focal_scale": self.focal_scale,
            "gyro_check_unexplained": self.unexplained,
            "gyro_check_correlation": self.correlation,
            "gyro_check_pairs": self.pairs,
            "gyro_check_turning_pairs": self.turning_pairs,
        }


def _kabsch(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rotation R minimising sum |R a_i - b_i|^2 (rows are unit vectors)."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation: FloatArray = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rotation


def visual_rotation(
    xy_prev: FloatArray,
    xy_now: FloatArray,
    *,
    rng: np.random.Generator,
    threshold_rad: float,
    iterations: int = 60,
) -> tuple[FloatArray, int]:
    """`R_now_prev` (3, 3) mapping the previous rays onto the current ones, and its inliers.

    `xy_prev` / `xy_now`: (N, 2) undistorted normalised coordinates of the same
    features. RANSAC over 3-point Kabsch fits with `threshold_rad` on the ray
    angle, refined on the inliers. Identity and 0 inliers for fewer than 8 points.
    """
    n = len(xy_prev)
    if n < 8:
        return np.eye(3), 0
    a = np.column_stack([xy_prev, np.ones(n)])
    b = np.column_stack([xy_now, np.ones(n)])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        pick = rng.choice(n, size=3, replace=False)
        rotation = _kabsch(a[pick], b[pick])
        inliers = np.linalg.norm(a @ rotation.T - b, axis=1) < threshold_rad
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < 3:
        return np.eye(3), 0
    return _kabsch(a[best], b[best]), int(best.sum())


def _gyro_angles(
    imu: ImuSamples, starts_ns: IntArray, ends_ns: IntArray, bias_rad_s: FloatArray
) -> FloatArray:
    """Small-angle rotation vectors (P, 3) of the body over each [start, end] (IMU clock).

    Cumulative trapezoid integral of the gyro, linearly interpolated at the
    ends; intervals outside the IMU span give NaN.
    """
    t = (imu.stamps_ns - imu.stamps_ns[0]).astype(np.float64) * 1e-9
    w = imu.gyro_rad_s - bias_rad_s
    cumulative = np.vstack(
        [np.zeros(3), np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None], axis=0)]
    )
    a = (starts_ns - imu.stamps_ns[0]).astype(np.float64) * 1e-9
    b = (ends_ns - imu.stamps_ns[0]).astype(np.float64) * 1e-9
    out = np.column_stack(
        [np.interp(b, t, cumulative[:, i]) - np.interp(a, t, cumulative[:, i]) for i in range(3)]
    )
    outside = (a < 0) | (b > t[-1])
    out[outside] = np.nan
    return out


def check_gyro_against_images(
    *,
    starts_ns: IntArray,
    ends_ns: IntArray,
    visual_now_from_prev: FloatArray,
    imu: ImuSamples,
    imu_from_cam_rotation: FloatArray,
    focal_px: float,
    options: GyroCheckOptions,
) -> GyroCheck:
    """Compare frame-to-frame image rotations with the gyro (see the module docstring).

    starts_ns / ends_ns: (P,) camera-clock stamps of the previous / current frame of
    each pair; visual_now_from_prev: (P, 3, 3) `R_Cnow_Cprev` from `visual_rotation`;
    imu_from_cam_rotation: `R_B_C`; focal_px: the guessed focal length of the
    normalised coordinates the visual rotations came from.
    """
    starts = np.asarray(starts_ns, dtype=np.int64)
    ends = np.asarray(ends_ns, dtype=np.int64)
    R_B_C = np.asarray(imu_from_cam_rotation, dtype=np.float64)
    # Body rotation prev -> now measured by the images, in B: R_B_C R_Cprev_Cnow R_C_B.
    visual = np.array([R_B_C @ so3_log(R.T) for R in visual_now_from_prev]).reshape(-1, 3)
    # No gyro bias is removed: GoPro parts drift ~0.01 rad/s, 0.2 px a frame, far below
    # the turning pairs' `min_rotation_px` that the fits use.
    bias = np.zeros(3)
    shifts = np.arange(-options.max_shift_s, options.max_shift_s + 1e-12, options.shift_step_s)
    best_shift, best_corr = 0.0, -np.inf
    visual_speed = np.linalg.norm(visual, axis=1)
    for shift in shifts:
        shift_ns = round(shift * 1e9)
        gyro = _gyro_angles(imu, starts + shift_ns, ends + shift_ns, bias)
        ok = np.all(np.isfinite(gyro), axis=1)
        if ok.sum() < 3:
            continue
        speed = np.linalg.norm(gyro[ok], axis=1)
        if np.std(speed) == 0 or np.std(visual_speed[ok]) == 0:
            continue
        corr = float(np.corrcoef(speed, visual_speed[ok])[0, 1])
        if corr > best_corr:
            best_shift, best_corr = float(shift), corr
    shift_ns = round(best_shift * 1e9)
    gyro = _gyro_angles(imu, starts + shift_ns, ends + shift_ns, bias)
    ok = np.all(np.isfinite(gyro), axis=1)
    turning = ok & (np.linalg.norm(gyro, axis=1) * focal_px >= options.min_rotation_px)
    count = int(turning.sum())
    if count < options.min_pairs:
        return GyroCheck("unknown", best_shift, 1.0, float("nan"), best_corr, len(starts), count)
    v, g = visual[turning], gyro[turning]
    gain = float(np.sum(v * g) / np.sum(g * g))  # visual = gain * gyro
    focal_scale = gain if gain > 0 else float("inf")
    scaled = v / gain if gain > 0 else v
    unexplained = float(
        np.median(np.linalg.norm(scaled - g, axis=1)) / np.median(np.linalg.norm(g, axis=1))
    )
    low, high = options.focal_scale_range
    rigid = low <= focal_scale <= high and unexplained <= options.max_unexplained
    return GyroCheck(
        "rigid" if rigid else "not rigid",
        best_shift,
        focal_scale,
        unexplained,
        best_corr,
        len(starts),
        count,
    )
