"""Robust averaging of rigid poses, with the covariance of the result.

Pure math: no I/O, no logging.

Error convention (used by every covariance in this package): a pose
`T = (R, t)` near an estimate `(R̄, t̄)` is written

    R = Exp(δθ) R̄,   t = t̄ + δt,

with `δθ` a rotation vector in the *parent* frame (radians) and `δt` a
translation in the parent frame (metres). A 6x6 covariance is that of
`[δθ, δt]`: rotation first, radians and metres.

`robust_pose_mean` averages many noisy observations of one pose (the target
seen from many keyframes): rotations by the chordal L2 mean or the quaternion
eigenvector mean (never Euler angles), translations by a weighted mean, both
on an inlier set chosen by a robust rule (median/MAD of the residual norms, or
a chi-square test on the 6-D residuals with a robust covariance). It starts
from a high-breakdown estimate (the rotation medoid and the coordinate-wise
median), so up to half of the observations may be outliers.

`fuse_pose_estimates` combines a few independent estimates of one pose that
each carry a covariance (information-weighted, Gauss-Newton on SE(3)).

`drift_weighted_mean` re-weighs the inliers of one session by generalised
least squares when the session's SLAM drifts as a random walk from where it
defines its frame (`DriftModel`, fitted by `estimate_drift_model` from the
scatter inside passes and the differences between passes): later passes
repeat the drift of earlier ones, so the mean leans on the earliest, and its
covariance includes the drift. The model is itself estimated from a few pairs
of passes, so a covariance computed as if it were exact is too small;
`calibrate_drift_model` measures by how much (a parametric bootstrap of the
session's own sightings) and the model carries that factor.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from shared.geometry import (
    make_pose,
    rotation_mean_chordal,
    rotation_mean_quaternion,
    so3_exp,
    so3_log,
)

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

RotationMean = Literal["chordal", "quaternion"]
OutlierRule = Literal["mad", "chi2"]

#: MAD of a normal sample times this is its standard deviation.
MAD_TO_SIGMA = 1.4826
#: chi-square quantiles with 6 degrees of freedom (probability -> threshold).
_CHI2_6DOF = {0.99: 16.812, 0.995: 18.548, 0.999: 22.458, 0.9999: 27.856}
#: E[log X] for X chi-square with one degree of freedom (digamma(1/2) + log 2).
_MEAN_LOG_CHI2_1 = -1.2703628454614782


@dataclass(frozen=True)
class PoseAverage:
    """The robust mean of N pose observations.

    pose: the mean `T_A_B` (4, 4), metres.
    covariance: (6, 6) covariance of the *mean* (rotation first, rad and m; see the module).
    spread_covariance: (6, 6) covariance of one inlier observation about the mean.
    inliers: (N,) True for the observations used.
    residuals: (N, 6) `[δθ, δt]` of every observation about the mean (rad, m).
    """

    pose: FloatArray
    covariance: FloatArray
    spread_covariance: FloatArray
    inliers: BoolArray
    residuals: FloatArray

    @property
    def inlier_count(self) -> int:
        """Number of observations used."""
        return int(np.count_nonzero(self.inliers))


def _as_poses(poses: npt.ArrayLike, what: str) -> FloatArray:
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim != 3 or array.shape[1:] != (4, 4) or array.shape[0] == 0:
        raise ValueError(f"{what}: expected (N, 4, 4) poses with N >= 1, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what}: poses contain non-finite values")
    return array


def pose_residuals(poses: npt.ArrayLike, mean: npt.ArrayLike) -> FloatArray:
    """(N, 6) residuals `[δθ, δt]` of poses (N, 4, 4) about `mean` (4, 4): R_i = Exp(δθ_i) R̄."""
    T = _as_poses(poses, "pose_residuals")
    M = np.asarray(mean, dtype=np.float64)
    rotation = so3_log(T[:, :3, :3] @ M[:3, :3].T)
    translation = T[:, :3, 3] - M[:3, 3]
    return np.concatenate((rotation.reshape(-1, 3), translation), axis=1)


def _rotation_medoid(rotations: FloatArray) -> FloatArray:
    """The observed rotation with the smallest summed chordal distance to all others."""
    flat = rotations.reshape(len(rotations), 9)
    # ||R_i - R_j||_F^2 = 6 - 2 trace(R_i^T R_j) and trace(R_i^T R_j) = <R_i, R_j>.
    traces = flat @ flat.T
    index = int(np.argmin(np.sum(6.0 - 2.0 * traces, axis=1)))
    medoid: FloatArray = rotations[index]
    return medoid


def _mean_rotation(rotations: FloatArray, weights: FloatArray, method: RotationMean) -> FloatArray:
    if method == "chordal":
        return rotation_mean_chordal(rotations, weights)
    return rotation_mean_quaternion(rotations, weights)


def _robust_z(values: FloatArray, floor: float) -> FloatArray:
    """(x - median) / (1.4826 MAD), one-sided (only large values count), MAD floored."""
    median = float(np.median(values))
    mad = float(np.median(np.abs(values - median)))
    scale = max(MAD_TO_SIGMA * mad, floor)
    return (values - median) / scale


def robust_pose_mean(
    poses: npt.ArrayLike,
    *,
    weights: npt.ArrayLike | None = None,
    rotation_mean: RotationMean = "chordal",
    outlier_rule: OutlierRule = "mad",
    mad_threshold: float = 3.5,
    chi2_probability: float = 0.999,
    min_rotation_sigma_rad: float = 1e-3,
    min_translation_sigma_m: float = 1e-3,
    prior_rotation_sigma_rad: float = np.deg2rad(1.0),
    prior_translation_sigma_m: float = 0.02,
    max_iterations: int = 20,
) -> PoseAverage:
    """Robust mean of pose observations (N, 4, 4) of one rigid pose, with its covariance.

    weights: relative weights (N,) (e.g. corner counts), None for equal.
    rotation_mean: "chordal" (projection of the weighted sum onto SO(3)) or
        "quaternion" (eigenvector of sum w q q^T, Markley 2007).
    outlier_rule: "mad" rejects an observation whose rotation angle or
        translation distance from the mean is more than `mad_threshold` robust
        sigmas (median + k * 1.4826 MAD) above the median; "chi2" rejects one
        whose 6-D residual has a squared Mahalanobis distance, under a robust
        covariance of the inliers, beyond the `chi2_probability` quantile of
        chi-square with 6 degrees of freedom.
    min_*_sigma: floor on the robust scales, so near-identical observations
        (noise-free data) do not reject each other over rounding.
    prior_*_sigma: the spread assumed for one observation before the data are
        seen; the spread reported shrinks toward it with the weight of two
        observations, so a mean from 1-3 observations still has a sane covariance.

    The covariance of the mean is the weighted inlier spread divided by the
    effective sample size. Observations from consecutive keyframes share SLAM
    drift, so this is a lower bound when they are correlated.
    Raises ValueError for malformed input or options.
    """
    T = _as_poses(poses, "robust_pose_mean")
    n = T.shape[0]
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
        raise ValueError(f"robust_pose_mean: weights must be ({n},) finite, >= 0, not all zero")
    if rotation_mean not in ("chordal", "quaternion"):
        raise ValueError(f"robust_pose_mean: unknown rotation_mean {rotation_mean!r}")
    if outlier_rule not in ("mad", "chi2"):
        raise ValueError(f"robust_pose_mean: unknown outlier_rule {outlier_rule!r}")
    if outlier_rule == "chi2" and chi2_probability not in _CHI2_6DOF:
        raise ValueError(
            f"robust_pose_mean: chi2_probability must be one of {sorted(_CHI2_6DOF)}, "
            f"got {chi2_probability}"
        )
    if not mad_threshold > 0:
        raise ValueError(f"robust_pose_mean: mad_threshold must be positive, got {mad_threshold}")

    rotations = T[:, :3, :3]
    translations = T[:, :3, 3]
    # High-breakdown start: the medoid rotation and the coordinate-wise median position.
    mean = make_pose(_rotation_medoid(rotations), np.median(translations, axis=0))
    inliers = np.ones(n, dtype=bool)
    for _ in range(max_iterations):
        residuals = pose_residuals(T, mean)
        if outlier_rule == "mad":
            angle = np.linalg.norm(residuals[:, :3], axis=1)
            distance = np.linalg.norm(residuals[:, 3:], axis=1)
            z_rot = _robust_z(angle, min_rotation_sigma_rad)
            z_trans = _robust_z(distance, min_translation_sigma_m)
            new_inliers = (z_rot <= mad_threshold) & (z_trans <= mad_threshold)
        else:
            new_inliers = _chi2_inliers(
                residuals,
                inliers,
                _CHI2_6DOF[chi2_probability],
                min_rotation_sigma_rad,
                min_translation_sigma_m,
            )
        new_inliers &= w > 0
        if np.count_nonzero(new_inliers) == 0:
            # Degenerate (every residual equal to the floor): keep what we had.
            new_inliers = inliers & (w > 0)
        wi = w[new_inliers]
        new_mean = make_pose(
            _mean_rotation(rotations[new_inliers], wi, rotation_mean),
            np.average(translations[new_inliers], axis=0, weights=wi),
        )
        converged = np.array_equal(new_inliers, inliers) and np.allclose(new_mean, mean, atol=1e-12)
        inliers, mean = new_inliers, new_mean
        if converged:
            break

    residuals = pose_residuals(T, mean)
    wi = w[inliers]
    r = residuals[inliers]
    n_eff = float(wi.sum() ** 2 / np.sum(wi**2))
    prior = np.diag([prior_rotation_sigma_rad**2] * 3 + [prior_translation_sigma_m**2] * 3)
    if r.shape[0] >= 2:
        sample = np.einsum("n,ni,nj->ij", wi, r, r) / wi.sum() * n_eff / (n_eff - 1.0)
        # Shrink toward the prior with the weight of two observations.
        spread = ((n_eff - 1.0) * sample + 2.0 * prior) / (n_eff + 1.0)
    else:
        spread = prior
    spread = 0.5 * (spread + spread.T)
    return PoseAverage(
        pose=mean,
        covariance=spread / n_eff,
        spread_covariance=spread,
        inliers=inliers,
        residuals=residuals,
    )


def _chi2_inliers(
    residuals: FloatArray,
    inliers: BoolArray,
    threshold: float,
    min_rotation_sigma_rad: float,
    min_translation_sigma_m: float,
) -> BoolArray:
    """Inliers by squared Mahalanobis distance under a robust (MAD-scaled) covariance."""
    r = residuals[inliers] if np.count_nonzero(inliers) >= 7 else residuals
    # Robust per-axis scales, then the correlation of the central half of the data.
    sigma = MAD_TO_SIGMA * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    floor = np.array([min_rotation_sigma_rad] * 3 + [min_translation_sigma_m] * 3)
    sigma = np.maximum(sigma, floor)
    scaled = r / sigma
    central = scaled[np.sum(scaled**2, axis=1) <= np.median(np.sum(scaled**2, axis=1))]
    if central.shape[0] >= 7:
        correlation = np.corrcoef(central, rowvar=False)
        if not np.all(np.isfinite(correlation)):
            correlation = np.eye(6)
    else:
        correlation = np.eye(6)
    # Keep the matrix well conditioned (a correlation of +-1 from few samples).
    correlation = 0.9 * correlation + 0.1 * np.eye(6)
    covariance = correlation * np.outer(sigma, sigma)
    information = np.linalg.inv(covariance)
    d2 = np.einsum("ni,ij,nj->n", residuals, information, residuals)
    result: BoolArray = d2 <= threshold
    return result


def fuse_pose_estimates(
    poses: npt.ArrayLike, covariances: npt.ArrayLike, *, max_iterations: int = 20
) -> tuple[FloatArray, FloatArray]:
    """Information-weighted mean of independent estimates (N, 4, 4) of one pose.

    covariances: (N, 6, 6), the module's convention (rotation first, rad and m).
    Returns (pose (4, 4), covariance (6, 6)) minimising sum r_i^T Σ_i^-1 r_i by
    Gauss-Newton on SE(3). Raises ValueError for a covariance that is not
    symmetric positive definite.
    """
    T = _as_poses(poses, "fuse_pose_estimates")
    S = np.asarray(covariances, dtype=np.float64)
    if S.shape != (T.shape[0], 6, 6):
        raise ValueError(f"fuse_pose_estimates: expected ({T.shape[0]}, 6, 6) covariances")
    information = []
    for i, cov in enumerate(S):
        try:
            np.linalg.cholesky(0.5 * (cov + cov.T))
        except np.linalg.LinAlgError:
            raise ValueError(
                f"fuse_pose_estimates: covariance {i} is not positive definite"
            ) from None
        information.append(np.linalg.inv(0.5 * (cov + cov.T)))
    info = np.array(information)
    total_information = info.sum(axis=0)
    fused_covariance = np.linalg.inv(total_information)
    # Start from the estimate with the most information (largest det).
    start = int(np.argmax([np.linalg.slogdet(i)[1] for i in info]))
    mean = T[start].copy()
    for _ in range(max_iterations):
        r = pose_residuals(T, mean)
        step = fused_covariance @ np.einsum("nij,nj->i", info, r)
        mean = make_pose(so3_exp(step[:3]) @ mean[:3, :3], mean[:3, 3] + step[3:])
        if np.linalg.norm(step) < 1e-12:
            break
    fused_covariance = 0.5 * (fused_covariance + fused_covariance.T)
    return mean, fused_covariance


def clustered_covariance(
    average: PoseAverage,
    cluster_ids: npt.ArrayLike,
    *,
    weights: npt.ArrayLike | None = None,
    prior_rotation_sigma_rad: float = np.deg2rad(0.2),
    prior_translation_sigma_m: float = 0.02,
) -> FloatArray:
    """Covariance (6, 6) of the mean when observations come in correlated clusters.

    Keyframes of one pass past a target share that pass's SLAM drift, so they
    are not independent: the mean is only as good as the number of passes.
    `cluster_ids` (N,) labels each observation's pass. The covariance of the
    mean is the scatter of the inlier cluster means divided by the number of
    clusters, shrunk toward a prior drift spread (the weight of two clusters),
    and never less than `average.covariance` (the independent-observation one).
    """
    labels = np.asarray(cluster_ids).reshape(-1)
    if labels.shape[0] != average.inliers.shape[0]:
        raise ValueError(
            f"clustered_covariance: {labels.shape[0]} cluster ids for "
            f"{average.inliers.shape[0]} observations"
        )
    w = (
        np.ones(labels.shape[0])
        if weights is None
        else np.asarray(weights, dtype=np.float64).reshape(-1)
    )
    means = []
    for label in np.unique(labels[average.inliers]):
        chosen = average.inliers & (labels == label)
        means.append(np.average(average.residuals[chosen], axis=0, weights=w[chosen]))
    cluster_means = np.array(means)
    n = cluster_means.shape[0]
    prior = np.diag([prior_rotation_sigma_rad**2] * 3 + [prior_translation_sigma_m**2] * 3)
    if n >= 2:
        centred = cluster_means - cluster_means.mean(axis=0)
        sample = centred.T @ centred / (n - 1)
        spread = ((n - 1) * sample + 2.0 * prior) / (n + 1)
    else:
        spread = prior
    clustered = spread / n
    result: FloatArray = (
        clustered if np.trace(clustered) > np.trace(average.covariance) else average.covariance
    )
    return 0.5 * (result + result.T)


@dataclass(frozen=True)
class DriftModel:
    """Per-axis noise of pose observations taken from a drifting SLAM session.

    An observation of a fixed pose at time τ (s since the session's anchor, where
    the SLAM frame is defined) is `x + d(τ) + e`: `d` a random walk with
    `drift_rate` (6,) variance per second (rad²/s, m²/s) starting at 0 at τ = 0,
    `e` independent per observation with `noise` (6,) variance (rad², m²).
    pass_pairs: how many pairs of consecutive passes the drift rate was measured
    on (0: the rate is the prior).
    calibration: (6,) per axis, how much larger the variance of an estimate built on
    this model is than the model alone says, because the model was fitted from the
    same few passes (`calibrate_drift_model`; ones: taken as exact).
    `drift_weighted_mean` multiplies its variance by it, and `scaled_rates` gives
    the drift rates with it, for covariances built elsewhere from the same model.
    """

    drift_rate: FloatArray
    noise: FloatArray
    pass_pairs: int = 0
    calibration: FloatArray = field(default_factory=lambda: np.ones(6))

    @property
    def scaled_rates(self) -> FloatArray:
        """The drift rates (6,) times `calibration`."""
        return np.asarray(self.drift_rate * self.calibration, dtype=np.float64)

    @property
    def scaled_noise(self) -> FloatArray:
        """The per-observation noise (6,) times `calibration`."""
        return np.asarray(self.noise * self.calibration, dtype=np.float64)


def estimate_drift_model(
    residuals: Sequence[FloatArray],
    times_s: Sequence[FloatArray],
    pass_ids: Sequence[npt.ArrayLike],
    *,
    prior_rate_rotation_rad2_per_s: float,
    prior_rate_translation_m2_per_s: float,
    prior_rate_tilt_rad2_per_s: float | None = None,
    prior_weight_pairs: float = 2.0,
    min_rotation_sigma_rad: float = 2e-4,
    min_translation_sigma_m: float = 2e-4,
) -> DriftModel:
    """Noise and drift rate of one session from its targets' inlier residuals.

    residuals: per target, (N, 6) inlier residuals about that target's mean.
    times_s: per target, (N,) seconds since the session anchor. pass_ids: per
    target, (N,) pass labels (a pass: keyframes close in time).
    Noise `s²` and rate `q` per axis solve two moment equations pooled over
    targets: the scatter inside passes and the differences of consecutive pass
    means (both exact for the model, see the code); the rate is then shrunk
    toward the prior with the weight of `prior_weight_pairs` pairs. With no
    pair of passes the rate is the prior. prior_rate_tilt_rad2_per_s: the prior of
    the first two rotation axes (roll and pitch in a gravity-aligned session frame)
    where it differs from the rotation's: a visual-inertial SLAM sees gravity, so its
    roll and pitch stay bounded instead of drifting (0); None: as the rotation's.
    Raises ValueError for mismatched lengths.
    """
    if not len(residuals) == len(times_s) == len(pass_ids):
        raise ValueError("estimate_drift_model: residuals, times and pass ids differ in length")
    floor = np.array([min_rotation_sigma_rad**2] * 3 + [min_translation_sigma_m**2] * 3)
    prior = np.array([prior_rate_rotation_rad2_per_s] * 3 + [prior_rate_translation_m2_per_s] * 3)
    if prior_rate_tilt_rad2_per_s is not None:
        prior[:2] = prior_rate_tilt_rad2_per_s
    # Moment equations per axis, exact for the random walk plus noise:
    #   inside passes: E[sum (r - pass mean)²] = (n - 1) s² + q c,
    #     c = sum τ - mean over (i, j) of min(τi, τj) (the drift inside the pass);
    #   consecutive passes: E[(m2 - m1)²] = s² (1/n1 + 1/n2) + q (S1 + S2 - 2 τ̄1),
    #     S = mean over (i, j) of min(τi, τj) within a pass.
    within_ss = np.zeros(6)
    within_dof = 0.0
    within_drift = 0.0
    between_ss = np.zeros(6)
    between_noise = 0.0
    between_drift = 0.0
    pairs = 0
    for r, t, p in zip(residuals, times_s, pass_ids, strict=True):
        r = np.asarray(r, dtype=np.float64).reshape(-1, 6)
        t = np.maximum(np.asarray(t, dtype=np.float64).reshape(-1), 0.0)
        labels = np.asarray(p).reshape(-1)
        if not r.shape[0] == t.shape[0] == labels.shape[0]:
            raise ValueError("estimate_drift_model: residuals, times and pass ids differ in length")
        target_passes = []
        for label in np.unique(labels):
            chosen = labels == label
            n = int(np.count_nonzero(chosen))
            mean = r[chosen].mean(axis=0)
            shared = float(np.mean(np.minimum.outer(t[chosen], t[chosen])))
            within_ss += np.sum((r[chosen] - mean) ** 2, axis=0)
            within_dof += n - 1
            within_drift += float(np.sum(t[chosen])) - n * shared
            target_passes.append((float(t[chosen].mean()), n, mean, shared))
        target_passes.sort(key=lambda x: x[0])
        for (t1, n1, m1, s1), (_, n2, m2, s2) in itertools.pairwise(target_passes):
            between_ss += (m2 - m1) ** 2
            between_noise += 1.0 / n1 + 1.0 / n2
            between_drift += s1 + s2 - 2.0 * t1
            pairs += 1
    if pairs and between_drift > 0 and within_dof > 0:
        system = np.array([[within_dof, within_drift], [between_noise, between_drift]])
        try:
            solved = np.linalg.solve(system, np.vstack((within_ss, between_ss)))
            noise, measured = solved[0], np.maximum(solved[1], 0.0)
        except np.linalg.LinAlgError:
            noise, measured = within_ss / within_dof, prior
        if np.any(noise < floor):
            # The data put (almost) everything into drift: keep the noise at its floor
            # and let the passes' differences give the rate.
            noise = np.maximum(noise, floor)
            measured = np.maximum((between_ss - between_noise * noise) / between_drift, 0.0)
        rate = (pairs * measured + prior_weight_pairs * prior) / (pairs + prior_weight_pairs)
    else:
        rate = prior
        noise = (
            np.maximum((within_ss - within_drift * prior) / within_dof, floor)
            if within_dof > 0
            else floor * 25.0
        )
    return DriftModel(drift_rate=rate, noise=noise, pass_pairs=pairs)


def local_frame_variance(model: DriftModel, target_times_s: npt.ArrayLike) -> FloatArray:
    """Per target, the variance (M, 6) of its local map frame about the session's mean frame.

    Where a drifting session filmed target m (at `target_times_s[m]`, s since the
    anchor) its map sits in a frame moved by the random walk `d(τ_m)`; one rigid
    transform can overlay the session's maps only up to how those frames differ.
    About their mean over the M targets, target m's frame is off by
    `d(τ_m) - mean_j d(τ_j)`, of variance per axis
    `q (τ_m - 2/M Σ_j min(τ_m, τ_j) + 1/M² Σ_ij min(τ_i, τ_j))` (`model.drift_rate`
    q). Adding it to each target's covariance weighs targets for the overlay, not for
    the anchored frame. Negative times count as 0. Raises ValueError for no target.
    """
    tau = np.maximum(np.asarray(target_times_s, dtype=np.float64).reshape(-1), 0.0)
    if tau.shape[0] == 0:
        raise ValueError("local_frame_variance: no target time")
    shared = np.minimum.outer(tau, tau)
    m = tau.shape[0]
    scale = tau - 2.0 / m * shared.sum(axis=1) + shared.sum() / m**2
    return np.asarray(np.outer(np.maximum(scale, 0.0), model.drift_rate), dtype=np.float64)


def drift_weights(
    times_s: npt.ArrayLike,
    model: DriftModel,
    *,
    observation_variance: npt.ArrayLike | None = None,
) -> FloatArray:
    """The weights (N, 6) `drift_weighted_mean` gives its N observations, per axis.

    Each column sums to 1: the mean's error is `Σ_i w_i (d(τ_i) + e_i)`, which tells
    how much of which moments of the session's drift it carries (`joint.DriftShare`).
    """
    tau = np.maximum(np.asarray(times_s, dtype=np.float64).reshape(-1), 0.0)
    n = tau.shape[0]
    extra = (
        np.zeros((n, 6))
        if observation_variance is None
        else np.asarray(observation_variance, dtype=np.float64).reshape(n, 6)
    )
    sigma = _gls_covariances(np.minimum.outer(tau, tau), model.drift_rate, model.noise + extra)
    solved = np.linalg.solve(sigma, np.ones((6, n, 1)))[:, :, 0]
    return np.asarray((solved / solved.sum(axis=1, keepdims=True)).T, dtype=np.float64)


def drift_weighted_mean(
    poses: npt.ArrayLike,
    times_s: npt.ArrayLike,
    model: DriftModel,
    *,
    start: npt.ArrayLike,
    observation_variance: npt.ArrayLike | None = None,
    iterations: int = 2,
) -> tuple[FloatArray, FloatArray]:
    """Generalised least-squares mean of pose observations (N, 4, 4) from a drifting session.

    Per axis the observations' covariance is `q min(τ_i, τ_j) + s_i δ_ij` (a
    random walk from the anchor plus independent noise, `DriftModel`): a later
    pass repeats the drift of an earlier one and adds its own, so it carries
    less information about the pose in the anchored session frame, and the
    result leans on the earliest observations. times_s: (N,) seconds since the
    anchor (negative values count as 0). observation_variance: (N, 6) extra
    per-observation variance (e.g. the PnP covariance's diagonal in the
    session frame), added to `model.noise`. start: (4, 4) the linearisation
    point (the robust mean). Returns (pose (4, 4), covariance (6, 6),
    diagonal: the axes are treated as independent; drift included, times
    `model.calibration`).
    """
    T = _as_poses(poses, "drift_weighted_mean")
    n = T.shape[0]
    tau = np.maximum(np.asarray(times_s, dtype=np.float64).reshape(-1), 0.0)
    if tau.shape != (n,):
        raise ValueError(f"drift_weighted_mean: expected ({n},) times, got {tau.shape}")
    extra = (
        np.zeros((n, 6))
        if observation_variance is None
        else np.asarray(observation_variance, dtype=np.float64).reshape(n, 6)
    )
    shared = np.minimum.outer(tau, tau)
    mean = np.asarray(start, dtype=np.float64).copy()
    variance = np.zeros(6)
    for _ in range(max(iterations, 1)):
        r = pose_residuals(T, mean)
        step, variance = _gls_mean_and_variance(r, shared, model.drift_rate, model.noise + extra)
        mean = make_pose(so3_exp(step[:3]) @ mean[:3, :3], mean[:3, 3] + step[3:])
    return mean, np.diag(variance * model.calibration)


def drift_inliers(
    poses: npt.ArrayLike,
    times_s: npt.ArrayLike,
    model: DriftModel,
    *,
    start: npt.ArrayLike,
    inliers: npt.ArrayLike,
    observation_variance: npt.ArrayLike | None = None,
    chi2_probability: float = 0.999,
) -> BoolArray:
    """Which of the pose observations (N, 4, 4) of one target the drift model explains.

    A robust mean's outlier rule measures each observation against one mean, so in a
    drifting session it cuts the passes furthest from it (the walk's tails) along with
    the gross errors; the drift model fitted from what is left then has too small a
    rate. Here each observation is predicted from the current `inliers` (N,) by the
    model (per axis the covariance `q min(τi, τj) + s_i δ_ij` with an unknown mean, as
    in `drift_weighted_mean`): an inlier from the others (leave one out), any other one
    from all of them. Its squared residual over the prediction's variance, summed over
    the six axes, beyond the chi-square quantile of `chi2_probability` (6 degrees of
    freedom) marks it an outlier. A sighting in a drifted pass is predicted from its
    own pass's neighbours and stays; a gross error does not. start: (4, 4) the
    linearisation point (the robust mean). times_s, observation_variance: as in
    `drift_weighted_mean`. Returns the new inliers (N,); `inliers` unchanged with fewer
    than two given, or when the model explains none of them (it does not describe this
    target: nothing to choose by). Raises ValueError for malformed input.
    """
    T = _as_poses(poses, "drift_inliers")
    n = T.shape[0]
    tau = np.maximum(np.asarray(times_s, dtype=np.float64).reshape(-1), 0.0)
    kept = np.asarray(inliers, dtype=bool).reshape(-1)
    if tau.shape != (n,) or kept.shape != (n,):
        raise ValueError(f"drift_inliers: expected ({n},) times and inliers")
    if chi2_probability not in _CHI2_6DOF:
        raise ValueError(
            f"drift_inliers: chi2_probability must be one of {sorted(_CHI2_6DOF)}, "
            f"got {chi2_probability}"
        )
    if np.count_nonzero(kept) < 2:
        return kept.copy()
    extra = (
        np.zeros((n, 6))
        if observation_variance is None
        else np.asarray(observation_variance, dtype=np.float64).reshape(n, 6)
    )
    d2 = _prediction_distances(pose_residuals(T, start), tau, kept, model, extra)
    result: BoolArray = d2 <= _CHI2_6DOF[chi2_probability]
    return result if np.any(result) else kept.copy()


def _prediction_distances(
    values: FloatArray, tau: FloatArray, kept: BoolArray, model: DriftModel, extra: FloatArray
) -> FloatArray:
    """Per observation (N,) the squared residual (`values` (N, 6)) about its prediction
    from the `kept` ones over the prediction's variance, summed over the axes
    (`drift_inliers`)."""
    n = values.shape[0]
    shared = np.minimum.outer(tau, tau)
    inside = np.flatnonzero(kept)
    outside = np.flatnonzero(~kept)
    # Per axis: K over the inliers, its inverse, and the inverse projected off the mean
    # (P = K⁻¹ - K⁻¹ 1 1ᵀ K⁻¹ / 1ᵀ K⁻¹ 1): leave-one-out residuals are (P y)_i / P_ii
    # with variance 1 / P_ii.
    sigma = _gls_covariances(
        shared[np.ix_(inside, inside)], model.drift_rate, model.noise + extra[inside]
    )
    inverse = np.linalg.inv(sigma)
    row = inverse.sum(axis=2)
    information = row.sum(axis=1)
    projected = inverse - row[:, :, None] * row[:, None, :] / information[:, None, None]
    y = values[inside].T
    leave_one_out = np.einsum("kij,kj->ki", projected, y)
    diagonal = np.diagonal(projected, axis1=1, axis2=2)
    d2 = np.zeros(n)
    d2[inside] = np.sum(leave_one_out**2 / diagonal, axis=0)
    if outside.size:
        # Universal kriging of the others from the inliers: the GLS mean plus the walk's
        # pull toward the inliers, with the mean's own variance in the prediction's.
        mean = np.einsum("ki,ki->k", row, y) / information
        cross = model.drift_rate[:, None, None] * shared[np.ix_(outside, inside)][None]
        gain = np.einsum("koi,kij->koj", cross, inverse)
        predicted = mean[:, None] + np.einsum("koj,kj->ko", gain, y - mean[:, None])
        own = model.drift_rate[:, None] * tau[outside][None] + (model.noise + extra[outside]).T
        explained = np.einsum("koj,koj->ko", gain, cross)
        unexplained = 1.0 - gain.sum(axis=2)
        variance = own - explained + unexplained**2 / information[:, None]
        d2[outside] = np.sum((values[outside].T - predicted) ** 2 / variance, axis=0)
    return d2


def _gls_covariances(shared: FloatArray, rates: FloatArray, noise: FloatArray) -> FloatArray:
    """Per axis the observations' covariance (6, N, N) `rates[k] min(τi, τj) +
    diag(noise[:, k])` (`shared` (N, N) the min(τi, τj), `noise` (N, 6))."""
    n = shared.shape[0]
    covariances: FloatArray = (
        rates[:, None, None] * shared[None] + noise.T[:, :, None] * np.eye(n)[None]
    )
    return covariances


def _gls_mean_and_variance(
    values: FloatArray, shared: FloatArray, rates: FloatArray, noise: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per axis the GLS mean (6,) of `values` (N, 6) and its variance (6,), the
    observations' covariance on axis k `rates[k] min(τi, τj) + diag(noise[:, k])`
    (`shared` (N, N) the min(τi, τj), `noise` (N, 6))."""
    n = values.shape[0]
    sigma = _gls_covariances(shared, rates, noise)
    rhs = np.stack((np.ones((6, n)), values.T), axis=2)
    solved = np.linalg.solve(sigma, rhs)
    information = solved[:, :, 0].sum(axis=1)
    return solved[:, :, 1].sum(axis=1) / information, 1.0 / information


def _thinned(times_s: FloatArray, most: int) -> npt.NDArray[np.int64]:
    """Indices of at most `most` of `times_s`: all of them in their order when there are
    no more, else spread evenly over their time order."""
    n = times_s.shape[0]
    if n <= most:
        return np.arange(n)
    order = np.argsort(times_s, kind="stable")
    picks = np.unique(np.linspace(0, n - 1, max(most, 1)).round().astype(np.int64))
    return np.asarray(order[picks], dtype=np.int64)


def calibrate_drift_model(
    model: DriftModel,
    times_s: Sequence[FloatArray],
    pass_ids: Sequence[npt.ArrayLike],
    refit: Callable[
        [Sequence[FloatArray], Sequence[FloatArray], Sequence[npt.ArrayLike]], DriftModel
    ],
    *,
    observation_variance: Sequence[FloatArray] | None = None,
    draws: int = 200,
    seed: int = 0,
    max_sightings: int = 120,
) -> DriftModel:
    """`model` with its `calibration`: a parametric bootstrap of the session's sightings.

    The drift rate comes from a few pairs of passes, so it is often well off; the
    variance `drift_weighted_mean` reports with a rate that came out low is too small,
    and its squared error over the reported variance is then larger than 1 on average
    (two targets in three passes each, a model exactly like the data's: 1.14-1.24;
    calibrated 1.02-1.12, as the bootstrap runs at the fitted, not the true, rate;
    `tests/postproc/merge/test_averaging.py`). `draws` times: one random walk of
    `model` shared by the session's targets plus each observation's noise, at the same
    times (`times_s`, per target (N,) s since the anchor) and passes (`pass_ids`);
    `refit` (the caller's `estimate_drift_model` with its priors) fits a model to their
    residuals, and each target's drift-weighted mean with that model is compared with
    the truth (zero). The calibration per axis is the squared error over the reported
    variance, as a geometric mean against that of a chi-square with one degree of
    freedom: with one or two pairs of passes a refit rate near zero now and then makes
    the plain mean of the ratio explode (23x on a 2-pair session of `test_stage.py`,
    whose errors were a tenth of the sigma that gave), and the geometric mean is not
    moved by them (2.6x there, and the same as the plain mean with four pairs). Never
    below 1 (below is sampling noise: a model fitted from the data cannot know more
    than the exact one). observation_variance: per target (N, 6) as in
    `drift_weighted_mean`. max_sightings: a target seen more often is thinned to this
    many sightings, evenly in time order, for the bootstrap (each draw solves an N x N
    system per axis: a target hovered over for minutes would otherwise cost minutes;
    thinning inside passes leaves the pass structure, which sets the factor).
    Deterministic for a `seed`. Raises ValueError for mismatched lengths or no target.
    """
    if not times_s or len(times_s) != len(pass_ids):
        raise ValueError("calibrate_drift_model: times and pass ids differ in length or are empty")
    taus = [np.maximum(np.asarray(t, dtype=np.float64).reshape(-1), 0.0) for t in times_s]
    extras = (
        [np.zeros((t.shape[0], 6)) for t in taus]
        if observation_variance is None
        else [np.asarray(v, dtype=np.float64).reshape(-1, 6) for v in observation_variance]
    )
    if any(e.shape[0] != t.shape[0] for e, t in zip(extras, taus, strict=True)):
        raise ValueError("calibrate_drift_model: observation variances and times differ in length")
    labels = [np.asarray(p).reshape(-1) for p in pass_ids]
    if any(label.shape[0] != t.shape[0] for label, t in zip(labels, taus, strict=True)):
        raise ValueError("calibrate_drift_model: pass ids and times differ in length")
    kept = [_thinned(t, max_sightings) for t in taus]
    taus = [t[k] for t, k in zip(taus, kept, strict=True)]
    extras = [e[k] for e, k in zip(extras, kept, strict=True)]
    labels = [label[k] for label, k in zip(labels, kept, strict=True)]
    every = np.unique(np.concatenate(taus))
    steps = np.diff(every, prepend=0.0)
    where = [np.searchsorted(every, t) for t in taus]
    shared = [np.minimum.outer(t, t) for t in taus]
    rng = np.random.default_rng(seed)
    logs = np.zeros(6)
    count = 0
    for _ in range(max(draws, 1)):
        walk = np.cumsum(
            rng.normal(size=(every.shape[0], 6)) * np.sqrt(steps[:, None] * model.drift_rate),
            axis=0,
        )
        observed = [
            walk[w] + rng.normal(size=(w.shape[0], 6)) * np.sqrt(model.noise + e)
            for w, e in zip(where, extras, strict=True)
        ]
        fitted = refit([o - o.mean(axis=0) for o in observed], taus, labels)
        for o, m, e in zip(observed, shared, extras, strict=True):
            mean, variance = _gls_mean_and_variance(o, m, fitted.drift_rate, fitted.noise + e)
            logs += np.log(np.maximum(mean**2 / variance, 1e-300))
        count += len(observed)
    return replace(model, calibration=np.maximum(np.exp(logs / count - _MEAN_LOG_CHI2_1), 1.0))
