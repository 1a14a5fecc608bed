"""Session-to-session alignment: covariance propagation, 6 DoF, 4 DoF, placing sessions."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.merge.align import (
    TargetEstimate,
    TargetPair,
    align_4dof,
    align_6dof,
    align_sessions,
    compose_with_covariance,
    invert_with_covariance,
    place_sessions,
    tilt_between_rad,
    tilt_vector_rad,
    yaw_rad,
)
from postproc.merge.averaging import pose_residuals
from shared.geometry import invert_pose, make_pose, pose_difference, so3_exp


def _perturb(pose, cov, rng):
    delta = rng.multivariate_normal(np.zeros(6), cov)
    return make_pose(so3_exp(delta[:3]) @ pose[:3, :3], pose[:3, 3] + delta[3:])


def _perturb_many(pose, cov, rng, n):
    delta = rng.normal(size=(n, 6)) @ np.linalg.cholesky(cov).T
    return make_pose(so3_exp(delta[:, :3]) @ pose[:3, :3], pose[:3, 3] + delta[:, 3:])


def _random_cov(rng, rot_sigma, trans_sigma):
    A = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
    cov = A @ A.T
    scale = np.diag([rot_sigma] * 3 + [trans_sigma] * 3)
    return scale @ cov @ scale


def test_compose_and_invert_covariances_match_monte_carlo():
    rng = np.random.default_rng(8)
    a_from_b = make_pose(so3_exp([0.3, -0.5, 1.1]), [4.0, -2.0, 1.0])
    b_from_c = make_pose(so3_exp([-0.7, 0.2, 0.4]), [1.0, 6.0, -3.0])
    cov_ab = _random_cov(rng, 0.01, 0.02)
    cov_bc = _random_cov(rng, 0.02, 0.01)
    pose, cov = compose_with_covariance(a_from_b, cov_ab, b_from_c, cov_bc)
    np.testing.assert_allclose(pose, a_from_b @ b_from_c)
    samples = _perturb_many(a_from_b, cov_ab, rng, 4000) @ _perturb_many(
        b_from_c, cov_bc, rng, 4000
    )
    r = pose_residuals(samples, pose)
    np.testing.assert_allclose(np.cov(r.T), cov, atol=0.08 * np.abs(cov).max())
    inverse, cov_inv = invert_with_covariance(a_from_b, cov_ab)
    samples = invert_pose(_perturb_many(a_from_b, cov_ab, rng, 4000))
    r = pose_residuals(samples, inverse)
    np.testing.assert_allclose(np.cov(r.T), cov_inv, atol=0.08 * np.abs(cov_inv).max())


def _scene(rng, a_from_b, targets_in_a, rot_sigma, trans_sigma, tilt_noise=True):
    """Target estimates in A and B with independent noise of the given sigmas."""
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    pairs = []
    for i, a_from_m in enumerate(targets_in_a):
        b_from_m = invert_pose(a_from_b) @ a_from_m
        pairs.append(
            TargetPair(
                f"t{i}",
                _perturb(a_from_m, cov, rng) if tilt_noise else a_from_m,
                cov,
                _perturb(b_from_m, cov, rng) if tilt_noise else b_from_m,
                cov,
            )
        )
    return pairs


def _gravity_aligned(yaw, t):
    c, s = np.cos(yaw), np.sin(yaw)
    return make_pose([[c, -s, 0], [s, c, 0], [0, 0, 1]], t)


TARGETS = [
    make_pose(so3_exp([0.2, 0.1, 0.5]), [12.0, 4.0, -3.0]),
    make_pose(so3_exp([-0.3, 0.2, -0.8]), [22.0, -6.0, -4.0]),
]


def test_noise_free_alignment_is_exact_in_4_and_6_dof():
    rng = np.random.default_rng(1)
    truth = _gravity_aligned(0.7, [3.0, -1.0, 0.5])
    pairs = _scene(rng, truth, TARGETS, 0.01, 0.01, tilt_noise=False)
    for result in (align_6dof(pairs), align_4dof(pairs)):
        rot, trans = pose_difference(result.a_from_b, truth)
        assert rot < 1e-9 and trans < 1e-9
        assert all(r < 1e-9 and t < 1e-9 for r, t in result.residuals_rad_m)


def test_4dof_beats_6dof_on_gravity_aligned_sessions():
    rng = np.random.default_rng(2)
    truth = _gravity_aligned(-1.1, [5.0, 2.0, -0.3])
    diffs4, diffs6 = [], []
    for _ in range(60):
        pairs = _scene(rng, truth, TARGETS, np.deg2rad(0.5), 0.01)
        diffs4.append(pose_difference(align_4dof(pairs).a_from_b, truth))
        diffs6.append(pose_difference(align_6dof(pairs).a_from_b, truth))
    err4, err6 = np.array(diffs4), np.array(diffs6)
    # Target tilt error times the ~20 m lever arm hurts only the 6-DoF fit.
    assert np.sqrt(np.mean(err4[:, 1] ** 2)) < 0.5 * np.sqrt(np.mean(err6[:, 1] ** 2))
    assert np.sqrt(np.mean(err4[:, 0] ** 2)) < np.sqrt(np.mean(err6[:, 0] ** 2))
    result = align_4dof(pairs)
    assert tilt_between_rad(result.a_from_b, np.eye(4)) == 0.0
    assert np.all(result.covariance[:2] == 0.0)
    assert result.dof == 4


def test_4dof_covariance_predicts_its_error():
    rng = np.random.default_rng(3)
    truth = _gravity_aligned(2.5, [1.0, 1.0, 1.0])
    residuals, covs = [], []
    for _ in range(200):
        pairs = _scene(rng, truth, TARGETS, np.deg2rad(0.5), 0.02)
        result = align_4dof(pairs)
        residuals.append(pose_residuals(result.a_from_b[None], truth)[0])
        covs.append(result.covariance)
    errors = np.array(residuals)
    predicted = np.mean(covs, axis=0)
    for k in (2, 3, 4, 5):
        assert np.mean(errors[:, k] ** 2) / predicted[k, k] == pytest.approx(1.0, abs=0.3)


def test_6dof_with_one_target_is_the_candidate():
    rng = np.random.default_rng(4)
    truth = make_pose(so3_exp([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    pairs = _scene(rng, truth, TARGETS[:1], 0.01, 0.01)
    result = align_6dof(pairs)
    np.testing.assert_allclose(result.a_from_b, pairs[0].candidate()[0], atol=1e-9)


def test_yaw_of_a_rotation_about_z():
    assert yaw_rad(_gravity_aligned(3.0, [0, 0, 0])[:3, :3]) == pytest.approx(3.0)


def test_place_sessions_chains_and_leaves_unconnected_sessions_out():
    rng = np.random.default_rng(5)
    world_from = {
        "a": np.eye(4),
        "b": _gravity_aligned(0.5, [3.0, 0.0, 0.0]),
        "c": _gravity_aligned(-0.4, [0.0, 5.0, 1.0]),
        "d": _gravity_aligned(1.0, [1.0, 1.0, 1.0]),
    }
    world_targets = {
        "bow": TARGETS[0],
        "mid": TARGETS[1],
        "stern": make_pose(np.eye(3), [40.0, 0.0, -5.0]),
        "lonely": make_pose(np.eye(3), [60.0, 0.0, -5.0]),
    }
    seen = {"a": ["bow"], "b": ["bow", "mid"], "c": ["mid", "stern"], "d": ["lonely"]}
    cov = np.diag([np.deg2rad(0.1) ** 2] * 3 + [0.005**2] * 3)
    estimates = {
        s: {
            m: TargetEstimate(
                _perturb(invert_pose(world_from[s]) @ world_targets[m], cov, rng), cov
            )
            for m in names
        }
        for s, names in seen.items()
    }
    placed = place_sessions(estimates, "a", dof=4)
    assert set(placed) == {"a", "b", "c"}
    assert placed["c"].via == ("b",)
    for s in ("b", "c"):
        rot, trans = pose_difference(placed[s].world_from_session, world_from[s])
        assert np.rad2deg(rot) < 0.5 and trans < 0.1
    # Uncertainty grows along the chain a -> b -> c.
    assert np.trace(placed["c"].covariance) > np.trace(placed["b"].covariance)
    assert placed["b"].diagnostic_6dof is not None


def test_tilt_vector_is_the_roll_pitch_part():
    w = np.array([0.03, -0.02])
    rotation = so3_exp([*w, 0.0]) @ _gravity_aligned(2.0, [0, 0, 0])[:3, :3]
    np.testing.assert_allclose(tilt_vector_rad(rotation), w, atol=1e-12)
    np.testing.assert_allclose(tilt_vector_rad(_gravity_aligned(-1.0, [0, 0, 0])), 0.0)
    # A small rotation applied on the left adds its x and y parts (first order).
    delta = np.array([1e-4, 2e-4, 0.5e-4])
    moved = tilt_vector_rad(so3_exp(delta) @ rotation)
    np.testing.assert_allclose(moved - w, delta[:2], atol=1e-5)
    np.testing.assert_allclose(tilt_vector_rad(np.diag([1.0, -1.0, -1.0])), [np.pi, 0.0])


def _tilted_truth(rng, tilt_sigma_rad):
    """A relative pose of two gravity-aligned sessions, each tilted by tilt_sigma per axis."""
    tilt = rng.normal(0.0, np.sqrt(2.0) * tilt_sigma_rad, 2)
    yaw = rng.uniform(-np.pi, np.pi)
    return make_pose(so3_exp([*tilt, 0.0]) @ _gravity_aligned(yaw, [0, 0, 0])[:3, :3], [4, -2, 1])


def test_tilt_prior_limits_are_6dof_and_4dof():
    rng = np.random.default_rng(11)
    truth = _tilted_truth(rng, np.deg2rad(0.3))
    pairs = _scene(rng, truth, TARGETS, np.deg2rad(0.2), 0.01)
    loose = align_6dof(pairs, tilt_prior_sigma_rad=10.0)
    np.testing.assert_allclose(loose.a_from_b, align_6dof(pairs).a_from_b, atol=1e-6)
    tight = align_6dof(pairs, tilt_prior_sigma_rad=1e-9)
    assert tilt_between_rad(tight.a_from_b, np.eye(4)) < 1e-8
    assert np.all(np.diag(tight.covariance)[:2] < 1e-17)
    assert tight.dof == 6


def test_tilt_prior_beats_4dof_and_6dof_when_sessions_are_slightly_tilted():
    """Relative tilt drawn from the prior, target evidence of similar strength: the MAP
    fit's roll/pitch error is below both the 4-DoF one (which keeps the whole tilt) and
    the 6-DoF one (which keeps all the noise), and its covariance predicts it."""
    rng = np.random.default_rng(12)
    sigma = np.deg2rad(0.05)
    errors: dict[str, list[np.ndarray]] = {"4": [], "6": [], "prior": []}
    predicted = []
    for _ in range(150):
        truth = _tilted_truth(rng, sigma)
        pairs = _scene(rng, truth, TARGETS, np.deg2rad(0.06), 0.005)
        fits = {
            "4": align_4dof(pairs),
            "6": align_6dof(pairs),
            "prior": align_6dof(pairs, tilt_prior_sigma_rad=sigma),
        }
        for name, fit in fits.items():
            errors[name].append(pose_residuals(fit.a_from_b[None], truth)[0, :2])
        predicted.append(np.diag(fits["prior"].covariance)[:2])
    rms = {k: np.sqrt(np.mean(np.square(v))) for k, v in errors.items()}
    assert rms["prior"] < 0.9 * rms["4"] and rms["prior"] < 0.9 * rms["6"]
    ratio = np.mean(np.square(errors["prior"])) / np.mean(predicted)
    assert ratio == pytest.approx(1.0, abs=0.35)


def test_place_sessions_passes_the_tilt_prior():
    rng = np.random.default_rng(13)
    truth = _tilted_truth(rng, np.deg2rad(1.0))
    cov = np.diag([np.deg2rad(0.05) ** 2] * 3 + [0.005**2] * 3)
    estimates = {
        "a": {f"t{i}": TargetEstimate(t, cov) for i, t in enumerate(TARGETS)},
        "b": {f"t{i}": TargetEstimate(invert_pose(truth) @ t, cov) for i, t in enumerate(TARGETS)},
    }
    free = place_sessions(estimates, "a", dof=6)["b"].world_from_session
    held = place_sessions(estimates, "a", dof=6, tilt_prior_sigma_rad=1e-6)["b"]
    # Noise-free targets: the free fit finds the tilt, a near-certain prior removes it.
    assert pose_difference(free, truth)[0] < 1e-9
    assert tilt_between_rad(held.world_from_session, np.eye(4)) < 1e-5
    assert held.alignment is not None and held.alignment.dof == 6


def test_align_raise_paths():
    with pytest.raises(ValueError, match="no shared target"):
        align_6dof([])
    with pytest.raises(ValueError, match="no shared target"):
        align_4dof([])
    pairs = _scene(np.random.default_rng(0), np.eye(4), TARGETS, 0.01, 0.01)
    for sigma in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="tilt_prior_sigma_rad must be positive"):
            align_6dof(pairs, tilt_prior_sigma_rad=sigma)
    with pytest.raises(ValueError, match="dof must be 4 or 6"):
        align_sessions([], dof=5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="reference"):
        place_sessions({"a": {}}, "z", dof=6)
