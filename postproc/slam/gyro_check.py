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
  true focal = guessed focal * gain, with its standard error from the residuals;
- rigidity: the share of the gyro rotation the scaled visual rotation leaves
  unexplained. A rigid camera-IMU pair with a fitting calibration leaves
  10-25 %. An electronically stabilised video (GoPro HyperSmooth, the MAX in
  HERO mode) re-renders every frame for a virtual camera that follows the
  body's intended motion, smoothed and late: its rotations still go the same
  way as the gyro's (a significantly positive gain) but are much smaller or
  mostly unexplained.

**Three verdicts, and what each needs.** A wrong "not rigid" throws the IMU
away, so it needs strong evidence; anything short of it is "unknown", which
keeps the IMU with the guessed calibration:

- "rigid": at least `min_pairs` turning pairs, the gain inside
  `focal_scale_range` and determined to `max_gain_relative_error`, at most
  `max_unexplained` of the gyro rotation unexplained, the angular speeds
  correlated by at least `min_correlation`, and the best shift inside the
  search range (at its edge the true shift may lie beyond).
- "not rigid": at least `strong_min_pairs` turning pairs, the images measure
  their own rotation well (a bound on their rotation noise, `visual_noise_px`:
  what they report while the gyro is still, or the jitter of consecutive
  rotations, is under `max_noise_fraction` of the gyro's typical turn), the
  gain is significantly positive (more than `min_gain_sigmas` standard
  errors: the images do follow the body), and the rigid model fails beyond
  its uncertainty (the gain `min_gain_sigmas` errors below the lowest
  accepted focal scale, or above the highest, or more than `max_unexplained`
  of the rotation unexplained).
- "unknown" otherwise, with `reason` saying why: too little rotation, or a
  degenerate fit (a gain that is zero, negative or not significant: the
  images and the gyro are unrelated, from bad tracking, a wrong axis
  convention or a frozen image; whichever it is, the data cannot tell), or
  evidence that is mixed.

Every number behind the verdict is in `GyroCheck.as_stats()` for stats.json.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.slam.options import GyroCheckOptions as GyroCheckOptions
from postproc.slam.types import FloatArray, ImuSamples, IntArray
from shared.clock import ns_from_seconds, seconds_from_ns
from shared.geometry import so3_log


@dataclass(kw_only=True)
class GyroCheck:
    """Outcome of `check_gyro_against_images`.

    verdict: "rigid" (the images turn with the gyro; shift and focal scale usable),
        "not rigid" (strong evidence they do not: stabilised video, or wrong axes) or
        "unknown" (not enough evidence either way; the IMU is kept).
    reason: one line saying what decided the verdict.
    time_shift_s: best t_imu - t_cam offset (Kalibr timeshift_cam_imu), seconds.
    shift_at_search_bound: the best shift is at the edge of the searched range.
    gain: least-squares visual / gyro rotation gain over the turning pairs (NaN: none).
    gain_standard_error: its standard error from the fit residuals.
    focal_scale: true focal / guessed focal (= gain when the gain is positive, else NaN).
    unexplained: median |visual / gain - gyro| / median |gyro| over the turning pairs.
    correlation: correlation of the angular speeds at the best shift.
    axis_correlation: (3,) correlation of visual and gyro rotation per body axis over the
        turning pairs (a negative one points at a sign error in the axis convention).
    gyro_rotation_px / visual_rotation_px: median turn of a turning pair, gyro / images,
        in pixels at the guessed focal.
    visual_noise_px: upper bound on the image rotation noise (`_visual_noise_px`; NaN: none).
    pairs / turning_pairs / still_pairs: pairs compared / turning / still.
    """

    verdict: str
    reason: str
    time_shift_s: float
    shift_at_search_bound: bool
    gain: float
    gain_standard_error: float
    focal_scale: float
    unexplained: float
    correlation: float
    axis_correlation: tuple[float, float, float]
    gyro_rotation_px: float
    visual_rotation_px: float
    visual_noise_px: float
    pairs: int
    turning_pairs: int
    still_pairs: int

    def as_stats(self) -> dict[str, float | int | str | bool | list[float | None] | None]:
        """Flat values for stats.json (non-finite numbers become null)."""

        def number(value: float) -> float | None:
            return float(value) if math.isfinite(value) else None

        return {
            "gyro_check": self.verdict,
            "gyro_check_reason": self.reason,
            "gyro_check_time_shift_s": number(self.time_shift_s),
            "gyro_check_shift_at_search_bound": self.shift_at_search_bound,
            "gyro_check_gain": number(self.gain),
            "gyro_check_gain_standard_error": number(self.gain_standard_error),
            "gyro_check_focal_scale": number(self.focal_scale),
            "gyro_check_unexplained": number(self.unexplained),
            "gyro_check_correlation": number(self.correlation),
            "gyro_check_axis_correlation": [number(c) for c in self.axis_correlation],
            "gyro_check_gyro_rotation_px": number(self.gyro_rotation_px),
            "gyro_check_visual_rotation_px": number(self.visual_rotation_px),
            "gyro_check_visual_noise_px": number(self.visual_noise_px),
            "gyro_check_pairs": self.pairs,
            "gyro_check_turning_pairs": self.turning_pairs,
            "gyro_check_still_pairs": self.still_pairs,
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
    t = seconds_from_ns(imu.stamps_ns - imu.stamps_ns[0])
    w = imu.gyro_rad_s - bias_rad_s
    cumulative = np.vstack(
        [np.zeros(3), np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None], axis=0)]
    )
    a = seconds_from_ns(starts_ns - imu.stamps_ns[0])
    b = seconds_from_ns(ends_ns - imu.stamps_ns[0])
    out = np.column_stack(
        [np.interp(b, t, cumulative[:, i]) - np.interp(a, t, cumulative[:, i]) for i in range(3)]
    )
    outside = (a < 0) | (b > t[-1])
    out[outside] = np.nan
    return out


