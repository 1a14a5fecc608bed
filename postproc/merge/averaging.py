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
"""

from __future__ import annotations

from dataclasses import dataclass
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
    return rotations[index]


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
