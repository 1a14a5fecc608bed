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
and `depth_offset_m` is the depth of the trajectory's origin (with a z rate,
the depth relation over the whole trajectory: see `DepthSync`). The sample is
taken as the trajectory depth at its own (continuous) time, so the estimate is
not limited to the 10 s sampling nor to any resampling grid: z is interpolated
at u_k and the offset moves it continuously.

Estimation, in three steps:

1. `coarse_offset_search`: the sum of squared depth residuals (depth offset
   free, scale 1, and a penalised steady z drift of the trajectory removed)
   for every whole-`step_s` clock offset, all at once with FFT
   cross-correlations of the masked signals (so hours of search cost as much
   as seconds). The dive samples keep their own times (rounded to `step_s`);
   nothing is interpolated between the 10 s samples. Lone depth spikes are
   replaced first and z is low-passed to the samples' Nyquist period, and the
   candidates are local minima of the score.
2. `offset_profile`: around each candidate, the robust misfit on a 0.25 s
   grid (one set of samples for every offset) picks the start of the fit.
3. `fit_depth_sync`: robust Gauss-Newton (iteratively reweighted, Huber
   weights on a MAD scale) on offset, drift, depth offset, the z rate and
   optionally scale. Uncertainties come from the Gauss-Newton covariance
   scaled by the residual variance; they assume independent residuals, so
   a VIO wobble in z makes them optimistic.

Then the answer is checked (`assess_offset`, `solve_clock_offset`): the fits of
every candidate (of every dive) are compared at one noise scale (two fits of a
dive on the samples both use, `cost_gap`), and the offset counts as known only
when each clearly different one fits worse by a margin (`evidence`), the fit
beats a flat profile by that margin too (`flat_profile_fit`), and the overlap
has enough samples and curvature. The best fit a bob period or two away
(`near_alternative`) is reported beside it, not a reason to refuse: it moves
the depth by a centimetre, though the time may be that far off. When the
offset is not known, a `ClockPrior` (the two
wall clocks agree within minutes, apart from time-zone steps) may restrict the
search; otherwise the caller is told that the offset is ambiguous.

Why the steps (issue 21, long flat dives): on 25 minutes within a metre of one
depth, a VIO z drifting 0.4 % of the distance swum (1.8 m) dominated the plain
misfit of every offset, so its curve was one broad valley and the five best
grid points all lay on its slopes; the true minimum was never fitted. A 9 s
finning bob sampled every 10 s looks like a 90 s depth change, so a fit could
also settle one bob period away; and one spike entering or leaving the overlap
outweighed a flat dive's whole signal.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from postproc.depth.options import QUANTISATION_SIGMA_M as QUANTISATION_SIGMA_M

FloatArray = npt.NDArray[np.float64]


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
    z_rate_m_per_s: steady drift of the trajectory's z found alongside (m/s;
        0 when not estimated), and its sigma: the samples are fitted by
        depth = depth_offset_m - depth_scale * z + z_rate_m_per_s * (u - u_mid),
        u_mid the middle of the trajectory, so depth_offset_m is the depth
        relation over the whole trajectory, as without the rate.
    prior_cost: the priors' share of the fit's cost (drift and z rate,
        0.5 (value / prior sigma)^2 each), nats.
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
    z_rate_m_per_s: float = 0.0
    z_rate_sigma_m_per_s: float = 0.0
    prior_cost: float = 0.0

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