def _best_shift(
    imu: ImuSamples,
    starts: IntArray,
    ends: IntArray,
    visual_speed: FloatArray,
    options: GyroCheckOptions,
) -> tuple[float, float]:
    """(shift_s, correlation) maximising the angular-speed correlation; (0, NaN) if none."""
    shifts = np.arange(-options.max_shift_s, options.max_shift_s + 1e-12, options.shift_step_s)
    best_shift, best_corr = 0.0, -np.inf
    for shift in shifts:
        shift_ns = ns_from_seconds(shift)
        gyro = _gyro_angles(imu, starts + shift_ns, ends + shift_ns, np.zeros(3))
        ok = np.all(np.isfinite(gyro), axis=1)
        if ok.sum() < 3:
            continue
        speed = np.linalg.norm(gyro[ok], axis=1)
        if np.std(speed) == 0 or np.std(visual_speed[ok]) == 0:
            continue
        corr = float(np.corrcoef(speed, visual_speed[ok])[0, 1])
        if corr > best_corr:
            best_shift, best_corr = float(shift), corr
    return best_shift, (best_corr if np.isfinite(best_corr) else float("nan"))


def _visual_noise_px(
    visual: FloatArray,
    starts: IntArray,
    ends: IntArray,
    still: npt.NDArray[np.bool_],
    focal_px: float,
) -> float:
    """An upper bound on the images' rotation noise (pixels), NaN when none can be formed.

    Two bounds, the smaller wins: the median image rotation while the gyro is still
    (any real turn only adds to it), and the median second difference of the image
    rotation over consecutive pairs, divided by sqrt(1.5) (white noise of sigma gives
    sigma sqrt(1.5) there; a smooth turn at 30 frames a second adds little), which
    needs no still moment: a camera that never stops turning has none.
    """
    bounds: list[float] = []
    if still.sum() >= 3:
        bounds.append(float(np.median(np.linalg.norm(visual[still], axis=1))) * focal_px)
    chained = np.flatnonzero(ends[:-2] == starts[1:-1]) if len(starts) >= 3 else np.zeros(0, int)
    chained = chained[ends[chained + 1] == starts[chained + 2]]
    if len(chained) >= 5:
        second = visual[chained + 1] - 0.5 * (visual[chained] + visual[chained + 2])
        bounds.append(float(np.median(np.linalg.norm(second, axis=1))) / math.sqrt(1.5) * focal_px)
    return min(bounds) if bounds else float("nan")


