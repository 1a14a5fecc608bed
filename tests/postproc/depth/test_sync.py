"""Clock and depth relation estimation on synthetic dives with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.depth.simulate import simulate_dive
from postproc.depth.sync import SyncError, coarse_offset_search, fit_depth_sync

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