def despike(depth_m: FloatArray, *, resolution_m: float = 0.1, k: float = 5.0) -> FloatArray:
    """Depths with isolated spikes replaced by the median of the sample and its neighbours.

    A spike is a sample further than `k` robust sigmas (MAD of the differences
    from that median, floored at the resolution) from it. A median of three
    follows a descent or an ascent exactly, so only lone jumps move. For the
    least-squares coarse search: one 3 m spike entering or leaving the overlap
    changes the misfit more than a flat dive's whole signal does.
    """
    if depth_m.size < 3:
        return depth_m
    padded = np.concatenate([depth_m[:1], depth_m, depth_m[-1:]])
    median3 = np.median(np.lib.stride_tricks.sliding_window_view(padded, 3), axis=1)
    deviation = depth_m - median3
    sigma = max(1.4826 * float(np.median(np.abs(deviation))), resolution_m)
    cleaned: FloatArray = np.where(np.abs(deviation) > k * sigma, median3, depth_m)
    return cleaned


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
    z_rate_sigma_m_per_s: float | None = None,
    noise_sigma_m: float = QUANTISATION_SIGMA_M,
    smooth_s: float | None = None,
    despike_depth: bool = True,
) -> CoarseResult:
    """Score every clock offset on a `step_s` grid by the depth misfit; best local minima first.

    For an offset o, each dive sample (reading v_k, rounded to the grid) meets
    the trajectory z at camera time v_k - o; the score is the RMS of
    depth_k + z minus its mean (the depth offset is free, the scale 1). With
    `z_rate_sigma_m_per_s`, a steady z drift of the trajectory is removed too:
    the misfit is that of depth_k + z = c + b v_k with b penalised by a
    zero-mean prior of that sigma (m/s) against depth noise `noise_sigma_m`
    (ridge regression; the score is the penalised RMS). A drift of a metre or
    two, 0.4 % of the distance swum, otherwise dominates the misfit of every
    offset of a flat dive and hides the one that fits. z is low-passed first
    as in `fit_depth_sync` (`smooth_s`; None: `antialias_sigma_s`), and lone
    depth spikes are replaced first (`despike`; `despike_depth`).

    Only offsets within `centre_offset_s +- max_offset_s` where at least
    `min_overlap_fraction` of the possible samples overlap are kept
    (possible: the fewer of the dive's samples and the samples that fit in the
    trajectory's duration). With a `prior`, only offsets inside its windows are
    kept. Candidates are local minima of the score (the least within one
    sample interval either side), so that one broad valley cannot fill the
    list with its own slopes while a sharp, distinct minimum goes unfitted.
    Raises SyncError when no offset qualifies.
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
    if despike_depth:
        depth = despike(depth)

    interval = sample_interval_s(dive_t)
    traj_z = smooth_z(traj_t, traj_z, antialias_sigma_s(interval) if smooth_s is None else smooth_s)
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
        if z_rate_sigma_m_per_s is not None:
            # e = depth + z regressed on x = (v - centre) / half_span: centred, the
            # sums stay well conditioned; the ridge is the rate prior in x units.
            centre = 0.5 * (dive_t.min() + dive_t.max())
            half_span = max(0.5 * float(np.ptp(dive_t)), step_s)
            x = (dive_t - centre) / half_span
            x_sum = np.zeros(n_dive)
            xx_sum = np.zeros(n_dive)
            xd_sum = np.zeros(n_dive)
            np.add.at(x_sum, bins - a0, x)
            np.add.at(xx_sum, bins - a0, x * x)
            np.add.at(xd_sum, bins - a0, x * depth)
            s_x = _correlate(x_sum, z_mask, size)
            s_xx = _correlate(xx_sum, z_mask, size)
            s_xe = _correlate(xd_sum, z_mask, size) + _correlate(x_sum, z_grid, size)
            ridge = (noise_sigma_m / (z_rate_sigma_m_per_s * half_span)) ** 2
            sxx_c = np.maximum(s_xx - s_x * s_x / n, 0.0)
            sxe_c = s_xe - s_x * sum_e / n
            sse = sse - sxe_c * sxe_c / (sxx_c + ridge)
        rms = np.sqrt(np.maximum(sse, 0.0) / n)

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
    separation = max(interval, 2.0 * step_s)
    half = max(1, int(separation / step_s))
    padded = np.concatenate([np.full(half, np.inf), score, np.full(half, np.inf)])
    local_min = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1).min(axis=1)
    minimum = np.isfinite(score) & (score <= local_min)
    order = np.flatnonzero(minimum)[np.argsort(score[minimum], kind="stable")]
    picked: list[CoarseCandidate] = []
    for index in order:
        if len(picked) >= candidates:
            break
        off = float(offsets[index])
        if any(abs(off - c.offset_s) < separation for c in picked):
            continue
        picked.append(CoarseCandidate(off, float(score[index]), int(n[index])))
    return CoarseResult(
        candidates=picked, offsets_s=offsets[ok], rms_m=rms[ok], overlap=n[ok].astype(np.int64)
    )


def antialias_sigma_s(sample_interval_s: float) -> float:
    """Gaussian sigma (s) that halves z at a period of two sample intervals (their Nyquist).

    exp(-0.5 (2 pi sigma / (2 T))^2) = 1/2 gives sigma = 0.375 T: 3.75 s for
    10 s samples, which keeps 97 % of a 90 s depth change and 3 % of a 9 s bob.
    """
    return math.sqrt(2.0 * math.log(2.0)) * sample_interval_s / math.pi


def smooth_z(traj_t_s: FloatArray, traj_z_m: FloatArray, sigma_s: float) -> FloatArray:
    """z low-passed by a Gaussian of `sigma_s` seconds (on a uniform grid, then back).

    A diver's finning bobs (a few centimetres at periods of seconds) are
    aliased by 10 s sampling: fitted raw, they put spurious minima a second
    or two from the true offset (a 9 s bob sampled every 10 s looks like a
    90 s depth change, and shifting z by one bob period matches it again).
    The clock information is in the slower changes, which survive a low-pass
    at the samples' Nyquist period (`antialias_sigma_s`); being symmetric,
    it adds no delay.
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
    z_rate_sigma_m_per_s: float | None = None,
    huber_k: float = 1.345,
    noise_floor_m: float = QUANTISATION_SIGMA_M,
    max_gap_s: float = 5.0,
    slope_half_window_s: float = 0.5,
    smooth_s: float | None = 2.0,
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
    anywhere. With `z_rate_sigma_m_per_s`, a steady drift of the trajectory's
    z (rate b, m/s, zero-mean Gaussian prior of that sigma) is fitted too:
    depth_k = depth_offset - scale * z(u_k) + b (u_k - u_mid), u_mid the middle
    of the trajectory. Samples outside the
    trajectory or in its gaps (> `max_gap_s`) are left out at each iteration.
    z is first low-passed with a Gaussian of `smooth_s` seconds (`smooth_z`;
    0 to fit the raw z; None: `antialias_sigma_s` of the dive's sample
    interval).

    Raises SyncError when fewer than 3 samples overlap.
    """
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    dive_t = np.asarray(dive_t_s, dtype=np.float64)
    depth = np.asarray(dive_depth_m, dtype=np.float64)
    _check_inputs(traj_t, traj_z, dive_t, depth)
    finite = np.isfinite(depth) & np.isfinite(dive_t)
    dive_t, depth = dive_t[finite], depth[finite]
    if smooth_s is None:
        smooth_s = antialias_sigma_s(sample_interval_s(dive_t))
    traj_z = smooth_z(traj_t, traj_z, smooth_s)

    # Parameters: offset_s, drift_ppm, depth_offset_m, scale, z rate (m/s).
    params = np.array(
        [initial_offset_s, initial_drift_ppm if estimate_drift else 0.0, 0.0, 1.0, 0.0]
    )
    active = np.array(
        [
            estimate_time,
            estimate_drift and estimate_time,
            True,
            estimate_scale,
            z_rate_sigma_m_per_s is not None,
        ]
    )
    # Zero-mean Gaussian priors (sigma per parameter; inf: none).
    prior_sigma = np.array(
        [math.inf, drift_prior_sigma_ppm, math.inf, math.inf, z_rate_sigma_m_per_s or math.inf]
    )
    has_prior = active & np.isfinite(prior_sigma)
    # The z rate is counted from the trajectory's middle, so that the depth offset
    # stays the fit over the whole trajectory (as precise as without the rate).
    mid_s = 0.5 * float(traj_t[0] + traj_t[-1])

    def evaluate(
        p: FloatArray,
    ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        u = camera_time_s(dive_t, p[0], p[1])
        use = valid_mask(traj_t, u, max_gap_s=max_gap_s)
        z, slope = _z_and_slope(traj_t, traj_z, u[use], slope_half_window_s)
        r: FloatArray = depth[use] - (p[2] - p[3] * z + p[4] * (u[use] - mid_s))
        rate = 1.0 + p[1] * 1e-6
        # d r / d offset and d r / d drift: z(u) moves with u, and so does the z rate term.
        du = (p[3] * slope - p[4]) / rate
        J = np.zeros((r.size, 5))
        J[:, 0] = -du
        J[:, 1] = -du * u[use] * 1e-6
        J[:, 2] = -1.0
        J[:, 3] = z
        J[:, 4] = -(u[use] - mid_s)
        return r, J, z, use

    def prior_cost(p: FloatArray) -> float:
        return float(0.5 * np.sum((p[has_prior] / prior_sigma[has_prior]) ** 2))

    def cost(r: FloatArray, scale: float, p: FloatArray) -> float:
        a = np.abs(r) / scale
        rho = np.where(a <= huber_k, 0.5 * a * a, huber_k * (a - 0.5 * huber_k))
        return (float(np.sum(rho)) + prior_cost(p)) / max(r.size, 1)

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
        for k in np.flatnonzero(has_prior[idx]):
            H[k, k] += 1.0 / prior_sigma[idx[k]] ** 2
            g[k] += params[idx[k]] / prior_sigma[idx[k]] ** 2
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
        small = np.abs(factor * step) < np.array([1e-4, 1e-3, 1e-5, 1e-6, 1e-9])[idx]
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
    for k in np.flatnonzero(has_prior[idx]):
        H[k, k] += 1.0 / prior_sigma[idx[k]] ** 2
    cov_active = np.linalg.pinv(H)
    cov = np.zeros((5, 5))
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
        covariance=cov[:4, :4],
        residuals_m=r,
        z_rate_m_per_s=float(params[4]),
        z_rate_sigma_m_per_s=float(sig[4]),
        prior_cost=prior_cost(params),
    )


def offset_profile(
    traj_t_s: npt.ArrayLike,
    traj_z_m: npt.ArrayLike,
    dive_t_s: npt.ArrayLike,
    dive_depth_m: npt.ArrayLike,
    *,
    centre_offset_s: float,
    half_width_s: float,
    step_s: float = 0.25,
    drift_ppm: float = 0.0,
    noise_sigma_m: float = QUANTISATION_SIGMA_M,
    z_rate_sigma_m_per_s: float | None = None,
    huber_k: float = 1.345,
    smooth_s: float | None = 2.0,
    max_gap_s: float = 5.0,
    iterations: int = 6,
) -> tuple[FloatArray, FloatArray]:
    """Mean robust misfit of every offset on a fine grid around one: (offsets_s, cost).

    For each offset centre +- half_width (every `step_s`), the depth offset
    and the z rate (as in `fit_depth_sync`, scale 1, drift held) are fitted
    by a few reweighting steps of Huber least squares at `noise_sigma_m`; the
    cost is the mean Huber loss of the samples inside the trajectory at every
    offset of the grid, plus the rate prior's share (inf with fewer than 3). Gauss-Newton from a
    coarse candidate follows its first step wherever the cost is lower, and
    with z known only through 10 s samples the cost has minima a bob period
    apart: a full step from a good start can land in the next one. This
    profile finds the lowest minimum near the candidate before the fit.
    """
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    dive_t = np.asarray(dive_t_s, dtype=np.float64)
    depth = np.asarray(dive_depth_m, dtype=np.float64)
    finite = np.isfinite(depth) & np.isfinite(dive_t)
    dive_t, depth = dive_t[finite], depth[finite]
    if smooth_s is None:
        smooth_s = antialias_sigma_s(sample_interval_s(dive_t))
    traj_z = smooth_z(traj_t, traj_z, smooth_s)
    offsets = centre_offset_s + step_s * np.arange(
        -math.floor(half_width_s / step_s), math.floor(half_width_s / step_s) + 1
    )
    # (offset, sample) arrays: camera times, validity, e = depth + z.
    u = (dive_t[None, :] - offsets[:, None]) / (1.0 + drift_ppm * 1e-6)
    valid = valid_mask(traj_t, u.ravel(), max_gap_s=max_gap_s).reshape(u.shape)
    # The same samples for every offset (those inside the trajectory at all of
    # them), so that no offset wins by leaving a bad sample out.
    valid = np.broadcast_to(valid.all(axis=0), valid.shape)
    e = depth[None, :] + np.interp(u, traj_t, traj_z)
    x = u - 0.5 * float(traj_t[0] + traj_t[-1])
    rate_sigma = z_rate_sigma_m_per_s or 0.0
    slope_free = rate_sigma > 0.0
    ridge = (noise_sigma_m / rate_sigma) ** 2 if slope_free else 0.0
    w = valid.astype(np.float64)
    c = np.zeros(offsets.size)
    b = np.zeros(offsets.size)
    for _ in range(iterations):
        sw = w.sum(axis=1)
        swx = (w * x).sum(axis=1)
        swxx = (w * x * x).sum(axis=1)
        swe = (w * e).sum(axis=1)
        swxe = (w * x * e).sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            if slope_free:
                det = sw * (swxx + ridge) - swx * swx
                c = (swe * (swxx + ridge) - swx * swxe) / det
                b = (sw * swxe - swx * swe) / det
            else:
                c = swe / sw
        r = e - c[:, None] - b[:, None] * x
        a = np.abs(r) / noise_sigma_m
        w = np.where(a > huber_k, huber_k / np.maximum(a, 1e-300), 1.0) * valid
    a = np.abs(e - c[:, None] - b[:, None] * x) / noise_sigma_m
    rho = np.where(a <= huber_k, 0.5 * a * a, huber_k * (a - 0.5 * huber_k)) * valid
    n = valid.sum(axis=1)
    prior = 0.5 * (b / rate_sigma) ** 2 if slope_free else np.zeros(offsets.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost: FloatArray = np.where(n >= 3, (rho.sum(axis=1) + prior) / n, np.inf)
    return offsets.astype(np.float64), cost


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
# by a margin, enough samples overlap, the trajectory explains the depths
# better than a constant depth does (the depth varies there, whatever its span
# in metres), and the offset's own uncertainty is small.

DEPTH_RESOLUTION_M = 0.1
EXPECTED_NOISE_M = math.hypot(QUANTISATION_SIGMA_M, 0.05)


@dataclass(frozen=True, kw_only=True)
class AmbiguityLimits:
    """When a clock offset counts as known (the thresholds of `assess_offset`).

    min_evidence: the best fit must beat every clearly different offset, and
        a flat profile, by this much: samples x the difference of mean Huber
        costs (`mean_huber_cost`, `cost_gap`) plus that of the priors' costs.
        For Gaussian residuals it is half the chi-square gap, a log-likelihood
        ratio: 10 means odds of about 2e4 to 1.
    min_samples: dive samples inside the trajectory at the solution (a fit has
        two or three free parameters, so fewer leave nothing to test it).
    min_separation_s: offsets closer than max(this, 3 sigma of the best) are
        one solution, seconds.
    min_depth_range_m: the overlapping dive depths and trajectory z must both
        span this much (5-95 percentile), metres; 0: no such gate. Flatness is
        judged by the data (`flat_cost`): the trajectory must explain the
        depths better than a constant depth does, by `min_evidence`.
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
    min_depth_range_m: float = 0.0
    max_time_sigma_s: float = 5.0
    noise_sigma_m: float = EXPECTED_NOISE_M
    resolution_m: float = DEPTH_RESOLUTION_M
    huber_k: float = 1.345