def _correlation(a: FloatArray, b: FloatArray) -> float:
    if len(a) < 3 or np.std(a) == 0 or np.std(b) == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


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
    starts = np.asarray(starts_ns, dtype=np.int64).reshape(-1)
    ends = np.asarray(ends_ns, dtype=np.int64).reshape(-1)
    R_B_C = np.asarray(imu_from_cam_rotation, dtype=np.float64)
    # Body rotation prev -> now measured by the images, in B: R_B_C R_Cprev_Cnow R_C_B.
    visual = np.array([R_B_C @ so3_log(R.T) for R in visual_now_from_prev]).reshape(-1, 3)
    # No gyro bias is removed: GoPro parts drift ~0.01 rad/s, 0.2 px a frame, far below
    # the turning pairs' `min_rotation_px` that the fits use.
    bias = np.zeros(3)
    nan = float("nan")
    best_shift, best_corr = _best_shift(imu, starts, ends, np.linalg.norm(visual, axis=1), options)
    at_bound = bool(abs(abs(best_shift) - options.max_shift_s) < 0.5 * options.shift_step_s)
    shift_ns = ns_from_seconds(best_shift)
    gyro = (
        _gyro_angles(imu, starts + shift_ns, ends + shift_ns, bias)
        if len(starts)
        else np.zeros((0, 3))
    )
    ok = np.all(np.isfinite(gyro), axis=1)
    gyro_px = np.where(ok, np.linalg.norm(np.nan_to_num(gyro), axis=1) * focal_px, nan)
    turning = ok & (gyro_px >= options.min_rotation_px)
    still = ok & (gyro_px < options.still_rotation_px)
    count = int(turning.sum())
    noise_px = _visual_noise_px(visual, starts, ends, still, focal_px)

    def outcome(verdict: str, reason: str, **numbers: float) -> GyroCheck:
        values = {
            "gain": nan,
            "gain_standard_error": nan,
            "focal_scale": nan,
            "unexplained": nan,
            "axis_correlation": (nan, nan, nan),
            "gyro_rotation_px": nan,
            "visual_rotation_px": nan,
        }
        values.update(numbers)
        return GyroCheck(
            verdict=verdict,
            reason=reason,
            time_shift_s=best_shift,
            shift_at_search_bound=at_bound,
            correlation=best_corr,
            visual_noise_px=noise_px,
            pairs=len(starts),
            turning_pairs=count,
            still_pairs=int(still.sum()),
            **values,  # type: ignore[arg-type]
        )

    if count < options.min_pairs:
        return outcome(
            "unknown",
            f"too little rotation: {count} frame pairs turn by >= {options.min_rotation_px:g} px "
            f"(need {options.min_pairs})",
        )
    v, g = visual[turning], gyro[turning]
    gg = float(np.sum(g * g))
    gain = float(np.sum(v * g) / gg)  # visual = gain * gyro
    residual = v - gain * g
    dof = max(3 * count - 1, 1)
    gain_error = float(np.sqrt(np.sum(residual**2) / dof / gg))
    g_norm = np.linalg.norm(g, axis=1)
    numbers: dict[str, object] = {
        "gain": gain,
        "gain_standard_error": gain_error,
        "axis_correlation": tuple(_correlation(g[:, i], v[:, i]) for i in range(3)),
        "gyro_rotation_px": float(np.median(g_norm) * focal_px),
        "visual_rotation_px": float(np.median(np.linalg.norm(v, axis=1)) * focal_px),
    }
    significant = gain > options.min_gain_sigmas * gain_error
    if gain <= 0 or not significant:
        return outcome(
            "unknown",
            f"degenerate fit: visual/gyro gain {gain:.3g} +- {gain_error:.2g} is not "
            "significantly positive (the images do not follow the gyro at all: bad tracking, "
            "a wrong axis convention or a frozen image; not enough evidence to drop the IMU)",
            **numbers,  # type: ignore[arg-type]
        )
    unexplained = float(np.median(np.linalg.norm(v / gain - g, axis=1)) / np.median(g_norm))
    numbers.update(focal_scale=gain, unexplained=unexplained)
    low, high = options.focal_scale_range
    in_range = low <= gain <= high
    precise = gain_error <= options.max_gain_relative_error * gain
    correlated = math.isfinite(best_corr) and best_corr >= options.min_correlation
    if (
        in_range
        and precise
        and correlated
        and not at_bound
        and (unexplained <= options.max_unexplained)
    ):
        return outcome(
            "rigid",
            f"the images turn with the gyro: focal x{gain:.3f} +- {gain_error:.3f}, "
            f"{100 * unexplained:.0f} % unexplained, speed correlation {best_corr:.2f} "
            f"over {count} turning pairs",
            **numbers,  # type: ignore[arg-type]
        )
    sigmas = options.min_gain_sigmas
    outside = gain + sigmas * gain_error < low or gain - sigmas * gain_error > high
    failing = outside or unexplained > options.max_unexplained
    measured = math.isfinite(noise_px) and noise_px <= options.max_noise_fraction * float(
        numbers["gyro_rotation_px"]  # type: ignore[arg-type]
    )
    if count >= options.strong_min_pairs and measured and failing:
        return outcome(
            "not rigid",
            f"the images follow the gyro but no rigid model holds: gain {gain:.3f} +- "
            f"{gain_error:.3f} (accepted {low:g}-{high:g}), {100 * unexplained:.0f} % of the "
            f"rotation unexplained over {count} turning pairs, image noise "
            f"{noise_px:.2f} px against {numbers['gyro_rotation_px']:.1f} px turns",
            **numbers,  # type: ignore[arg-type]
        )
    why = []
    if count < options.strong_min_pairs:
        why.append(f"{count} turning pairs (need {options.strong_min_pairs} to reject)")
    if not measured:
        why.append(f"image rotation noise {noise_px:.2f} px not established as small")
    if not failing:
        why.append("the rigid model is not clearly rejected")
    if not precise:
        why.append(f"gain {gain:.3f} +- {gain_error:.3f} imprecise")
    if not correlated:
        why.append(f"speed correlation {best_corr:.2f}")
    if at_bound:
        why.append("best shift at the search bound")
    return outcome(
        "unknown",
        "mixed evidence: " + "; ".join(why),
        **numbers,  # type: ignore[arg-type]
    )
