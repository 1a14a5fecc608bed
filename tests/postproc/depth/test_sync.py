"""Clock and depth relation estimation on synthetic dives with known truth."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from postproc.depth.sync import (
    AmbiguityLimits,
    ClockPrior,
    DepthSync,
    Solution,
    SyncError,
    assess_offset,
    coarse_offset_search,
    cost_gap,
    fit_depth_sync,
    mean_huber_cost,
    solve_clock_offset,
)
from sim.dive import simulate_dive

from .inputs import relative_inputs


def _estimate(sim, **kwargs):
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    coarse = coarse_offset_search(traj_t, traj_z, dive_t, depth, max_offset_s=15 * 3600.0)
    fits = [
        fit_depth_sync(traj_t, traj_z, dive_t, depth, initial_offset_s=c.offset_s, **kwargs)
        for c in coarse.candidates
    ]
    return coarse, min(fits, key=lambda f: f.robust_scale_m)


@pytest.mark.parametrize(
    ("seed", "offset_s", "drift_ppm"),
    [
        (0, 30.0, 0.0),
        (1, 290.37, 20.0),
        (2, 3 * 3600.0 + 12.5, -50.0),
        (3, -9 * 3600.0 - 7.3, 50.0),
    ],
)
def test_offset_drift_and_depth_recovered(seed, offset_s, drift_ppm):
    sim = simulate_dive(seed=seed, time_offset_s=offset_s, drift_ppm=drift_ppm)
    coarse, sync = _estimate(sim)
    assert abs(coarse.candidates[0].offset_s - offset_s) <= 2.0
    # Sub-sample: 10 s sampling, yet the offset is found to a fraction of a second.
    assert abs(sync.time_offset_s - offset_s) < 0.5
    assert abs(sync.depth_offset_m - sim.depth_offset_m) < 0.05
    assert sync.depth_scale == 1.0
    # The clock model holds at the end of the trajectory too (drift included).
    end = float(sim.trajectory.stamps_ns[-1] - sim.trajectory.stamps_ns[0]) / 1e9
    true_end = end + offset_s + drift_ppm * 1e-6 * end
    assert abs(float(sync.dive_time_s(end)) - true_end) < 0.5
    # The uncertainty is honest to within a small factor and not absurdly large.
    assert 0.0 < sync.time_offset_sigma_s < 0.5
    assert sync.depth_offset_sigma_m < 0.05
    assert sync.residual_rms_m < 0.1


def test_robust_to_outliers_and_surface_interval():
    sim = simulate_dive(
        seed=5,
        time_offset_s=-1234.6,
        outlier_fraction=0.08,
        surface_break=True,
        trajectory_start_s=200.0,
        trajectory_duration_s=2000.0,
    )
    _, sync = _estimate(sim)
    assert abs(sync.time_offset_s + 1234.6) < 0.5
    assert abs(sync.depth_offset_m - sim.depth_offset_m) < 0.05
    assert sync.inliers < sync.used  # the spikes were down-weighted


def test_scale_estimated_when_asked():
    sim = simulate_dive(seed=6, time_offset_s=45.0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    sync = fit_depth_sync(
        traj_t, 0.9 * traj_z, dive_t, depth, initial_offset_s=44.0, estimate_scale=True
    )
    assert sync.depth_scale == pytest.approx(1 / 0.9, abs=0.02)
    assert abs(sync.time_offset_s - 45.0) < 0.5


def test_fixed_time_keeps_offset():
    sim = simulate_dive(seed=7, time_offset_s=100.0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    sync = fit_depth_sync(
        traj_t, traj_z, dive_t, depth, initial_offset_s=100.0, estimate_time=False
    )
    assert sync.time_offset_s == 100.0
    assert sync.drift_ppm == 0.0
    assert sync.time_offset_sigma_s == 0.0
    assert abs(sync.depth_offset_m - sim.depth_offset_m) < 0.05


def test_no_overlap_raises():
    sim = simulate_dive(seed=8, time_offset_s=20 * 3600.0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    with pytest.raises(SyncError, match="does not overlap"):
        coarse_offset_search(traj_t, traj_z, dive_t, depth, max_offset_s=15 * 3600.0)
    with pytest.raises(SyncError, match="inside the trajectory"):
        fit_depth_sync(traj_t, traj_z, dive_t, depth, initial_offset_s=0.0)


def test_too_few_samples_raises():
    sim = simulate_dive(seed=9, time_offset_s=0.0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    with pytest.raises(SyncError, match="only 2 dive samples"):
        coarse_offset_search(traj_t, traj_z, dive_t[:2], depth[:2], max_offset_s=60.0)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="1-D"):
        coarse_offset_search(np.zeros(3), np.zeros(4), np.zeros(3), np.zeros(3), max_offset_s=1)
    with pytest.raises(ValueError, match="increasing"):
        fit_depth_sync(
            np.array([0.0, 0.0, 1.0]), np.zeros(3), np.zeros(3), np.zeros(3), initial_offset_s=0.0
        )


def test_clock_prior_windows_repeat_by_zone_step():
    prior = ClockPrior(window_s=300.0, zone_step_s=900.0)
    offsets = np.array([0.0, -299.0, 301.0, 3600.0 + 120.0, -5400.0 - 250.0, 450.0])
    np.testing.assert_allclose(prior.distance_s(offsets), [0.0, 299.0, 301.0, 120.0, 250.0, 450.0])
    np.testing.assert_array_equal(prior.contains(offsets), [True, True, False, True, True, False])
    same_zone = ClockPrior(window_s=60.0, centre_offset_s=10.0)
    np.testing.assert_array_equal(same_zone.contains([10.0, 70.0, 71.0, 3610.0]), [1, 1, 0, 0])
    assert "+- 300 s" in prior.describe() and "900 s zone" in prior.describe()


def test_coarse_search_inside_the_prior_only():
    sim = simulate_dive(seed=10, time_offset_s=2 * 3600.0 + 40.0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    prior = ClockPrior(window_s=120.0, zone_step_s=3600.0)
    coarse = coarse_offset_search(
        traj_t, traj_z, dive_t, depth, max_offset_s=15 * 3600.0, prior=prior
    )
    assert np.all(prior.contains(coarse.offsets_s))
    assert all(prior.contains(c.offset_s) for c in coarse.candidates)
    assert abs(coarse.candidates[0].offset_s - sim.time_offset_s) <= 2.0
    # A prior that excludes every overlapping offset leaves nothing to search.
    with pytest.raises(SyncError, match=r"clock prior \+0 \+- 60 s.*does not overlap"):
        coarse_offset_search(
            traj_t,
            traj_z,
            dive_t,
            depth,
            max_offset_s=15 * 3600.0,
            prior=ClockPrior(window_s=60.0, centre_offset_s=0.0),
        )


def test_mean_huber_cost():
    r = np.array([0.01, -0.02, 0.03])
    assert mean_huber_cost(r, 0.1) == pytest.approx(np.mean(0.5 * (r / 0.1) ** 2))
    # Linear beyond the threshold: a 1 m spike costs k (1/sigma - k/2), not 0.5 / sigma^2.
    assert mean_huber_cost(np.array([1.0]), 0.1, k=1.345) == pytest.approx(1.345 * (10 - 0.6725))
    assert mean_huber_cost(np.zeros(0), 0.1) == math.inf


def _sync(offset_s, residuals, *, sigma_s=0.2, depth_offset_m=10.0, robust_scale_m=0.03):
    r = np.asarray(residuals, dtype=np.float64)
    return DepthSync(
        time_offset_s=offset_s,
        drift_ppm=0.0,
        depth_offset_m=depth_offset_m,
        depth_scale=1.0,
        residual_rms_m=float(np.sqrt(np.mean(r * r))),
        time_offset_sigma_s=sigma_s,
        drift_sigma_ppm=1.0,
        depth_offset_sigma_m=0.01,
        depth_scale_sigma=0.0,
        used=r.size,
        inliers=r.size,
        robust_scale_m=robust_scale_m,
        covariance=np.zeros((4, 4)),
        residuals_m=r,
    )


def test_assess_offset_weighs_the_runner_up():
    rng = np.random.default_rng(3)
    good = rng.normal(0.0, 0.04, 6)
    # A wrong offset that fits four samples exactly and two badly: its own robust
    # scale is the smaller, yet at the common scale it is the worse fit.
    wrong = np.array([0.0, 0.01, -0.01, 0.0, 0.35, -0.3])
    solutions = [
        Solution(0, _sync(232.0, wrong, depth_offset_m=5.1, robust_scale_m=0.029), 2.0, 2.1),
        Solution(0, _sync(-112.0, good, depth_offset_m=14.5, robust_scale_m=0.05), 2.0, 2.1),
        Solution(0, _sync(-111.0, 1.5 * good), 2.0, 2.1),  # the same solution, converged worse
    ]
    best, ambiguity = assess_offset(solutions)
    assert best.sync.time_offset_s == -112.0
    assert ambiguity.runner_up_offset_s == 232.0
    assert ambiguity.runner_up_depth_offset_m == 5.1
    assert ambiguity.solutions == 2
    expected = 6 * (
        mean_huber_cost(wrong, ambiguity.cost_sigma_m)
        - mean_huber_cost(good, ambiguity.cost_sigma_m)
    )
    assert ambiguity.evidence == pytest.approx(expected)
    assert ambiguity.excursion_steps == pytest.approx(20.0)
    strict = AmbiguityLimits(min_evidence=expected + 1.0)
    _, refused = assess_offset(solutions, strict)
    assert refused.ambiguous
    assert "another offset fits almost as well: -112.0 s" in refused.reasons[0]
    assert not assess_offset(solutions, AmbiguityLimits(min_evidence=expected - 1.0))[1].ambiguous


def test_assess_offset_reasons():
    flat = Solution(1, _sync(10.0, [0.01, -0.01, 0.0, 0.02]), 0.3, 0.4)
    _, ambiguity = assess_offset([flat], AmbiguityLimits(min_depth_range_m=1.0))
    assert ambiguity.runner_up_offset_s is None and ambiguity.evidence == math.inf
    assert ambiguity.reasons == (
        "the depth profile is too flat to find the clock offset (depth spans 0.30 m, "
        "trajectory z 0.40 m where they overlap; need 1.00 m)",
    )
    few = Solution(0, _sync(10.0, [0.01, -0.01, 0.0], sigma_s=9.0), 3.0, 3.0)
    _, ambiguity = assess_offset([few])
    assert len(ambiguity.reasons) == 2
    assert ambiguity.reasons[0].startswith("only 3 dive samples overlap")
    assert ambiguity.reasons[1].startswith("the clock offset is undetermined (10.0 +- 9.0 s")
    # Another dive at the same offset is a different solution.
    other = Solution(1, _sync(10.0, [0.01, -0.01, 0.0, 0.02]), 3.0, 3.0)
    best = Solution(0, _sync(10.0, [0.01, -0.01, 0.0, 0.01]), 3.0, 3.0)
    _, ambiguity = assess_offset([best, other])
    assert ambiguity.runner_up_dive == 1 and ambiguity.ambiguous
    with pytest.raises(ValueError, match="no solution"):
        assess_offset([])


def test_solve_long_dive_is_unambiguous_and_ignores_the_prior():
    sim = simulate_dive(seed=11, time_offset_s=3600.0 + 450.0, drift_ppm=-20.0, earlier_dives=1)
    traj_t, traj_z, _, _ = relative_inputs(sim)
    reference_s = sim.trajectory.stamps_ns[0] / 1e9
    dives: list[tuple[npt.ArrayLike, npt.ArrayLike]] = [
        (d.stamps_s - reference_s, d.depth_m) for d in sim.dives
    ]
    prior = ClockPrior(window_s=300.0, zone_step_s=900.0)
    solution = solve_clock_offset(traj_t, traj_z, dives, max_offset_s=15 * 3600.0, prior=prior)
    assert solution.dive == sim.dive_index
    assert abs(solution.sync.time_offset_s - sim.time_offset_s) < 0.5
    assert not solution.ambiguity.ambiguous and solution.ambiguity.evidence > 100.0
    assert solution.ambiguity is solution.search_ambiguity
    # 450 s past a zone step is outside the prior: the data win, and it is said.
    assert solution.prior_used is False
    assert solution.prior_distance_s == pytest.approx(450.0, abs=1.0)
    with pytest.raises(SyncError, match="dive 0: no clock offset"):
        solve_clock_offset(traj_t, traj_z, dives[:1], max_offset_s=600.0)


def test_fits_of_one_dive_are_compared_on_the_samples_both_use():
    rng = np.random.default_rng(4)
    n = 40
    shared_good = rng.normal(0.0, 0.03, n - 1)
    shared_worse = rng.normal(0.0, 0.09, n - 1)
    # a: samples 0..39, the first a 3 m spike at the trajectory's start; b: samples 1..40.
    a_mask = np.zeros(n + 1, dtype=bool)
    a_mask[:n] = True
    b_mask = np.zeros(n + 1, dtype=bool)
    b_mask[1:] = True
    a = Solution(0, _sync(100.0, np.concatenate([[3.0], shared_good])), 2.0, 2.0, None, 0.0, a_mask)
    b = Solution(
        0, _sync(110.0, np.concatenate([shared_worse, [0.01]])), 2.0, 2.0, None, 0.0, b_mask
    )
    sigma = 0.06
    assert cost_gap(a, b, sigma) > 10.0  # b fits the samples both use clearly worse
    # By mean cost over each fit's own samples the spike would make b look better.
    unmasked_a = Solution(0, a.sync, 2.0, 2.0)
    unmasked_b = Solution(0, b.sync, 2.0, 2.0)
    assert cost_gap(unmasked_a, unmasked_b, sigma) < 0.0
    best, ambiguity = assess_offset([b, a])
    assert best is a and ambiguity.runner_up_offset_s == 110.0
    assert ambiguity.evidence == pytest.approx(cost_gap(a, b, ambiguity.cost_sigma_m))
    # Fits that share few samples (offsets far apart) are compared by mean cost.
    far_mask = np.zeros(n + 1, dtype=bool)
    far_mask[n - 3 :] = True
    far = Solution(0, _sync(900.0, np.full(4, 0.01)), 2.0, 2.0, None, 0.0, far_mask)
    mean_gap = a.sync.used * (
        mean_huber_cost(far.sync.residuals_m, sigma) - mean_huber_cost(a.sync.residuals_m, sigma)
    )
    assert cost_gap(a, far, sigma) == pytest.approx(mean_gap)