@dataclass(frozen=True)
class Solution:
    """One fitted clock solution: the dive it uses (index into the caller's dives) and the fit.

    depth_range_m, z_range_m: 5-95 percentile spans of the overlapping dive
    depths and of the trajectory z there, metres (`depth_variation_m`).
    flat_residuals_m, flat_prior_cost: the same samples fitted by a flat
    profile, no trajectory at all (`flat_profile_fit`): the null model the
    fit must beat; None when not computed.
    used_mask: which of the dive's samples the fit used (its residuals are
        theirs, in order), so that two fits of one dive are compared on the
        samples both use; None when not known.
    """

    dive: int
    sync: DepthSync
    depth_range_m: float
    z_range_m: float
    flat_residuals_m: FloatArray | None = field(default=None, repr=False)
    flat_prior_cost: float = 0.0
    used_mask: npt.NDArray[np.bool_] | None = field(default=None, repr=False)


def _shared(a: Solution, b: Solution) -> npt.NDArray[np.bool_] | None:
    """The samples two fits of one dive both use, when that is most (80 %) of each's."""
    if a.dive != b.dive or a.used_mask is None or b.used_mask is None:
        return None
    common = a.used_mask & b.used_mask
    n = int(common.sum())
    if n < 3 or n < 0.8 * max(int(a.used_mask.sum()), int(b.used_mask.sum())):
        return None
    return common


