"""Dive-computer clock and depth relation from a trajectory's z and a depth profile.

Pure math, no I/O. Times are float seconds *relative to a reference* chosen by
the caller (the stage uses the trajectory's first stamp), so float64 keeps
sub-microsecond precision:

* `traj_t_s` are camera-clock times minus the reference, `traj_z_m` the z of
  the trajectory frame (z up, gravity aligned, arbitrary origin);
* `dive_t_s` are dive-computer clock readings minus the same reference number,
  `dive_depth_m` the logged depths (metres, positive down).

The model (one dive computer sample k, at dive-clock reading v_k):

    v = u + time_offset_s + drift_ppm * 1e-6 * u           (u: camera time)
    depth_k = depth_offset_m - depth_scale * z(u_k) + e_k    (e_k: noise, quantisation)

so `time_offset_s` is dive-computer time minus camera time at the reference
and `depth_offset_m` is the depth of the trajectory's origin. The sample is
taken as the trajectory depth at its own (continuous) time, so the estimate is
not limited to the 10 s sampling nor to any resampling grid: z is interpolated
at u_k and the offset moves it continuously.

Estimation, in two steps:

1. `coarse_offset_search`: the sum of squared depth residuals (depth offset
   free, scale 1) for every whole-`step_s` clock offset, all at once with FFT
   cross-correlations of the masked signals (so hours of search cost as much
   as seconds). The dive samples keep their own times (rounded to `step_s`);
   nothing is interpolated between the 10 s samples.
2. `fit_depth_sync`: robust Gauss-Newton (iteratively reweighted, Huber
   weights on a MAD scale) on offset, drift, depth offset and optionally
   scale, from the best coarse candidates. Uncertainties come from the
   Gauss-Newton covariance scaled by the residual variance; they assume
   independent residuals, so slow VIO drift in z makes them optimistic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

# Standard deviation of a uniform quantisation error of a 0.1 m depth resolution.
QUANTISATION_SIGMA_M = 0.1 / math.sqrt(12.0)


class SyncError(ValueError):
    """The data cannot give a clock offset (no overlap, nothing to correlate)."""


@dataclass(frozen=True)
class CoarseCandidate:
    """One local minimum of the coarse search.

    offset_s: dive-computer time minus camera time (seconds), on the `step_s` grid.
    rms_m: RMS depth residual there (depth offset removed, scale 1), metres.
    overlap: number of dive samples inside the trajectory at that offset.
    """

    offset_s: float
    rms_m: float
    overlap: int


@dataclass(frozen=True)
class CoarseResult:
    """Best offsets of the coarse search, best first, and the whole score curve."""

    candidates: list[CoarseCandidate]
    offsets_s: FloatArray
    rms_m: FloatArray
    overlap: npt.NDArray[np.int64]


@dataclass(frozen=True)
class DepthSync:
    """The estimated clock and depth relation, with one-sigma uncertainties.

    time_offset_s: dive-computer time minus camera time at the reference (u = 0), s.
    drift_ppm: dive-computer rate minus camera rate, parts per million.
    depth_offset_m: depth of the trajectory frame's origin (z = 0), metres.
    depth_scale: depth = depth_offset_m - depth_scale * z (1 when not estimated).
    residual_rms_m: RMS of the inlier depth residuals, metres.
    *_sigma: one-sigma uncertainties (0 for a parameter held fixed).
    used: dive samples inside the trajectory; inliers: those with full Huber weight.
    """

    time_offset_s: float
    drift_ppm: float
    depth_offset_m: float
    depth_scale: float
    residual_rms_m: float
    time_offset_sigma_s: float
    drift_sigma_ppm: float
    depth_offset_sigma_m: float
    depth_scale_sigma: float
    used: int
    inliers: int
    robust_scale_m: float
    covariance: FloatArray = field(repr=False)

    def camera_time_s(self, dive_t_s: npt.ArrayLike) -> FloatArray:
        """Camera-clock times (relative seconds) of dive-clock readings (relative seconds)."""
        return camera_time_s(
            np.asarray(dive_t_s, dtype=np.float64), self.time_offset_s, self.drift_ppm
        )

    def dive_time_s(self, camera_t_s: npt.ArrayLike) -> FloatArray:
        """Dive-clock readings (relative seconds) at camera-clock times (relative seconds)."""
        u = np.asarray(camera_t_s, dtype=np.float64)
        return u + self.time_offset_s + self.drift_ppm * 1e-6 * u

    def depth_m(self, z_m: npt.ArrayLike) -> FloatArray:
        """Depth (metres, positive down) of a trajectory z (metres, up)."""
        return self.depth_offset_m - self.depth_scale * np.asarray(z_m, dtype=np.float64)

    def world_z_m(self, z_m: npt.ArrayLike) -> FloatArray:
        """World z (metres, 0 at the surface, up) of a trajectory z."""
        return -self.depth_m(z_m)


def camera_time_s(dive_t_s: FloatArray, offset_s: float, drift_ppm: float) -> FloatArray:
    """Invert v = u + offset + drift * u: camera times u of dive-clock readings v."""
    return (dive_t_s - offset_s) / (1.0 + drift_ppm * 1e-6)


def valid_mask(
    traj_t_s: FloatArray, query_t_s: FloatArray, *, max_gap_s: float
) -> npt.NDArray[np.bool_]:
    """True where a query time lies inside the trajectory and not inside a gap > max_gap_s."""
    inside = (query_t_s >= traj_t_s[0]) & (query_t_s <= traj_t_s[-1])
    right = np.clip(np.searchsorted(traj_t_s, query_t_s), 1, traj_t_s.size - 1)
    gap = traj_t_s[right] - traj_t_s[right - 1]
    mask: npt.NDArray[np.bool_] = inside & (gap <= max_gap_s)
    return mask


def _check_inputs(
    traj_t_s: FloatArray, traj_z_m: FloatArray, dive_t_s: FloatArray, dive_depth_m: FloatArray
) -> None:
    if traj_t_s.ndim != 1 or traj_t_s.shape != traj_z_m.shape or traj_t_s.size < 2:
        raise ValueError("traj_t_s and traj_z_m must be 1-D of one length >= 2")
    if dive_t_s.ndim != 1 or dive_t_s.shape != dive_depth_m.shape:
        raise ValueError("dive_t_s and dive_depth_m must be 1-D of one length")
    if np.any(np.diff(traj_t_s) <= 0):
        raise ValueError("traj_t_s must be strictly increasing")


def sample_interval_s(dive_t_s: FloatArray) -> float:
    """Typical step between dive samples (median), seconds; 10.0 for fewer than 2 samples."""
    if dive_t_s.size < 2:
        return 10.0
    return float(np.median(np.diff(dive_t_s)))


def _correlate(a: FloatArray, b: FloatArray, size: int) -> FloatArray:
    """c[s] = sum_i a[i] * b[i + s] for s = -(len(a) - 1) .. len(b) - 1."""
    fa = np.fft.rfft(a, size)
    fb = np.fft.rfft(b, size)
    full = np.fft.irfft(np.conj(fa) * fb, size)
    # Negative shifts wrap around to the end of the circular result.
    return np.concatenate([full[size - (a.size - 1) :], full[: b.size]])


def coarse_offset_search(
    traj_t_s: npt.ArrayLike,
    traj_z_m: npt.ArrayLike,
    dive_t_s: npt.ArrayLike,
    dive_depth_m: npt.ArrayLike,
    *,
    max_offset_s: float,
    centre_offset_s: float = 0.0,
    step_s: float = 1.0,
    min_overlap_fraction: float = 0.5,
    max_gap_s: float = 5.0,
    candidates: int = 5,
) -> CoarseResult:
    """Score every clock offset on a `step_s` grid by the depth misfit; best candidates first.

    For an offset o, each dive sample (reading v_k, rounded to the grid) meets
    the trajectory z at camera time v_k - o; the score is the RMS of
    depth_k + z minus its mean (the depth offset is free, the scale 1). Only
    offsets within `centre_offset_s +- max_offset_s` where at least
    `min_overlap_fraction` of the possible samples overlap are kept
    (possible: the fewer of the dive's samples and the samples that fit in the
    trajectory's duration). Raises SyncError when no offset qualifies.
    """
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    dive_t = np.asarray(dive_t_s, dtype=np.float64)
    depth = np.asarray(dive_depth_m, dtype=np.float64)
    _check_inputs(traj_t, traj_z, dive_t, depth)
    keep = np.isfinite(depth) & np.isfinite(dive_t)
    dive_t, depth = dive_t[keep], depth[keep]
    if dive_t.size < 3:
        raise SyncError(f"only {dive_t.size} dive samples with a depth (need at least 3)")

    # Trajectory z on the grid j * step + t0, zero (masked) outside and inside gaps.
    t0 = traj_t[0]
    n_traj = round((traj_t[-1] - t0) / step_s) + 1
    grid_t = t0 + step_s * np.arange(n_traj)
    z_mask = valid_mask(traj_t, grid_t, max_gap_s=max_gap_s).astype(np.float64)
    z_grid = np.interp(grid_t, traj_t, traj_z) * z_mask

    # Dive samples as impulses on their own grid (bin a at time (a + a0) * step).
    bins = np.rint(dive_t / step_s).astype(np.int64)
    a0 = int(bins.min())
    n_dive = int(bins.max()) - a0 + 1
    count = np.zeros(n_dive)
    d_sum = np.zeros(n_dive)
    d_sq = np.zeros(n_dive)
    np.add.at(count, bins - a0, 1.0)
    np.add.at(d_sum, bins - a0, depth)
    np.add.at(d_sq, bins - a0, depth * depth)

    size = 1 << math.ceil(math.log2(n_dive + n_traj))
    n = _correlate(count, z_mask, size)
    s_d = _correlate(d_sum, z_mask, size)
    s_dd = _correlate(d_sq, z_mask, size)
    s_z = _correlate(count, z_grid, size)
    s_zz = _correlate(count, z_grid * z_grid, size)
    s_dz = _correlate(d_sum, z_grid, size)
    shifts = np.arange(-(n_dive - 1), n_traj)
    # Dive bin a meets trajectory bin a + s: v = (a + a0) step, u = t0 + (a + s) step.
    offsets = (a0 - shifts) * step_s - t0
    n = np.rint(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        sum_e = s_d + s_z
        sse = s_dd + 2.0 * s_dz + s_zz - sum_e * sum_e / n
        rms = np.sqrt(np.maximum(sse, 0.0) / n)

    interval = sample_interval_s(dive_t)
    possible = min(dive_t.size, (traj_t[-1] - traj_t[0]) / interval + 1.0)
    need = max(3.0, min_overlap_fraction * possible)
    ok = (n >= need) & (np.abs(offsets - centre_offset_s) <= max_offset_s)
    if not np.any(ok):
        best_n = int(n[np.abs(offsets - centre_offset_s) <= max_offset_s].max(initial=0))
        raise SyncError(
            f"no clock offset within {centre_offset_s:+.0f} +- {max_offset_s:.0f} s puts "
            f"{need:.0f} dive samples inside the trajectory (at most {best_n}); the dive "
            "does not overlap the trajectory"
        )
    score = np.where(ok, rms, np.inf)
    # Local minima of the score, best first, at least a sample interval apart.
    order = np.argsort(score, kind="stable")
    picked: list[CoarseCandidate] = []
    separation = max(interval, 2.0 * step_s)
    for index in order:
        if not np.isfinite(score[index]) or len(picked) >= candidates:
            break
        off = float(offsets[index])
        if any(abs(off - c.offset_s) < separation for c in picked):
            continue
        picked.append(CoarseCandidate(off, float(score[index]), int(n[index])))
    return CoarseResult(
        candidates=picked, offsets_s=offsets[ok], rms_m=rms[ok], overlap=n[ok].astype(np.int64)
    )


def smooth_z(traj_t_s: FloatArray, traj_z_m: FloatArray, sigma_s: float) -> FloatArray:
    """z low-passed by a Gaussian of `sigma_s` seconds (on a uniform grid, then back).

    A diver's finning bobs (a few centimetres at periods of seconds) are
    aliased by 10 s sampling: fitted raw, they put spurious minima a second
    or two from the true offset. The clock information is in the slower
    changes, which a 2 s Gaussian keeps; being symmetric, it adds no delay.
    """
    if sigma_s <= 0.0 or traj_t_s.size < 3:
        return traj_z_m
    step = min(float(np.median(np.diff(traj_t_s))), sigma_s / 4.0)
    grid = traj_t_s[0] + step * np.arange(int((traj_t_s[-1] - traj_t_s[0]) / step) + 2)
    z = np.interp(grid, traj_t_s, traj_z_m)
    radius = int(4.0 * sigma_s / step)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) * step / sigma_s) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([np.full(radius, z[0]), z, np.full(radius, z[-1])])
    smoothed: FloatArray = np.interp(traj_t_s, grid, np.convolve(padded, kernel, mode="valid"))
    return smoothed


def _z_and_slope(
    traj_t: FloatArray, traj_z: FloatArray, u: FloatArray, half_window_s: float
) -> tuple[FloatArray, FloatArray]:
    """z(u) by linear interpolation and dz/du by a central difference over +-half_window_s."""
    z = np.interp(u, traj_t, traj_z)
    lo = np.maximum(u - half_window_s, traj_t[0])
    hi = np.minimum(u + half_window_s, traj_t[-1])
    span = np.maximum(hi - lo, 1e-9)
    slope = (np.interp(hi, traj_t, traj_z) - np.interp(lo, traj_t, traj_z)) / span
    return z, slope


def _huber_weights(r: FloatArray, scale: float, k: float) -> FloatArray:
    a = np.abs(r)
    w = np.ones_like(r)
    big = a > k * scale
    w[big] = k * scale / a[big]
    return w


def _robust_scale(r: FloatArray, floor_m: float) -> float:
    mad = float(np.median(np.abs(r - np.median(r)))) if r.size else 0.0
    return max(1.4826 * mad, floor_m)


def fit_depth_sync(
    traj_t_s: npt.ArrayLike,
    traj_z_m: npt.ArrayLike,
    dive_t_s: npt.ArrayLike,
    dive_depth_m: npt.ArrayLike,
    *,
    initial_offset_s: float,
    estimate_time: bool = True,
    estimate_drift: bool = True,
    estimate_scale: bool = False,
    initial_drift_ppm: float = 0.0,
    drift_prior_sigma_ppm: float = 50.0,
    huber_k: float = 1.345,
    noise_floor_m: float = QUANTISATION_SIGMA_M,
    max_gap_s: float = 5.0,
    slope_half_window_s: float = 0.5,
    smooth_s: float = 2.0,
    max_iterations: int = 50,
) -> DepthSync:
    """Robust Gauss-Newton fit of the clock (offset, drift) and the depth relation.

    Residual of sample k: depth_k - (depth_offset - scale * z(u_k)), with
    u_k = (v_k - offset) / (1 + drift * 1e-6) and z linearly interpolated in
    the trajectory (dz/du by a central difference over
    +-`slope_half_window_s`). Huber weights (threshold `huber_k` times a MAD
    scale floored at `noise_floor_m`) make single bad samples and a lever arm
    between wrist and camera harmless. The drift has a zero-mean Gaussian
    prior of `drift_prior_sigma_ppm` so a short or flat dive cannot send it
    anywhere. Samples outside the trajectory or in its gaps (> `max_gap_s`)
    are left out at each iteration. z is first low-passed with a Gaussian of
    `smooth_s` seconds (`smooth_z`; 0 to fit the raw z).

    Raises SyncError when fewer than 3 samples overlap.
    """
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    dive_t = np.asarray(dive_t_s, dtype=np.float64)
    depth = np.asarray(dive_depth_m, dtype=np.float64)
    _check_inputs(traj_t, traj_z, dive_t, depth)
    finite = np.isfinite(depth) & np.isfinite(dive_t)
    dive_t, depth = dive_t[finite], depth[finite]
    traj_z = smooth_z(traj_t, traj_z, smooth_s)

    # Parameters: offset_s, drift_ppm, depth_offset_m, scale.
    params = np.array([initial_offset_s, initial_drift_ppm if estimate_drift else 0.0, 0.0, 1.0])
    active = np.array([estimate_time, estimate_drift and estimate_time, True, estimate_scale])

    def evaluate(
        p: FloatArray,
    ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        u = camera_time_s(dive_t, p[0], p[1])
        use = valid_mask(traj_t, u, max_gap_s=max_gap_s)
        z, slope = _z_and_slope(traj_t, traj_z, u[use], slope_half_window_s)
        r: FloatArray = depth[use] - (p[2] - p[3] * z)
        rate = 1.0 + p[1] * 1e-6
        J = np.zeros((r.size, 4))
        J[:, 0] = -p[3] * slope / rate
        J[:, 1] = -p[3] * slope * u[use] / rate * 1e-6
        J[:, 2] = -1.0
        J[:, 3] = z
        return r, J, z, use

    def cost(r: FloatArray, scale: float, p: FloatArray) -> float:
        a = np.abs(r) / scale
        rho = np.where(a <= huber_k, 0.5 * a * a, huber_k * (a - 0.5 * huber_k))
        prior = 0.5 * (p[1] / drift_prior_sigma_ppm) ** 2 if active[1] else 0.0
        return (float(np.sum(rho)) + prior) / max(r.size, 1)

    r, J, z, use = evaluate(params)
    if r.size < 3:
        raise SyncError(f"only {r.size} dive samples fall inside the trajectory (need 3)")
    # Start the depth offset at the median so the first weights are meaningful.
    params[2] = float(np.median(depth[use] + params[3] * z))
    idx = np.flatnonzero(active)
    scale_m = noise_floor_m
    for _ in range(max_iterations):
        r, J, z, use = evaluate(params)
        if r.size < 3:
            raise SyncError(f"only {r.size} dive samples fall inside the trajectory (need 3)")
        scale_m = _robust_scale(r, noise_floor_m)
        # Weights include 1 / scale^2 so the drift prior is in the same units as the data.
        w = _huber_weights(r, scale_m, huber_k) / scale_m**2
        Ja = J[:, idx]
        H = Ja.T @ (Ja * w[:, None])
        g = Ja.T @ (w * r)
        if active[1]:
            k1 = int(np.flatnonzero(idx == 1)[0])
            H[k1, k1] += 1.0 / drift_prior_sigma_ppm**2
            g[k1] += params[1] / drift_prior_sigma_ppm**2
        step = -np.linalg.solve(H + 1e-12 * np.eye(idx.size), g)
        current = cost(r, scale_m, params)
        # Backtracking: a linear interpolant makes the cost piecewise smooth only.
        factor = 1.0
        while factor > 1e-3:
            trial = params.copy()
            trial[idx] += factor * step
            r_trial, *_ = evaluate(trial)
            if r_trial.size >= 3 and cost(r_trial, scale_m, trial) <= current + 1e-15:
                break
            factor *= 0.5
        else:
            break
        params[idx] += factor * step
        small = np.abs(factor * step) < np.array([1e-4, 1e-3, 1e-5, 1e-6])[idx]
        if np.all(small):
            break

    r, J, z, use = evaluate(params)
    scale_m = _robust_scale(r, noise_floor_m)
    w = _huber_weights(r, scale_m, huber_k)
    Ja = J[:, idx]
    # Gauss-Newton covariance with the residual variance from the weighted residuals.
    dof = max(r.size - idx.size, 1)
    variance = max(float(np.sum(w * r * r)) / dof, 1e-12)
    H = Ja.T @ (Ja * w[:, None]) / variance
    if active[1]:
        k1 = int(np.flatnonzero(idx == 1)[0])
        H[k1, k1] += 1.0 / drift_prior_sigma_ppm**2
    cov_active = np.linalg.pinv(H)
    cov = np.zeros((4, 4))
    cov[np.ix_(idx, idx)] = cov_active
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    inlier = w >= 1.0
    rms = float(np.sqrt(np.mean(r[inlier] ** 2))) if np.any(inlier) else float("nan")
    return DepthSync(
        time_offset_s=float(params[0]),
        drift_ppm=float(params[1]),
        depth_offset_m=float(params[2]),
        depth_scale=float(params[3]),
        residual_rms_m=rms,
        time_offset_sigma_s=float(sig[0]),
        drift_sigma_ppm=float(sig[1]),
        depth_offset_sigma_m=float(sig[2]),
        depth_scale_sigma=float(sig[3]),
        used=int(r.size),
        inliers=int(np.count_nonzero(inlier)),
        robust_scale_m=scale_m,
        covariance=cov,
    )


def robust_cost_m(sync: DepthSync) -> float:
    """A comparable misfit of a fit (robust scale, metres) for choosing between candidates."""
    return sync.robust_scale_m


def depth_variation_m(
    traj_t_s: npt.ArrayLike,
    traj_z_m: npt.ArrayLike,
    dive_t_s: npt.ArrayLike,
    dive_depth_m: npt.ArrayLike,
    sync: DepthSync,
    *,
    max_gap_s: float = 5.0,
) -> tuple[float, float]:
    """Robust spread (5-95 percentile range, metres) of the overlapping dive depths and of z."""
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    dive_t = np.asarray(dive_t_s, dtype=np.float64)
    depth = np.asarray(dive_depth_m, dtype=np.float64)
    u = sync.camera_time_s(dive_t)
    use = valid_mask(traj_t, u, max_gap_s=max_gap_s) & np.isfinite(depth)
    if np.count_nonzero(use) < 2:
        return 0.0, 0.0
    lo, hi = np.percentile(depth[use], [5, 95])
    inside = (traj_t >= u[use].min()) & (traj_t <= u[use].max())
    zlo, zhi = np.percentile(traj_z[inside], [5, 95]) if np.any(inside) else (0.0, 0.0)
    return float(hi - lo), float(zhi - zlo)
