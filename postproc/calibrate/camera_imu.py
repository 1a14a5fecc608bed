"""Camera-IMU rotation and time shift from the rotations a camera saw and a gyro measured.

Pure math, no I/O. Inputs are the camera's relative rotations between pairs of frames
(from AprilGrid poses or from tracked features, on the camera clock) and the gyro
samples (IMU clock). Conventions as Kalibr: the camera rotation is `cam_from_imu`
(`T_C_B` rotation) and the time shift satisfies t_imu = t_cam + shift.

Model: between frames stamped a and b (camera clock) the camera turned by
    cam_a_from_cam_b = R_CB * D_B(a + shift, b + shift) * R_CB^T
where D_B(s, t) is the body rotation from integrating the gyro (minus its bias) from s
to t, IMU clock. Estimation in three steps:

1. Coarse shift: the magnitude of the angular rate does not depend on the mounting
   rotation, so the camera's |omega| and the gyro's |omega| (averaged over the same
   window as a frame interval) are cross-correlated on a uniform grid; the peak is
   refined to sub-sample with a parabola through its neighbours.
2. Rotation: with that shift, R_CB aligns the gyro's mean rates with the camera's
   (Wahba's problem, solved with an SVD).
3. Joint fit: rotation, shift and a constant gyro bias by robust nonlinear least
   squares on the rotation residuals log(cam_a_from_cam_b^T * predicted) (radians),
   integrating the linearly interpolated gyro over each interval, so the shift is
   resolved far below the IMU and frame sample periods.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.calibrate.options import CameraImuOptions as CameraImuOptions
from shared.clock import seconds_from_ns
from shared.errors import StageError
from shared.geometry import project_to_so3, so3_exp, so3_log

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RotationIntervals:
    """Relative camera rotations between pairs of frames.

    start_ns, end_ns: (N,) int64 frame stamps (camera clock, ns since epoch), end > start.
    start_from_end: (N,3,3) `cam_start_from_cam_end` rotations.
    """

    start_ns: IntArray
    end_ns: IntArray
    start_from_end: FloatArray

    def __post_init__(self) -> None:
        n = len(self.start_ns)
        if self.end_ns.shape != (n,) or self.start_from_end.shape != (n, 3, 3):
            raise ValueError(
                "RotationIntervals: start_ns (N,), end_ns (N,) and start_from_end (N,3,3) "
                f"disagree: {self.start_ns.shape}, {self.end_ns.shape}, "
                f"{self.start_from_end.shape}"
            )
        if n and not np.all(self.end_ns > self.start_ns):
            raise ValueError("RotationIntervals: every interval needs end_ns > start_ns")

    def __len__(self) -> int:
        return len(self.start_ns)

    def subset(self, keep: npt.NDArray[np.bool_]) -> RotationIntervals:
        return RotationIntervals(self.start_ns[keep], self.end_ns[keep], self.start_from_end[keep])


def intervals_from_orientations(
    stamps_ns: npt.ArrayLike, ref_from_cam: npt.ArrayLike, *, max_gap_ns: int
) -> RotationIntervals:
    """Intervals between consecutive orientations (sorted by time) no more than `max_gap_ns` apart.

    ref_from_cam: (N,3,3) camera orientations in any fixed frame (a target, the world).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    rotations = np.asarray(ref_from_cam, dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    stamps, rotations = stamps[order], rotations[order]
    gap = np.diff(stamps)
    keep = (gap > 0) & (gap <= max_gap_ns)
    start = np.flatnonzero(keep)
    relative = np.swapaxes(rotations[start], 1, 2) @ rotations[start + 1]
    return RotationIntervals(stamps[start], stamps[start + 1], relative)


class GyroSignal:
    """A gyro stream as a continuous function: linear interpolation between samples.

    stamps_ns (N,) int64 (IMU clock); rates (N,3) rad/s. Times are handled as float
    seconds from `origin_ns`, so nanosecond stamps far from 1970 keep full precision.
    """

    def __init__(self, stamps_ns: npt.ArrayLike, rates: npt.ArrayLike, origin_ns: int) -> None:
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        values = np.asarray(rates, dtype=np.float64)
        if stamps.ndim != 1 or values.shape != (len(stamps), 3):
            raise ValueError(f"gyro: expected (N,) stamps and (N,3) rates, got {values.shape}")
        if len(stamps) < 2:
            raise StageError("gyro: fewer than 2 samples")
        order = np.argsort(stamps, kind="stable")
        stamps, values = stamps[order], values[order]
        unique = np.concatenate(([True], np.diff(stamps) > 0))
        self.origin_ns = int(origin_ns)
        self.t_s = seconds_from_ns(stamps[unique] - self.origin_ns)
        self.rates = values[unique]
        steps = np.diff(self.t_s)
        self.sample_period_s = float(np.median(steps))
        # Cumulative integral of the piecewise-linear rate (trapezoids), for window means.
        area = 0.5 * (self.rates[1:] + self.rates[:-1]) * steps[:, None]
        self._cumulative = np.vstack((np.zeros((1, 3)), np.cumsum(area, axis=0)))

    @property
    def span_s(self) -> tuple[float, float]:
        return float(self.t_s[0]), float(self.t_s[-1])

    def rate(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M,3) interpolated rate at times t_s (s from origin); NaN outside the samples."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        out = np.column_stack([np.interp(t, self.t_s, self.rates[:, a]) for a in range(3)])
        out[(t < self.t_s[0]) | (t > self.t_s[-1])] = np.nan
        return out

    def integral(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M,3) integral of the rate from the first sample to t_s (rad); NaN outside."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        inside = (t >= self.t_s[0]) & (t <= self.t_s[-1])
        index = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2)
        tau = (t - self.t_s[index])[:, None]
        h = (self.t_s[index + 1] - self.t_s[index])[:, None]
        w0, w1 = self.rates[index], self.rates[index + 1]
        out = self._cumulative[index] + w0 * tau + (w1 - w0) * tau * tau / (2.0 * h)
        out[~inside] = np.nan
        return out

    def mean_rate(self, start_s: npt.ArrayLike, end_s: npt.ArrayLike) -> FloatArray:
        """(M,3) mean rate over [start, end] (rad/s); NaN where the window leaves the samples."""
        start = np.atleast_1d(np.asarray(start_s, dtype=np.float64))
        end = np.atleast_1d(np.asarray(end_s, dtype=np.float64))
        result: FloatArray = (self.integral(end) - self.integral(start)) / (end - start)[:, None]
        return result

    def rotation(
        self, start_s: npt.ArrayLike, end_s: npt.ArrayLike, bias: FloatArray, substeps: int
    ) -> FloatArray:
        """(M,3,3) body rotation `body_start_from_body_end` integrating rate - bias (midpoint
        rule on `substeps` equal steps of each window, rate interpolated linearly)."""
        start = np.atleast_1d(np.asarray(start_s, dtype=np.float64))
        end = np.atleast_1d(np.asarray(end_s, dtype=np.float64))
        step = (end - start) / substeps
        result = np.tile(np.eye(3), (len(start), 1, 1))
        for j in range(substeps):
            mid = start + (j + 0.5) * step
            omega = self.rate(mid) - bias[None, :]
            result = result @ so3_exp(omega * step[:, None])
        return result


