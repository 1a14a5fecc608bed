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

Then the answer is checked (`assess_offset`, `solve_clock_offset`): the fits of
every candidate (of every dive) are compared at one noise scale, and the offset
counts as known only when each clearly different one fits worse by a margin
(`evidence`) and the overlap has enough samples, depth excursion and
curvature. When it does not, a `ClockPrior` (the two wall clocks agree within
minutes, apart from time-zone steps) may restrict the search; otherwise the
caller is told that the offset is ambiguous.
"""

from __future__ import annotations

import dataclasses
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
class ClockPrior:
    """What the clocks' own readings say about the offset (dive-computer minus camera), s.

    Both devices keep a wall clock: the camera's stamps (the trajectory's) and the
    dive computer's log usually agree to within minutes, apart from a time-zone
    difference (the computer keeps local time with no zone). So the offset is
    expected within `window_s` of `centre_offset_s + k * zone_step_s` for some
    integer k (only k = 0 when `zone_step_s` is 0). Offsets are in the caller's
    relative time base, where equal wall-clock readings give `centre_offset_s` = 0.
    """

    window_s: float
    zone_step_s: float = 0.0
    centre_offset_s: float = 0.0

    def distance_s(self, offset_s: npt.ArrayLike) -> FloatArray:
        """|offset - nearest allowed centre| (seconds), elementwise."""
        d = np.asarray(offset_s, dtype=np.float64) - self.centre_offset_s
        if self.zone_step_s > 0.0:
            d = d - self.zone_step_s * np.round(d / self.zone_step_s)
        distance: FloatArray = np.abs(d)
        return distance

    def contains(self, offset_s: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """True where an offset (seconds) lies inside the prior's windows."""
        inside: npt.NDArray[np.bool_] = self.distance_s(offset_s) <= self.window_s
        return inside

    def describe(self) -> str:
        """The windows in words, for messages."""
        zones = f" (+ whole {self.zone_step_s:.0f} s zone steps)" if self.zone_step_s > 0 else ""
        return f"{self.centre_offset_s:+.0f} +- {self.window_s:.0f} s{zones}"


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
    residuals_m: depth residuals of the used samples at the solution (metres).
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
    residuals_m: FloatArray = field(repr=False, default_factory=lambda: np.zeros(0))

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
    prior: ClockPrior | None = None,
) -> CoarseResult:
    """Score every clock offset on a `step_s` grid by the depth misfit; best candidates first.

    For an offset o, each dive sample (reading v_k, rounded to the grid) meets
    the trajectory z at camera time v_k - o; the score is the RMS of
    depth_k + z minus its mean (the depth offset is free, the scale 1). Only
    offsets within `centre_offset_s +- max_offset_s` where at least
    `min_overlap_fraction` of the possible samples overlap are kept
    (possible: the fewer of the dive's samples and the samples that fit in the
    trajectory's duration). With a `prior`, only offsets inside its windows are
    kept. Raises SyncError when no offset qualifies.
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
    searched = np.abs(offsets - centre_offset_s) <= max_offset_s
    where = f"within {centre_offset_s:+.0f} +- {max_offset_s:.0f} s"
    if prior is not None:
        searched &= prior.contains(offsets)
        where += f" and the clock prior {prior.describe()}"
    ok = (n >= need) & searched
    if not np.any(ok):
        best_n = int(n[searched].max(initial=0))
        raise SyncError(
            f"no clock offset {where} puts {need:.0f} dive samples inside the trajectory "
            f"(at most {best_n}); the dive does not overlap the trajectory"
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
        residuals_m=r,
    )


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


# Ambiguity: does the data single out one clock offset?
#
# A long dive leaves one offset standing: any other one misplaces hundreds of
# samples. A minute of video holds six 10 s samples, and with the depth offset
# free a nearly flat stretch of z also matches the safety stop or the other
# dive of the day, a few hundred seconds or hours away. The fits of every
# coarse candidate (of every dive) are compared at one common noise scale; the
# answer counts as known only when each clearly different offset fits worse
# by a margin, enough samples overlap, the depth varies there, and the
# offset's own uncertainty is small.

DEPTH_RESOLUTION_M = 0.1
EXPECTED_NOISE_M = math.hypot(QUANTISATION_SIGMA_M, 0.05)


@dataclass(frozen=True, kw_only=True)
class AmbiguityLimits:
    """When a clock offset counts as known (the thresholds of `assess_offset`).

    min_evidence: the best fit must beat every clearly different offset by this
        much: samples x the difference of mean Huber costs (`mean_huber_cost`).
        For Gaussian residuals it is half the chi-square gap, a log-likelihood
        ratio: 10 means odds of about 2e4 to 1.
    min_samples: dive samples inside the trajectory at the solution (a fit has
        two or three free parameters, so fewer leave nothing to test it).
    min_separation_s: offsets closer than max(this, 3 sigma of the best) are
        one solution, seconds.
    min_depth_range_m: the overlapping dive depths and trajectory z must both
        span this much (5-95 percentile), metres.
    max_time_sigma_s: the offset's one-sigma uncertainty must be below this, s.
    noise_sigma_m: expected depth noise (quantisation, lever arm), metres: the
        scale candidates are ranked at and the least scale costs are compared at.
    resolution_m: the dive computer's depth resolution, metres (for the
        excursion in steps).
    huber_k: Huber threshold in units of the scale.
    """

    min_evidence: float = 6.0
    min_samples: int = 4
    min_separation_s: float = 3.0
    min_depth_range_m: float = 1.0
    max_time_sigma_s: float = 5.0
    noise_sigma_m: float = EXPECTED_NOISE_M
    resolution_m: float = DEPTH_RESOLUTION_M
    huber_k: float = 1.345


@dataclass(frozen=True)
class Solution:
    """One fitted clock solution: the dive it uses (index into the caller's dives) and the fit.

    depth_range_m, z_range_m: 5-95 percentile spans of the overlapping dive
    depths and of the trajectory z there, metres (`depth_variation_m`).
    """

    dive: int
    sync: DepthSync
    depth_range_m: float
    z_range_m: float


@dataclass(frozen=True)
class OffsetAmbiguity:
    """How well the data single out the chosen clock offset.

    samples: dive samples inside the trajectory at the chosen offset.
    depth_range_m, z_range_m: their depth span and the trajectory z span (5-95 %), m.
    excursion_steps: depth_range_m in steps of the depth resolution.
    time_offset_sigma_s: one-sigma uncertainty of the offset (curvature of the fit), s.
    cost_sigma_m: the noise scale the costs below are measured at, metres: the
        larger of the expected noise and the chosen fit's robust scale.
    best_cost: mean Huber cost of the chosen fit (0.5 (r/sigma)^2 inside the
        threshold, linear beyond).
    runner_up_*: the best fit at a clearly different offset (or another dive):
        its offset (s), dive index, mean cost and depth offset (m); None when
        there is none.
    evidence: samples x (runner_up_cost - best_cost); inf without a runner-up.
    solutions: distinct offsets compared (the chosen one included).
    reasons: why the offset is not known; empty when it is.
    """

    samples: int
    depth_range_m: float
    z_range_m: float
    excursion_steps: float
    time_offset_sigma_s: float
    cost_sigma_m: float
    best_cost: float
    runner_up_offset_s: float | None
    runner_up_dive: int | None
    runner_up_cost: float | None
    runner_up_depth_offset_m: float | None
    evidence: float
    solutions: int
    reasons: tuple[str, ...]

    @property
    def ambiguous(self) -> bool:
        """True when the data do not single out one offset."""
        return bool(self.reasons)


def mean_huber_cost(residuals_m: FloatArray, sigma_m: float, k: float = 1.345) -> float:
    """Mean Huber loss of residuals (metres) at scale `sigma_m`; inf for no residual."""
    if residuals_m.size == 0:
        return math.inf
    a = np.abs(residuals_m) / sigma_m
    rho = np.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k))
    return float(np.mean(rho))


def assess_offset(
    solutions: list[Solution], limits: AmbiguityLimits | None = None
) -> tuple[Solution, OffsetAmbiguity]:
    """The best solution and how ambiguous it is.

    The best is the one of least mean Huber cost at `limits.noise_sigma_m` (a
    common, fixed scale: each fit's own robust scale is no measure to choose
    by, since with a handful of samples a wrong offset can declare a third of
    them outliers and fit the rest exactly). Raises ValueError for no solution.
    """
    if not solutions:
        raise ValueError("assess_offset: no solution to assess")
    lim = limits or AmbiguityLimits()
    k = lim.huber_k
    ranked = sorted(
        solutions, key=lambda s: mean_huber_cost(s.sync.residuals_m, lim.noise_sigma_m, k)
    )
    best = ranked[0]
    sync = best.sync
    sigma_t = sync.time_offset_sigma_s
    cost_sigma = max(lim.noise_sigma_m, sync.robust_scale_m)
    best_cost = mean_huber_cost(sync.residuals_m, cost_sigma, k)
    separation = max(lim.min_separation_s, 3.0 * sigma_t if math.isfinite(sigma_t) else 0.0)
    others = [
        s
        for s in ranked[1:]
        if s.dive != best.dive or abs(s.sync.time_offset_s - sync.time_offset_s) > separation
    ]
    distinct: list[Solution] = []
    for s in others:
        if not any(
            s.dive == d.dive and abs(s.sync.time_offset_s - d.sync.time_offset_s) <= separation
            for d in distinct
        ):
            distinct.append(s)
    runner: Solution | None = None
    runner_cost = math.inf
    for s in distinct:
        cost = mean_huber_cost(s.sync.residuals_m, cost_sigma, k)
        if cost < runner_cost:
            runner, runner_cost = s, cost
    evidence = sync.used * (runner_cost - best_cost) if runner is not None else math.inf

    reasons = []
    if sync.used < lim.min_samples:
        reasons.append(
            f"only {sync.used} dive samples overlap the trajectory (need {lim.min_samples})"
        )
    if min(best.depth_range_m, best.z_range_m) < lim.min_depth_range_m:
        reasons.append(
            f"the depth profile is too flat to find the clock offset (depth spans "
            f"{best.depth_range_m:.2f} m, trajectory z {best.z_range_m:.2f} m where they overlap;"
            f" need {lim.min_depth_range_m:.2f} m)"
        )
    if runner is not None and not evidence >= lim.min_evidence:
        reasons.append(
            f"another offset fits almost as well: {sync.time_offset_s:+.1f} s (depth of the "
            f"trajectory origin {sync.depth_offset_m:.2f} m) against "
            f"{runner.sync.time_offset_s:+.1f} s ({runner.sync.depth_offset_m:.2f} m), "
            f"evidence {evidence:.1f} (need {lim.min_evidence:.1f})"
        )
    if not sigma_t <= lim.max_time_sigma_s:
        reasons.append(
            f"the clock offset is undetermined ({sync.time_offset_s:.1f} +- {sigma_t:.1f} s: "
            "nothing to correlate)"
        )
    ambiguity = OffsetAmbiguity(
        samples=sync.used,
        depth_range_m=best.depth_range_m,
        z_range_m=best.z_range_m,
        excursion_steps=best.depth_range_m / lim.resolution_m,
        time_offset_sigma_s=sigma_t,
        cost_sigma_m=cost_sigma,
        best_cost=best_cost,
        runner_up_offset_s=None if runner is None else runner.sync.time_offset_s,
        runner_up_dive=None if runner is None else runner.dive,
        runner_up_cost=None if runner is None else runner_cost,
        runner_up_depth_offset_m=None if runner is None else runner.sync.depth_offset_m,
        evidence=evidence,
        solutions=1 + len(distinct),
        reasons=tuple(reasons),
    )
    return best, ambiguity


@dataclass(frozen=True)
class ClockSolution:
    """The clock offset found, how ambiguous it is, and whether the clock prior decided it.

    dive: index of the dive used (into the caller's list); sync: its fit.
    ambiguity: of the answer given (measured inside the prior when it was used);
        when `ambiguity.ambiguous`, the answer is not to be trusted.
    search_ambiguity: of the unrestricted search.
    prior: the clock prior (None when there is none); prior_used: the answer
        comes from the search restricted to the prior's windows (the
        unrestricted one was ambiguous); prior_distance_s: the answer's distance
        from the prior's nearest centre (None without a prior).
    candidates: coarse candidates of the chosen dive, best first.
    """

    dive: int
    sync: DepthSync
    ambiguity: OffsetAmbiguity
    search_ambiguity: OffsetAmbiguity
    prior: ClockPrior | None
    prior_used: bool
    prior_distance_s: float | None
    candidates: list[CoarseCandidate]


def _fitted_solutions(
    traj_t: FloatArray,
    traj_z: FloatArray,
    dives: list[tuple[FloatArray, FloatArray]],
    *,
    prior: ClockPrior | None,
    search: dict[str, float],
    fit: dict[str, float | bool],
    candidates: int,
    labels: list[str],
) -> tuple[list[Solution], dict[int, list[CoarseCandidate]], list[str]]:
    solutions: list[Solution] = []
    coarse_by_dive: dict[int, list[CoarseCandidate]] = {}
    failures: list[str] = []
    for index, (dive_t, depth) in enumerate(dives):
        try:
            coarse = coarse_offset_search(
                traj_t,
                traj_z,
                dive_t,
                depth,
                max_offset_s=search["max_offset_s"],
                step_s=search["step_s"],
                min_overlap_fraction=search["min_overlap_fraction"],
                max_gap_s=search["max_gap_s"],
                candidates=candidates,
                prior=prior,
            )
        except SyncError as error:
            failures.append(f"{labels[index]}: {error}")
            continue
        coarse_by_dive[index] = coarse.candidates
        for candidate in coarse.candidates:
            try:
                sync = fit_depth_sync(
                    traj_t,
                    traj_z,
                    dive_t,
                    depth,
                    initial_offset_s=candidate.offset_s,
                    max_gap_s=search["max_gap_s"],
                    **fit,  # type: ignore[arg-type]
                )
            except SyncError:
                continue
            if prior is not None and not bool(prior.contains(sync.time_offset_s)):
                continue  # the fit walked out of the prior's window
            depth_range, z_range = depth_variation_m(
                traj_t, traj_z, dive_t, depth, sync, max_gap_s=search["max_gap_s"]
            )
            solutions.append(Solution(index, sync, depth_range, z_range))
    return solutions, coarse_by_dive, failures


def solve_clock_offset(
    traj_t_s: npt.ArrayLike,
    traj_z_m: npt.ArrayLike,
    dives: list[tuple[npt.ArrayLike, npt.ArrayLike]],
    *,
    max_offset_s: float,
    prior: ClockPrior | None = None,
    limits: AmbiguityLimits | None = None,
    labels: list[str] | None = None,
    step_s: float = 1.0,
    min_overlap_fraction: float = 0.5,
    max_gap_s: float = 5.0,
    candidates: int = 5,
    estimate_drift: bool = True,
    estimate_scale: bool = False,
    drift_prior_sigma_ppm: float = 50.0,
) -> ClockSolution:
    """Find the clock offset against one or more dives, and say whether it is known.

    `dives` holds (dive_t_s, dive_depth_m) pairs in the relative time base of
    the module docstring. Every dive is searched over +-`max_offset_s`
    (`coarse_offset_search`), every candidate fitted (`fit_depth_sync`), and the
    fits compared (`assess_offset`). When that is ambiguous and a `prior` is
    given, the search is repeated inside the prior's windows; its best answer
    is taken when it is unambiguous there and the unrestricted search does not
    rule it out (no fit outside beats it by `limits.min_evidence`). The result
    may still be ambiguous: the caller decides what to do then.

    Raises SyncError when no dive overlaps the trajectory at any offset.
    """
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    arrays = [(np.asarray(t, dtype=np.float64), np.asarray(d, dtype=np.float64)) for t, d in dives]
    names = labels if labels is not None else [f"dive {k}" for k in range(len(arrays))]
    lim = limits or AmbiguityLimits()
    search = {
        "max_offset_s": max_offset_s,
        "step_s": step_s,
        "min_overlap_fraction": min_overlap_fraction,
        "max_gap_s": max_gap_s,
    }
    fit: dict[str, float | bool] = {
        "estimate_drift": estimate_drift,
        "estimate_scale": estimate_scale,
        "drift_prior_sigma_ppm": drift_prior_sigma_ppm,
    }
    solutions, coarse, failures = _fitted_solutions(
        traj_t,
        traj_z,
        arrays,
        prior=None,
        search=search,
        fit=fit,
        candidates=candidates,
        labels=names,
    )
    if not solutions:
        raise SyncError("; ".join(failures) or "no fit converged")
    best, ambiguity = assess_offset(solutions, lim)

    def distance(offset_s: float) -> float | None:
        return None if prior is None else float(prior.distance_s(offset_s))

    answer = ClockSolution(
        dive=best.dive,
        sync=best.sync,
        ambiguity=ambiguity,
        search_ambiguity=ambiguity,
        prior=prior,
        prior_used=False,
        prior_distance_s=distance(best.sync.time_offset_s),
        candidates=coarse[best.dive],
    )
    if not ambiguity.ambiguous or prior is None:
        return answer
    inside, inside_coarse, _ = _fitted_solutions(
        traj_t,
        traj_z,
        arrays,
        prior=prior,
        search=search,
        fit=fit,
        candidates=candidates,
        labels=names,
    )
    if not inside:
        return answer
    chosen, inside_ambiguity = assess_offset(inside, lim)
    # The data outside the prior may still rule its answer out.
    sigma = ambiguity.cost_sigma_m
    gap = chosen.sync.used * (
        mean_huber_cost(chosen.sync.residuals_m, sigma, lim.huber_k)
        - mean_huber_cost(best.sync.residuals_m, sigma, lim.huber_k)
    )
    if gap >= lim.min_evidence:
        inside_ambiguity = dataclasses.replace(
            inside_ambiguity,
            reasons=(
                *inside_ambiguity.reasons,
                f"the best offset inside the clock prior ({chosen.sync.time_offset_s:+.1f} s) "
                f"fits clearly worse than {best.sync.time_offset_s:+.1f} s outside it "
                f"(evidence {gap:.1f})",
            ),
        )
    return ClockSolution(
        dive=chosen.dive,
        sync=chosen.sync,
        ambiguity=inside_ambiguity,
        search_ambiguity=ambiguity,
        prior=prior,
        prior_used=True,
        prior_distance_s=distance(chosen.sync.time_offset_s),
        candidates=inside_coarse[chosen.dive],
    )