def cost_gap(a: Solution, b: Solution, sigma_m: float, k: float = 1.345) -> float:
    """How much worse b fits than a (nats: Huber costs at `sigma_m` plus prior costs).

    Two fits of one dive that share most of their samples (`_shared`: offsets
    a few sample intervals apart) are compared on the samples both use: a
    sample inside one overlap only (a spike at the trajectory's end, say)
    would otherwise decide between them. Other pairs are compared by mean
    cost over a's sample count.
    """
    priors = b.sync.prior_cost - a.sync.prior_cost
    common = _shared(a, b)
    if common is not None and a.used_mask is not None and b.used_mask is not None:
        ra = a.sync.residuals_m[common[a.used_mask]]
        rb = b.sync.residuals_m[common[b.used_mask]]
        return (
            ra.size * (mean_huber_cost(rb, sigma_m, k) - mean_huber_cost(ra, sigma_m, k)) + priors
        )
    mean_a = mean_huber_cost(a.sync.residuals_m, sigma_m, k)
    mean_b = mean_huber_cost(b.sync.residuals_m, sigma_m, k)
    return a.sync.used * (mean_b - mean_a) + priors


def flat_profile_fit(
    u_s: FloatArray,
    depth_m: FloatArray,
    *,
    noise_sigma_m: float,
    z_rate_sigma_m_per_s: float | None,
    huber_k: float = 1.345,
    iterations: int = 30,
) -> tuple[FloatArray, float]:
    """Residuals (m) and prior cost (nats) of the depths fitted with no trajectory at all.

    The null model of the sync: depth_k = c + b u_k (a constant depth plus the
    same penalised z rate the sync may use), by iteratively reweighted Huber
    least squares at `noise_sigma_m`. A clock offset is only found when the
    trajectory's z explains the depths clearly better than this: on a flat
    profile it explains nothing, whatever its span in metres.
    """
    columns = [np.ones_like(u_s), u_s] if z_rate_sigma_m_per_s else [np.ones_like(u_s)]
    X = np.column_stack(columns)
    ridge = np.zeros(X.shape[1])
    if z_rate_sigma_m_per_s:
        ridge[1] = (noise_sigma_m / z_rate_sigma_m_per_s) ** 2
    coef = np.zeros(X.shape[1])
    coef[0] = float(np.median(depth_m)) if depth_m.size else 0.0
    for _ in range(iterations):
        r = depth_m - X @ coef
        w = _huber_weights(r, noise_sigma_m, huber_k)
        new = np.linalg.solve(X.T @ (X * w[:, None]) + np.diag(ridge), X.T @ (w * depth_m))
        if np.allclose(new, coef, rtol=0.0, atol=1e-9):
            coef = new
            break
        coef = new
    residuals: FloatArray = depth_m - X @ coef
    prior = 0.5 * (coef[1] / z_rate_sigma_m_per_s) ** 2 if z_rate_sigma_m_per_s else 0.0
    return residuals, float(prior)


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
    evidence: samples x (runner_up_cost - best_cost), plus the difference of
        the two fits' prior costs; inf without a runner-up.
    solutions: distinct offsets compared (the chosen one included).
    reasons: why the offset is not known; empty when it is.
    flat_evidence: the same measure against a flat profile (the depths
        fitted with no trajectory, `flat_profile_fit`): how much the
        trajectory explains at all; inf when not computed.
    near_offset_s, near_evidence, near_depth_offset_m: the best fit a few
        sample intervals from the answer (`near_alternative`: a finning bob's
        period away, where no coarse candidate lies), its evidence and depth
        offset; None / inf when none was found. Not a reason to refuse: such
        an offset moves the depth by near_depth_offset_m - the answer's, a
        centimetre or so on a flat dive, but the time may be that far off.
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
    flat_evidence: float = math.inf
    near_offset_s: float | None = None
    near_evidence: float = math.inf
    near_depth_offset_m: float | None = None

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
    them outliers and fit the rest exactly), its priors' cost (drift, z rate)
    shared out over its samples. The best must beat every clearly different
    offset, and a flat profile fitted to its samples (when the solution
    carries one), by `limits.min_evidence`. Raises ValueError for no solution.
    """
    if not solutions:
        raise ValueError("assess_offset: no solution to assess")
    lim = limits or AmbiguityLimits()
    k = lim.huber_k

    def ranking_cost(s: Solution) -> float:
        used = max(s.sync.used, 1)
        return mean_huber_cost(s.sync.residuals_m, lim.noise_sigma_m, k) + s.sync.prior_cost / used

    ranked = sorted(solutions, key=ranking_cost)
    best = ranked[0]
    # A fit that beats the first on the samples both use takes its place.
    for _ in range(len(ranked)):
        better = [s for s in ranked if cost_gap(best, s, lim.noise_sigma_m, k) < 0.0]
        if not better:
            break
        best = min(better, key=lambda s: cost_gap(best, s, lim.noise_sigma_m, k))
    ranked = [best, *[s for s in ranked if s is not best]]
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
    evidence = math.inf
    for s in distinct:
        gap = cost_gap(best, s, cost_sigma, k)
        if gap < evidence:
            runner, evidence = s, gap
            runner_cost = mean_huber_cost(s.sync.residuals_m, cost_sigma, k)
    best_total = sync.used * best_cost + sync.prior_cost
    flat_evidence = math.inf
    if best.flat_residuals_m is not None:
        flat_cost = mean_huber_cost(best.flat_residuals_m, cost_sigma, k)
        flat_evidence = sync.used * flat_cost + best.flat_prior_cost - best_total

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
    if not flat_evidence >= lim.min_evidence:
        reasons.append(
            f"the depth profile is too flat to find the clock offset (depth spans "
            f"{best.depth_range_m:.2f} m, trajectory z {best.z_range_m:.2f} m where they overlap, "
            f"and the trajectory explains the depths hardly better than a constant depth: "
            f"evidence {flat_evidence:.1f}, need {lim.min_evidence:.1f})"
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
        flat_evidence=flat_evidence,
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


def z_rate_prior_sigma_m_per_s(
    traj_t_s: FloatArray, z_walk_sigma_m_per_sqrt_s: float | None
) -> float | None:
    """Prior sigma (m/s) of a steady z drift over a trajectory, from its random walk (m/sqrt(s)).

    A random walk of sigma w drifts w sqrt(T) over the trajectory's duration T:
    a rate of w / sqrt(T). None without a walk or a duration.
    """
    duration_s = float(traj_t_s[-1] - traj_t_s[0]) if traj_t_s.size else 0.0
    if z_walk_sigma_m_per_sqrt_s is None or duration_s <= 0.0:
        return None
    return z_walk_sigma_m_per_sqrt_s / math.sqrt(duration_s)


@dataclass(frozen=True)
class _FitContext:
    """One dive against the trajectory, with the search's settings: fits and profiles."""

    index: int
    traj_t: FloatArray
    traj_z: FloatArray
    dive_t: FloatArray
    depth: FloatArray
    max_gap_s: float
    noise_sigma_m: float
    z_rate_sigma_m_per_s: float | None
    fit: dict[str, float | bool]
    prior: ClockPrior | None

    def profile(
        self, centre_s: float, half_width_s: float, drift_ppm: float
    ) -> tuple[FloatArray, FloatArray]:
        return offset_profile(
            self.traj_t,
            self.traj_z,
            self.dive_t,
            self.depth,
            centre_offset_s=centre_s,
            half_width_s=half_width_s,
            drift_ppm=drift_ppm,
            noise_sigma_m=self.noise_sigma_m,
            z_rate_sigma_m_per_s=self.z_rate_sigma_m_per_s,
            max_gap_s=self.max_gap_s,
        )

    def solution(self, start_s: float, drift_ppm: float) -> Solution | None:
        """The fit from `start_s` with what the assessment needs; None when it fails
        or walks out of the prior's windows."""
        try:
            sync = fit_depth_sync(
                self.traj_t,
                self.traj_z,
                self.dive_t,
                self.depth,
                initial_offset_s=start_s,
                initial_drift_ppm=drift_ppm,
                max_gap_s=self.max_gap_s,
                z_rate_sigma_m_per_s=self.z_rate_sigma_m_per_s,
                **self.fit,  # type: ignore[arg-type]
            )
        except SyncError:
            return None
        if self.prior is not None and not bool(self.prior.contains(sync.time_offset_s)):
            return None
        depth_range, z_range = depth_variation_m(
            self.traj_t, self.traj_z, self.dive_t, self.depth, sync, max_gap_s=self.max_gap_s
        )
        u = sync.camera_time_s(self.dive_t)
        finite = np.isfinite(self.depth) & np.isfinite(self.dive_t)
        used = np.zeros(self.dive_t.size, dtype=bool)
        used[finite] = valid_mask(self.traj_t, u[finite], max_gap_s=self.max_gap_s)
        flat_residuals, flat_prior = flat_profile_fit(
            u[used],
            self.depth[used],
            noise_sigma_m=self.noise_sigma_m,
            z_rate_sigma_m_per_s=self.z_rate_sigma_m_per_s,
        )
        mask = used if int(used.sum()) == sync.residuals_m.size else None
        return Solution(self.index, sync, depth_range, z_range, flat_residuals, flat_prior, mask)