@dataclass(frozen=True)
class OffsetEstimate:
    """A time offset from cross-correlation: `offset_s` (sub-sample), the normalised
    correlation at the peak (-1..1) and the grid step used (s)."""

    offset_s: float
    peak_correlation: float
    grid_step_s: float


def correlate_offset(
    reference: FloatArray,
    reference_start_s: float,
    other: FloatArray,
    other_start_s: float,
    step_s: float,
    *,
    max_offset_s: float,
    min_overlap: int,
    centre_offset_s: float = 0.0,
) -> OffsetEstimate:
    """The offset d maximising the correlation of other(t + d) with reference(t).

    Both signals are sampled every `step_s`: reference[i] at reference_start_s + i*step,
    other[j] at other_start_s + j*step (any common time base). Offsets within
    `max_offset_s` of `centre_offset_s` are tried on the grid, scored by the Pearson
    correlation over the samples both signals have (NaN marks a missing sample), and
    the best is refined to sub-sample by a parabola through it and its neighbours.
    Every lag is evaluated at once with FFT correlations of the masked sums.
    """
    from scipy.signal import correlate

    mask_a = np.isfinite(reference).astype(np.float64)
    mask_b = np.isfinite(other).astype(np.float64)
    a = np.where(mask_a > 0, reference, 0.0)
    b = np.where(mask_b > 0, other, 0.0)
    # Centre both first: the masked sums below then do not cancel large means.
    a = (a - a[mask_a > 0].mean()) * mask_a if mask_a.any() else a
    b = (b - b[mask_b > 0].mean()) * mask_b if mask_b.any() else b

    def xcorr(u: FloatArray, v: FloatArray) -> FloatArray:
        # c[k] = sum_i u[i + k] v[i], k = -(len(v) - 1) .. len(u) - 1.
        return np.asarray(correlate(u, v, mode="full", method="fft"), dtype=np.float64)

    count = np.round(xcorr(mask_b, mask_a))
    sum_a = xcorr(mask_b, a)
    sum_b = xcorr(b, mask_a)
    sum_aa = xcorr(mask_b, a * a)
    sum_bb = xcorr(b * b, mask_a)
    sum_ab = xcorr(b, a)
    lags = np.arange(-(len(a) - 1), len(b))
    offsets = other_start_s + lags * step_s - reference_start_s
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.maximum(count, 1.0)
        covariance = sum_ab - sum_a * sum_b / n
        variance = (sum_aa - sum_a**2 / n) * (sum_bb - sum_b**2 / n)
        scores = covariance / np.sqrt(np.maximum(variance, 0.0))
    allowed = (np.abs(offsets - centre_offset_s) <= max_offset_s + 1e-12) & (count >= min_overlap)
    scores = np.where(allowed & np.isfinite(scores), scores, -np.inf)
    best = int(np.argmax(scores))
    if not np.isfinite(scores[best]):
        raise StageError(
            "time offset: the two signals do not overlap for any offset tried "
            f"(|offset - {centre_offset_s:g}| <= {max_offset_s:g} s, "
            f"need {min_overlap} common samples)"
        )
    refined = float(offsets[best])
    if 0 < best < len(scores) - 1 and np.isfinite(scores[best - 1 : best + 2]).all():
        left, centre, right = scores[best - 1], scores[best], scores[best + 1]
        curvature = left - 2.0 * centre + right
        if curvature < 0:
            refined += 0.5 * (left - right) / curvature * step_s
    return OffsetEstimate(refined, float(scores[best]), step_s)


