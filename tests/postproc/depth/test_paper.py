"""The paper's baseline: 100 Hz cross-correlation and linear regression."""

from __future__ import annotations

import pytest

from postproc.depth.paper import paper_depth_sync
from postproc.depth.sync import SyncError
from sim.dive import simulate_dive

from .inputs import relative_inputs


def test_paper_method_finds_a_small_offset():
    sim = simulate_dive(seed=11, time_offset_s=29.91)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    sync = paper_depth_sync(traj_t, traj_z, dive_t, depth)
    # Whole 0.01 s lags only, and a shift of seconds at worst on this dive.
    assert round(sync.time_offset_s * 100) == pytest.approx(sync.time_offset_s * 100, abs=1e-6)
    assert abs(sync.time_offset_s - 29.91) < 5.0
    assert abs(sync.depth_offset_m - sim.depth_offset_m) < 0.2
    assert sync.depth_scale == pytest.approx(1.0, abs=0.05)
    assert sync.drift_ppm == 0.0


def test_paper_method_uses_a_known_zone_shift():
    sim = simulate_dive(seed=12, time_offset_s=2 * 3600.0 + 25.94)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    sync = paper_depth_sync(traj_t, traj_z, dive_t, depth, prior_offset_s=7200.0)
    assert abs(sync.time_offset_s - (7200.0 + 25.94)) < 5.0


def test_paper_method_needs_a_common_period():
    sim = simulate_dive(seed=13, time_offset_s=3 * 3600.0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    with pytest.raises(SyncError, match="needs at least 60 s in common"):
        paper_depth_sync(traj_t, traj_z, dive_t, depth)