def near_alternative(
    context: _FitContext, best: Solution, *, min_separation_s: float, cost_sigma_m: float
) -> tuple[Solution, float] | None:
    """The best distinct fit within two sample intervals of `best`, and how much worse it is.

    The fine profile (`offset_profile`) over +-2 sample intervals around the
    answer, its local minima (the least within +-1 s) outside max(
    min_separation_s, 3 sigma) of it, each fitted; the one of least
    `cost_gap` is returned with that gap (nats). None when there is none.
    """
    sync = best.sync
    interval = sample_interval_s(context.dive_t)
    offsets, cost = context.profile(sync.time_offset_s, 2.0 * interval, sync.drift_ppm)
    apart = max(min_separation_s, 3.0 * sync.time_offset_sigma_s)
    half = max(1, round(1.0 / float(offsets[1] - offsets[0]))) if offsets.size > 1 else 1
    padded = np.concatenate([np.full(half, np.inf), cost, np.full(half, np.inf)])
    least = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1).min(axis=1)
    keep = np.isfinite(cost) & (cost <= least) & (np.abs(offsets - sync.time_offset_s) > apart)
    found: tuple[Solution, float] | None = None
    for index in np.flatnonzero(keep)[np.argsort(cost[keep], kind="stable")][:3]:
        near = context.solution(float(offsets[index]), sync.drift_ppm)
        if near is None or abs(near.sync.time_offset_s - sync.time_offset_s) <= apart:
            continue
        gap = cost_gap(best, near, cost_sigma_m)
        if found is None or gap < found[1]:
            found = (near, gap)
    return found


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
    z_rate_sigma_m_per_s: float | None,
    noise_sigma_m: float,
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
                z_rate_sigma_m_per_s=z_rate_sigma_m_per_s,
                noise_sigma_m=noise_sigma_m,
            )
        except SyncError as error:
            failures.append(f"{labels[index]}: {error}")
            continue
        coarse_by_dive[index] = coarse.candidates
        separation_s = max(sample_interval_s(dive_t), 2.0 * search["step_s"])
        context = _FitContext(
            index=index,
            traj_t=traj_t,
            traj_z=traj_z,
            dive_t=dive_t,
            depth=depth,
            max_gap_s=search["max_gap_s"],
            noise_sigma_m=noise_sigma_m,
            z_rate_sigma_m_per_s=z_rate_sigma_m_per_s,
            fit=fit,
            prior=prior,
        )
        for candidate in coarse.candidates:
            # The lowest minimum within the candidate's reach (up to the next local
            # minimum the coarse search could have kept), then the fit from it.
            offsets, cost = context.profile(candidate.offset_s, separation_s, 0.0)
            finite = bool(np.isfinite(cost).any())
            found = context.solution(
                float(offsets[np.argmin(cost)]) if finite else candidate.offset_s, 0.0
            )
            if found is None:
                continue
            solutions.append(found)
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
    z_walk_sigma_m_per_sqrt_s: float | None = 0.01,
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

    `z_walk_sigma_m_per_sqrt_s` is the trajectory's vertical drift (VIO: a
    random walk of about 0.01 m/sqrt(s), or a steady 0.4 % of the distance
    swum): its steady part, a z rate, is fitted alongside the clock under a
    prior of that sigma over the square root of the trajectory's duration
    (None: no z rate). On a long, nearly flat dive a drift of a metre or two
    is larger than the depth changes the clock is read from.

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
    z_rate_sigma = z_rate_prior_sigma_m_per_s(traj_t, z_walk_sigma_m_per_sqrt_s)
    solutions, coarse, failures = _fitted_solutions(
        traj_t,
        traj_z,
        arrays,
        prior=None,
        search=search,
        fit=fit,
        candidates=candidates,
        labels=names,
        z_rate_sigma_m_per_s=z_rate_sigma,
        noise_sigma_m=lim.noise_sigma_m,
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
        return _with_near(
            answer, traj_t, traj_z, arrays, search, fit, z_rate_sigma, lim, best, solutions
        )
    inside, inside_coarse, _ = _fitted_solutions(
        traj_t,
        traj_z,
        arrays,
        prior=prior,
        search=search,
        fit=fit,
        candidates=candidates,
        labels=names,
        z_rate_sigma_m_per_s=z_rate_sigma,
        noise_sigma_m=lim.noise_sigma_m,
    )
    if not inside:
        return answer
    chosen, inside_ambiguity = assess_offset(inside, lim)
    # The data outside the prior may still rule its answer out.
    gap = cost_gap(best, chosen, ambiguity.cost_sigma_m, lim.huber_k)
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
    answer = ClockSolution(
        dive=chosen.dive,
        sync=chosen.sync,
        ambiguity=inside_ambiguity,
        search_ambiguity=ambiguity,
        prior=prior,
        prior_used=True,
        prior_distance_s=distance(chosen.sync.time_offset_s),
        candidates=inside_coarse[chosen.dive],
    )
    return _with_near(
        answer, traj_t, traj_z, arrays, search, fit, z_rate_sigma, lim, chosen, inside
    )


def _with_near(
    answer: ClockSolution,
    traj_t: FloatArray,
    traj_z: FloatArray,
    dives: list[tuple[FloatArray, FloatArray]],
    search: dict[str, float],
    fit: dict[str, float | bool],
    z_rate_sigma_m_per_s: float | None,
    lim: AmbiguityLimits,
    best: Solution,
    solutions: list[Solution],
) -> ClockSolution:
    """The answer with its near alternative (`near_alternative`) in its ambiguity.

    A near fit better than the answer (on the samples both use) takes its place,
    assessed against the same solutions, and the old answer becomes its near
    alternative.
    """
    dive_t, depth = dives[answer.dive]
    context = _FitContext(
        index=answer.dive,
        traj_t=traj_t,
        traj_z=traj_z,
        dive_t=dive_t,
        depth=depth,
        max_gap_s=search["max_gap_s"],
        noise_sigma_m=lim.noise_sigma_m,
        z_rate_sigma_m_per_s=z_rate_sigma_m_per_s,
        fit=fit,
        prior=answer.prior if answer.prior_used else None,
    )
    near = near_alternative(
        context,
        best,
        min_separation_s=lim.min_separation_s,
        cost_sigma_m=answer.ambiguity.cost_sigma_m,
    )
    ambiguity = answer.ambiguity
    if near is not None and near[1] < 0.0:
        rebest, reassessed = assess_offset([near[0], *solutions], lim)
        if rebest is near[0]:
            best, ambiguity = rebest, reassessed
            near = near_alternative(
                context,
                best,
                min_separation_s=lim.min_separation_s,
                cost_sigma_m=ambiguity.cost_sigma_m,
            )
    if near is not None:
        ambiguity = dataclasses.replace(
            ambiguity,
            near_offset_s=near[0].sync.time_offset_s,
            near_evidence=near[1],
            near_depth_offset_m=near[0].sync.depth_offset_m,
        )
    offset_s = best.sync.time_offset_s
    return dataclasses.replace(
        answer,
        sync=best.sync,
        ambiguity=ambiguity,
        search_ambiguity=answer.search_ambiguity if answer.prior_used else ambiguity,
        prior_distance_s=None if answer.prior is None else float(answer.prior.distance_s(offset_s)),
    )