def kabsch_rotation(target: FloatArray, source: FloatArray) -> FloatArray:
    """The rotation R minimising sum |target_i - R source_i|^2 over (N,3) vectors."""
    return project_to_so3(target.T @ source)


@dataclass(frozen=True)
class CameraImuResult:
    """The estimate. cam_from_imu_rotation: (3,3) `R_CB`; timeshift_cam_imu_s: Kalibr's shift
    (t_imu = t_cam + shift); gyro_bias_rad_s: (3,); coarse_timeshift_s and peak_correlation
    from the cross-correlation; residual_rms_rad: RMS of the inlier rotation residuals;
    intervals_used / intervals_total: frame pairs kept / given; axis_excitation: smallest
    over largest singular value of the camera rates."""

    cam_from_imu_rotation: FloatArray
    timeshift_cam_imu_s: float
    gyro_bias_rad_s: FloatArray
    coarse_timeshift_s: float
    peak_correlation: float
    residual_rms_rad: float
    intervals_used: int
    intervals_total: int
    axis_excitation: float
    explained_fraction: float


def _camera_rates(intervals: RotationIntervals, origin_ns: int) -> tuple[FloatArray, ...]:
    start_s = seconds_from_ns(intervals.start_ns - origin_ns)
    end_s = seconds_from_ns(intervals.end_ns - origin_ns)
    rates = so3_log(intervals.start_from_end) / (end_s - start_s)[:, None]
    return start_s, end_s, rates


