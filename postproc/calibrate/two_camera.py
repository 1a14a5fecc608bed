"""Two unsynchronised rigs on one mount: their clock offset and relative rotation from gyros.

Pure math, no I/O. Two cameras with their own IMUs (two GoPros on one bar, an OAK and
a GoPro) record the same rigid motion, so their gyros measure the same angular
velocity, each in its own frame and on its own clock:

    omega_1(t + offset) = R_10 * omega_0(t) + (b_1 - R_10 b_0)

with t on clock 0 and t + offset the same instant on clock 1 (offset = clock 1 minus
clock 0, seconds) and R_10 = `imu1_from_imu0`. The offset comes from the
cross-correlation of the rate magnitudes (which do not depend on R_10), refined to
sub-sample by a parabola; R_10 from an SVD alignment of the rate vectors; then all of
offset, rotation and the bias difference by robust least squares with the second gyro
interpolated linearly, so the offset is resolved far below the sample period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.calibrate.camera_imu import GyroSignal, correlate_offset, kabsch_rotation
from postproc.calibrate.options import RigSyncOptions as RigSyncOptions
from shared.errors import StageError
from shared.geometry import so3_exp

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class RigSyncResult:
    """offset_s: clock 1 minus clock 0 (s) at the same instant; imu1_from_imu0: (3,3);
    bias_difference_rad_s: b_1 - R_10 b_0 (3,); coarse_offset_s and peak_correlation from
    the cross-correlation; residual_rms_rad_s over the fit samples; overlap_s: shared
    duration used (s)."""

    offset_s: float
    imu1_from_imu0: FloatArray
    bias_difference_rad_s: FloatArray
    coarse_offset_s: float
    peak_correlation: float
    residual_rms_rad_s: float
    overlap_s: float


def _magnitude_grid(signal: GyroSignal, step_s: float, window_s: float) -> tuple[FloatArray, float]:
    lo, hi = signal.span_s
    grid = np.arange(lo + window_s, hi - window_s, step_s)
    if len(grid) < 4:
        raise StageError(f"gyro recording of {hi - lo:.2f} s is too short to correlate")
    half = 0.5 * window_s
    magnitude = np.linalg.norm(signal.mean_rate(grid - half, grid + half), axis=1)
    return magnitude, float(grid[0])


def estimate_rig_sync(
    stamps0_ns: npt.ArrayLike,
    gyro0_rad_s: npt.ArrayLike,
    stamps1_ns: npt.ArrayLike,
    gyro1_rad_s: npt.ArrayLike,
    options: RigSyncOptions | None = None,
) -> RigSyncResult:
    """Clock offset (clock 1 minus clock 0) and `imu1_from_imu0` of two rigidly joined gyros.

    stamps*_ns: (N,) int64 ns on each rig's own clock; gyro*_rad_s: (N,3) in each IMU
    frame. Raises StageError when the recordings do not overlap for long enough within
    the search range, or the motion does not excite two axes.
    """
    from scipy.optimize import least_squares

    options = options or RigSyncOptions()
    stamps0 = np.asarray(stamps0_ns, dtype=np.int64)
    stamps1 = np.asarray(stamps1_ns, dtype=np.int64)
    if len(stamps0) < 2 or len(stamps1) < 2:
        raise StageError("rig sync: each gyro needs at least 2 samples")
    # One time origin for both (the offset is then a difference of small floats).
    origin = int(stamps0[0])
    gyro0 = GyroSignal(stamps0, gyro0_rad_s, origin)
    gyro1 = GyroSignal(stamps1, gyro1_rad_s, origin)
    window = max(options.smoothing_s, options.coarse_step_s)
    min_overlap = max(int(options.min_overlap_s / options.coarse_step_s), 10)
    a, a0 = _magnitude_grid(gyro0, options.coarse_step_s, window)
    b, b0 = _magnitude_grid(gyro1, options.coarse_step_s, window)
    coarse = correlate_offset(
        a,
        a0,
        b,
        b0,
        options.coarse_step_s,
        max_offset_s=options.max_offset_s,
        min_overlap=min_overlap,
        centre_offset_s=options.prior_offset_s,
    )
    if coarse.peak_correlation < options.min_correlation:
        raise StageError(
            f"rig sync: the two gyros' rates do not correlate (peak "
            f"{coarse.peak_correlation:.2f} < {options.min_correlation} within "
            f"{options.max_offset_s:g} s of {options.prior_offset_s:g} s)"
        )
    a, a0 = _magnitude_grid(gyro0, options.fine_step_s, options.smoothing_s)
    b, b0 = _magnitude_grid(gyro1, options.fine_step_s, options.smoothing_s)
    fine = correlate_offset(
        a,
        a0,
        b,
        b0,
        options.fine_step_s,
        max_offset_s=2.0 * options.coarse_step_s,
        min_overlap=int(options.min_overlap_s / options.fine_step_s),
        centre_offset_s=coarse.offset_s,
    )
    # Clock-0 sample times where the second gyro (shifted) has data, with some margin.
    lo0, hi0 = gyro0.span_s
    lo1, hi1 = gyro1.span_s
    margin = 0.1 + 2.0 * options.coarse_step_s
    start = max(lo0, lo1 - fine.offset_s) + margin
    end = min(hi0, hi1 - fine.offset_s) - margin
    if end - start < options.min_overlap_s:
        raise StageError(
            f"rig sync: the recordings share {max(end - start, 0.0):.1f} s at offset "
            f"{fine.offset_s:.3f} s (need {options.min_overlap_s:g} s)"
        )
    times = np.arange(start, end, 1.0 / options.fit_rate_hz)
    half = 0.5 * options.smoothing_s
    rates0 = gyro0.mean_rate(times - half, times + half)
    rates1 = gyro1.mean_rate(times + fine.offset_s - half, times + fine.offset_s + half)
    singular = np.linalg.svd(rates0 - rates0.mean(axis=0), compute_uv=False)
    excitation = float(singular[-1] / singular[0]) if singular[0] > 0 else 0.0
    if excitation < options.min_axis_excitation:
        raise StageError(
            f"rig sync: the rigs turned about one axis only (excitation {excitation:.3f} < "
            f"{options.min_axis_excitation}); the rotation between them is not observable"
        )
    base = kabsch_rotation(rates1 - rates1.mean(axis=0), rates0 - rates0.mean(axis=0))

    def residuals(params: FloatArray) -> FloatArray:
        rotation = so3_exp(params[:3]) @ base
        shifted = times + params[3]
        predicted = rates0 @ rotation.T + params[4:7]
        measured = gyro1.mean_rate(shifted - half, shifted + half)
        error = measured - predicted
        error[~np.isfinite(error)] = 0.0
        return error.ravel()

    params = np.zeros(7)
    params[3] = fine.offset_s
    solution = least_squares(
        residuals,
        params,
        loss="huber",
        f_scale=options.robust_scale_rad_s,
        x_scale=np.array([0.01, 0.01, 0.01, 0.001, 0.001, 0.001, 0.001]),
    )
    params = solution.x
    error = residuals(params).reshape(-1, 3)
    return RigSyncResult(
        offset_s=float(params[3]),
        imu1_from_imu0=so3_exp(params[:3]) @ base,
        bias_difference_rad_s=params[4:7].copy(),
        coarse_offset_s=coarse.offset_s,
        peak_correlation=fine.peak_correlation,
        residual_rms_rad_s=float(np.sqrt(np.mean(np.sum(error**2, axis=1)))),
        overlap_s=float(end - start),
    )
