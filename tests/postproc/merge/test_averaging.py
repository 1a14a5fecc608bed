"""Robust SE(3) averaging: truth recovered, planted outliers rejected, covariances honest."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.merge.averaging import (
    clustered_covariance,
    fuse_pose_estimates,
    pose_residuals,
    robust_pose_mean,
)
from shared.geometry import make_pose, pose_difference, so3_exp


def _noisy(truth, n, rng, rot_sigma, trans_sigma):
    return np.array(
        [
            make_pose(
                so3_exp(rng.normal(0, rot_sigma, 3)) @ truth[:3, :3],
                truth[:3, 3] + rng.normal(0, trans_sigma, 3),
            )
            for _ in range(n)
        ]
    )


TRUTH = make_pose(so3_exp([0.4, -1.2, 2.0]), [3.0, -2.0, -11.0])


@pytest.mark.parametrize("rotation_mean", ["chordal", "quaternion"])
@pytest.mark.parametrize("rule", ["mad", "chi2"])
def test_recovers_truth_and_rejects_planted_outliers(rotation_mean, rule):
    rng = np.random.default_rng(4)
    good = _noisy(TRUTH, 60, rng, np.deg2rad(0.5), 0.02)
    bad = np.array(
        [
            make_pose(
                so3_exp(rng.normal(size=3) * np.deg2rad(8)) @ TRUTH[:3, :3],
                TRUTH[:3, 3] + rng.normal(size=3) * 0.4,
            )
            for _ in range(15)
        ]
    )
    poses = np.concatenate((good, bad))
    result = robust_pose_mean(poses, rotation_mean=rotation_mean, outlier_rule=rule)
    rot, trans = pose_difference(result.pose, TRUTH)
    assert np.rad2deg(rot) < 0.25
    assert trans < 0.01
    assert not result.inliers[60:].any(), "every planted outlier is rejected"
    assert result.inliers[:60].mean() > 0.9
    # The plain mean is dragged away by the outliers: the test can fail.
    plain = robust_pose_mean(poses, mad_threshold=1e9)
    assert pose_difference(plain.pose, TRUTH)[1] > 2 * trans


def test_covariance_matches_the_scatter_of_the_mean():
    rng = np.random.default_rng(5)
    rot_sigma, trans_sigma, n = np.deg2rad(1.0), 0.05, 40
    errors = []
    covariances = []
    for _ in range(100):
        result = robust_pose_mean(_noisy(TRUTH, n, rng, rot_sigma, trans_sigma))
        errors.append(pose_residuals(result.pose[None], TRUTH)[0])
        covariances.append(result.covariance)
    errors = np.array(errors)
    predicted = np.mean(covariances, axis=0)
    empirical = errors.T @ errors / len(errors)
    ratio = np.diag(empirical) / np.diag(predicted)
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio
    # Expected sigma of the mean: rot_sigma / sqrt(n) per axis.
    assert np.sqrt(predicted[0, 0]) == pytest.approx(rot_sigma / np.sqrt(n), rel=0.3)
    assert np.sqrt(predicted[4, 4]) == pytest.approx(trans_sigma / np.sqrt(n), rel=0.3)


def test_single_observation_gets_the_prior_spread():
    result = robust_pose_mean(TRUTH[None])
    np.testing.assert_allclose(result.pose, TRUTH, atol=1e-12)
    assert result.covariance[0, 0] == pytest.approx(np.deg2rad(1.0) ** 2)
    assert result.covariance[3, 3] == pytest.approx(0.02**2)
    assert result.inlier_count == 1


def test_identical_observations_are_all_inliers():
    result = robust_pose_mean(np.repeat(TRUTH[None], 5, axis=0))
    assert result.inliers.all()
    np.testing.assert_allclose(result.pose, TRUTH, atol=1e-12)


def test_weights_pull_the_mean():
    a = make_pose(np.eye(3), [0.0, 0.0, 0.0])
    b = make_pose(np.eye(3), [0.01, 0.0, 0.0])
    result = robust_pose_mean(np.array([a, b]), weights=[3.0, 1.0], mad_threshold=1e9)
    assert result.pose[0, 3] == pytest.approx(0.0025)


def test_fuse_pose_estimates_weights_by_information():
    a = make_pose(so3_exp([0.0, 0.0, 0.01]), [1.0, 0.0, 0.0])
    b = make_pose(so3_exp([0.0, 0.0, -0.01]), [1.1, 0.0, 0.0])
    cov_a = np.diag([1e-4] * 3 + [1e-4] * 3)
    cov_b = np.diag([4e-4] * 3 + [4e-4] * 3)
    pose, cov = fuse_pose_estimates(np.array([a, b]), np.array([cov_a, cov_b]))
    # Weights 4:1 -> translation 1.02, yaw 0.006.
    assert pose[0, 3] == pytest.approx(1.02, abs=1e-9)
    assert pose_residuals(pose[None], np.eye(4))[0, 2] == pytest.approx(0.006, abs=1e-6)
    np.testing.assert_allclose(np.diag(cov), [0.8e-4] * 6, rtol=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"weights": [1.0, -1.0]}, "weights"),
        ({"weights": [0.0, 0.0]}, "weights"),
        ({"weights": [1.0]}, "weights"),
        ({"rotation_mean": "euler"}, "rotation_mean"),
        ({"outlier_rule": "sigma"}, "outlier_rule"),
        ({"outlier_rule": "chi2", "chi2_probability": 0.5}, "chi2_probability"),
        ({"mad_threshold": 0.0}, "mad_threshold"),
    ],
)
def test_robust_pose_mean_rejects_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        robust_pose_mean(np.array([TRUTH, TRUTH]), **kwargs)


def test_robust_pose_mean_rejects_bad_poses():
    with pytest.raises(ValueError, match="N >= 1"):
        robust_pose_mean(np.zeros((0, 4, 4)))
    with pytest.raises(ValueError, match="non-finite"):
        robust_pose_mean(np.full((2, 4, 4), np.nan))


def test_fuse_rejects_bad_covariances():
    with pytest.raises(ValueError, match="positive definite"):
        fuse_pose_estimates(TRUTH[None], -np.eye(6)[None])
    with pytest.raises(ValueError, match="covariances"):
        fuse_pose_estimates(TRUTH[None], np.eye(6))


def test_clustered_covariance_counts_passes_not_keyframes():
    rng = np.random.default_rng(9)
    drift_sigma, n_pass, per_pass = 0.03, 4, 15
    errors, clustered, naive = [], [], []
    for _ in range(120):
        poses, labels = [], []
        for k in range(n_pass):
            offset = rng.normal(0, drift_sigma, 3)
            for _ in range(per_pass):
                poses.append(
                    make_pose(TRUTH[:3, :3], TRUTH[:3, 3] + offset + rng.normal(0, 0.005, 3))
                )
                labels.append(k)
        result = robust_pose_mean(np.array(poses), mad_threshold=1e9)
        errors.append(result.pose[:3, 3] - TRUTH[:3, 3])
        naive.append(np.diag(result.covariance)[3:])
        clustered.append(np.diag(clustered_covariance(result, labels))[3:])
    empirical = np.mean(np.array(errors) ** 2, axis=0)
    # Independent-sample covariance is ~10x too small; the clustered one is about right.
    assert np.all(empirical / np.mean(naive, axis=0) > 5)
    ratio = empirical / np.mean(clustered, axis=0)
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    with pytest.raises(ValueError, match="cluster ids"):
        clustered_covariance(result, [0, 1])