def coarse_timeshift(
    intervals: RotationIntervals, gyro: GyroSignal, options: CameraImuOptions
) -> OffsetEstimate:
    """Step 1: the shift maximising the correlation of |camera rate| and |gyro rate|."""
    start_s, end_s, rates = _camera_rates(intervals, gyro.origin_ns)
    step = options.correlation_step_s
    mid = 0.5 * (start_s + end_s)
    grid = np.arange(mid[0], mid[-1], step)
    # Camera |omega| on the grid; NaN across gaps between intervals (no data there).
    camera = np.interp(grid, mid, np.linalg.norm(rates, axis=1))
    typical = float(np.median(end_s - start_s))
    after = np.clip(np.searchsorted(mid, grid), 1, len(mid) - 1)
    camera[(mid[after] - mid[after - 1]) > 3.0 * typical] = np.nan
    # The gyro averaged over a frame interval, as the camera's rate is.
    lo, hi = gyro.span_s
    gyro_grid = np.arange(lo, hi, step)
    half = 0.5 * typical
    gyro_magnitude = np.linalg.norm(gyro.mean_rate(gyro_grid - half, gyro_grid + half), axis=1)
    return correlate_offset(
        camera,
        float(grid[0]),
        gyro_magnitude,
        float(gyro_grid[0]),
        step,
        max_offset_s=options.max_timeshift_s,
        min_overlap=max(10, int(np.isfinite(camera).sum()) // 2),
    )


def _residuals(
    params: FloatArray,
    base_rotation: FloatArray,
    start_s: FloatArray,
    end_s: FloatArray,
    measured: FloatArray,
    gyro: GyroSignal,
    options: CameraImuOptions,
) -> FloatArray:
    rotation = so3_exp(params[:3]) @ base_rotation
    shift = params[3]
    bias = params[4:7] if options.estimate_gyro_bias else np.zeros(3)
    body = gyro.rotation(start_s + shift, end_s + shift, bias, options.integration_substeps)
    predicted = rotation[None] @ body @ rotation.T[None]
    error = so3_log(np.swapaxes(measured, 1, 2) @ predicted)
    error[~np.isfinite(error)] = 0.0
    return error.ravel()


def estimate_camera_imu(
    intervals: RotationIntervals,
    gyro_stamps_ns: npt.ArrayLike,
    gyro_rad_s: npt.ArrayLike,
    options: CameraImuOptions | None = None,
) -> CameraImuResult:
    """Camera-IMU rotation `R_CB`, time shift (t_imu = t_cam + shift) and gyro bias.

    intervals: the camera's relative rotations (camera clock); gyro_stamps_ns (N,) int64
    (IMU clock) and gyro_rad_s (N,3). Raises StageError when there are too few intervals,
    the motion turns about one axis only, or the signals do not overlap in time.
    """
    from scipy.optimize import least_squares

    options = options or CameraImuOptions()
    total = len(intervals)
    if total < options.min_intervals:
        raise StageError(
            f"camera-IMU: only {total} frame pairs with a camera rotation "
            f"(need {options.min_intervals}; is the target or the scene visible?)"
        )
    order = np.argsort(intervals.start_ns, kind="stable")
    intervals = RotationIntervals(
        intervals.start_ns[order], intervals.end_ns[order], intervals.start_from_end[order]
    )
    origin = int(intervals.start_ns[0])
    gyro = GyroSignal(gyro_stamps_ns, gyro_rad_s, origin)
    start_s, end_s, camera_rates = _camera_rates(intervals, origin)
    singular = np.linalg.svd(camera_rates, compute_uv=False)
    excitation = float(singular[-1] / singular[0]) if singular[0] > 0 else 0.0
    if excitation < options.min_axis_excitation:
        raise StageError(
            f"camera-IMU: the camera turned about one axis only (excitation {excitation:.3f} "
            f"< {options.min_axis_excitation}); rotate it about all three axes"
        )
    coarse = coarse_timeshift(intervals, gyro, options)
    if coarse.peak_correlation < options.min_correlation:
        raise StageError(
            f"camera-IMU: the camera's and the gyro's rotation rates do not correlate (peak "
            f"{coarse.peak_correlation:.2f} < {options.min_correlation} within "
            f"+-{options.max_timeshift_s} s; a stabilised video, another IMU, a larger shift?)"
        )
    gyro_rates = gyro.mean_rate(start_s + coarse.offset_s, end_s + coarse.offset_s)
    usable = np.all(np.isfinite(gyro_rates), axis=1)
    if usable.sum() < options.min_intervals:
        raise StageError(
            f"camera-IMU: only {int(usable.sum())} frame pairs fall inside the IMU recording"
        )
    base_rotation = kabsch_rotation(camera_rates[usable], gyro_rates[usable])
    params = np.zeros(7 if options.estimate_gyro_bias else 4)
    params[3] = coarse.offset_s
    keep = usable.copy()
    # The shift may move by a few sample periods in the fit; keep intervals with margin.
    margin = 2.0 * max(gyro.sample_period_s, options.correlation_step_s)
    lo, hi = gyro.span_s
    keep &= (start_s + coarse.offset_s - margin >= lo) & (end_s + coarse.offset_s + margin <= hi)
    for _round in range(options.max_rounds):
        args = (
            base_rotation,
            start_s[keep],
            end_s[keep],
            intervals.start_from_end[keep],
            gyro,
            options,
        )
        solution = least_squares(
            _residuals,
            params,
            args=args,
            loss="cauchy",
            f_scale=options.robust_scale_rad,
            x_scale=np.concatenate(([0.01, 0.01, 0.01, 0.001], np.full(len(params) - 4, 0.001))),
        )
        params = solution.x
        residual = np.linalg.norm(
            _residuals(
                params, base_rotation, start_s, end_s, intervals.start_from_end, gyro, options
            ).reshape(-1, 3),
            axis=1,
        )
        sigma = 1.4826 * float(np.median(residual[keep]))
        threshold = max(options.outlier_threshold_rad, options.outlier_mad_factor * sigma)
        inliers = usable & (residual <= threshold)
        inliers &= (start_s + params[3] - margin >= lo) & (end_s + params[3] + margin <= hi)
        if np.array_equal(inliers, keep):
            break
        keep = inliers
        if keep.sum() < options.min_intervals:
            raise StageError(
                f"camera-IMU: only {int(keep.sum())} frame pairs agree with the fit "
                f"(residual <= {threshold:.4f} rad)"
            )
    rotation = so3_exp(params[:3]) @ base_rotation
    rms = float(np.sqrt(np.mean(residual[keep] ** 2)))
    # Excitation again over the pairs the fit kept, from the gyro (less noisy than the
    # camera): outliers and tracking noise can fake it in the camera's rates.
    bias_now = params[4:7] if options.estimate_gyro_bias else np.zeros(3)
    kept_rates = gyro.mean_rate(start_s[keep] + params[3], end_s[keep] + params[3]) - bias_now
    singular = np.linalg.svd(kept_rates, compute_uv=False)
    excitation = float(singular[-1] / singular[0]) if singular[0] > 0 else 0.0
    if excitation < options.min_axis_excitation:
        raise StageError(
            f"camera-IMU: the frame pairs that agree with the gyro turn about one axis only "
            f"(excitation {excitation:.3f} < {options.min_axis_excitation}); rotate the camera "
            "about all three axes"
        )
    # How much of the camera's rotation the gyro explains: 1 - residual power / rotation
    # power over the pairs used. Near 1 on good data; low when the per-frame rotation is
    # at the noise level (a steady shot) or the video is stabilised against the body.
    turned = np.linalg.norm(so3_log(intervals.start_from_end[keep]), axis=1)
    explained = 1.0 - float(np.sum(residual[keep] ** 2)) / max(float(np.sum(turned**2)), 1e-300)
    if explained < options.min_explained:
        raise StageError(
            f"camera-IMU: the fit explains only {100 * max(explained, 0.0):.0f} % of the "
            f"camera's rotation (residual {np.degrees(rms):.3f} deg per frame pair against "
            f"{np.degrees(float(np.sqrt(np.mean(turned**2)))):.3f} deg turned; need "
            f"{100 * options.min_explained:.0f} %): turn the camera more briskly, and not "
            "with a stabilised video"
        )
    return CameraImuResult(
        cam_from_imu_rotation=rotation,
        timeshift_cam_imu_s=float(params[3]),
        gyro_bias_rad_s=params[4:7].copy() if options.estimate_gyro_bias else np.zeros(3),
        coarse_timeshift_s=coarse.offset_s,
        peak_correlation=coarse.peak_correlation,
        residual_rms_rad=rms,
        intervals_used=int(keep.sum()),
        intervals_total=total,
        axis_excitation=excitation,
        explained_fraction=explained,
    )
