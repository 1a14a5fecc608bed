"""Long dives that hold one depth (issue 21): the clock is in a metre of slow depth change.

A 25-minute trajectory over a wreck's deck, the depth within about a metre,
the dive computer every 10 s with 0.1 m steps and 30 ppm of clock drift, and
a VIO whose z drifts 0.4 % of the distance swum (1.8 m here) with a 5 cm
wobble. The search used to refuse such dives (its five candidates all on the
slopes of one broad valley of a misfit the drift dominated) or, inside the
clock prior, answer hundreds of seconds wrong. The data tell: the stage must
answer within a second, unambiguously, without needing the prior.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from postproc.depth.stage import DepthOptions, run
from postproc.depth.sync import (
    coarse_offset_search,
    despike,
    fit_depth_sync,
    flat_profile_fit,
    mean_huber_cost,
    offset_profile,
    solve_clock_offset,
)
from shared.formats.diveprofile import DiveProfile, stamp_s_to_iso, write_dive
from shared.formats.tum import write_tum
from shared.trajectory import Trajectory
from sim.dive import simulate_dive

from .inputs import relative_inputs, write_inputs

TRUE_OFFSET_S = 161.9


def _flat_dive(seed: int, *, bottom_range_m: float = 1.0, duration_s: float = 1500.0):
    return simulate_dive(
        seed=seed,
        time_offset_s=TRUE_OFFSET_S,
        drift_ppm=30.0,
        trajectory_duration_s=duration_s,
        bottom_range_m=bottom_range_m,
        vio_z_drift_per_m=0.004,
        vio_z_wobble_m=0.05,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_long_flat_dive_is_synced(tmp_path, seed):
    sim = _flat_dive(seed)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    # The kind of dive the issue describes: flat, with a VIO drift larger than the signal.
    overlap = (dive_t - TRUE_OFFSET_S >= 0.0) & (dive_t - TRUE_OFFSET_S <= traj_t[-1])
    assert np.percentile(depth[overlap], 95) - np.percentile(depth[overlap], 5) < 1.2
    assert np.ptp(traj_z) > 1.5

    trajectory, dives = write_inputs(tmp_path, sim)
    options = DepthOptions(fuse=False, plot=False)
    doc = json.loads(run(options, trajectory, dives, tmp_path / "out").read_text())
    assert abs(doc["time_offset_s"] - TRUE_OFFSET_S) < 1.0
    ambiguity = doc["offset_ambiguity"]
    assert ambiguity["ambiguous"] is False
    assert ambiguity["evidence"] >= options.min_evidence
    assert ambiguity["flat_evidence"] >= options.min_evidence
    assert doc["clock_prior"]["used"] is False
    # The steady VIO drift was seen for what it is: 0.4 % of 0.3 m/s, up or down.
    assert abs(doc["z_rate_m_per_s"]) == pytest.approx(0.0012, abs=0.0003)


def test_half_metre_flat_dive_is_synced(tmp_path):
    sim = _flat_dive(3, bottom_range_m=0.5, duration_s=2100.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    doc = json.loads(
        run(DepthOptions(fuse=False, plot=False), trajectory, dives, tmp_path / "out").read_text()
    )
    assert abs(doc["time_offset_s"] - TRUE_OFFSET_S) < 2.0
    assert doc["offset_ambiguity"]["ambiguous"] is False


def test_coarse_candidates_are_distinct_local_minima():
    sim = _flat_dive(0)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    coarse = coarse_offset_search(
        traj_t, traj_z, dive_t, depth, max_offset_s=3600.0, z_rate_sigma_m_per_s=2.6e-4
    )
    offsets = np.array([c.offset_s for c in coarse.candidates])
    assert abs(offsets[0] - TRUE_OFFSET_S) <= 3.0
    assert np.all(np.abs(np.diff(np.sort(offsets))) >= 10.0)
    # Each is the least of the score within a sample interval either side.
    for c in coarse.candidates:
        near = np.abs(coarse.offsets_s - c.offset_s) <= 10.0
        assert c.rms_m == pytest.approx(coarse.rms_m[near].min())
    # Without the drift term the misfit at the truth is the drift's, not the noise's.
    plain = coarse_offset_search(traj_t, traj_z, dive_t, depth, max_offset_s=3600.0)
    at_truth = np.argmin(np.abs(coarse.offsets_s - TRUE_OFFSET_S))
    assert coarse.rms_m[at_truth] < 0.5 * plain.rms_m[np.argmin(np.abs(plain.offsets_s - 162))]


def test_despike_moves_lone_spikes_only():
    descent = np.round(np.linspace(0.0, 12.0, 13), 1)
    depth = np.concatenate([descent, np.full(6, 12.0)])
    spiked = depth.copy()
    spiked[15] += 3.0
    np.testing.assert_array_equal(despike(spiked), depth)
    np.testing.assert_array_equal(despike(depth), depth)  # a descent is no spike


def test_offset_profile_and_flat_null_model():
    sim = _flat_dive(1)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    offsets, cost = offset_profile(
        traj_t,
        traj_z,
        dive_t,
        depth,
        centre_offset_s=TRUE_OFFSET_S + 6.0,
        half_width_s=10.0,
        noise_sigma_m=0.06,
        z_rate_sigma_m_per_s=2.6e-4,
    )
    assert offsets.size == 81 and np.all(np.isfinite(cost))
    assert abs(offsets[np.argmin(cost)] - TRUE_OFFSET_S) < 2.0
    sync = fit_depth_sync(
        traj_t,
        traj_z,
        dive_t,
        depth,
        initial_offset_s=float(offsets[np.argmin(cost)]),
        z_rate_sigma_m_per_s=2.6e-4,
    )
    assert abs(sync.time_offset_s - TRUE_OFFSET_S) < 1.0
    assert sync.prior_cost > 0.0
    # The flat profile (no trajectory) leaves the depth's own metre of change unexplained.
    u = sync.camera_time_s(dive_t)
    inside = (u >= traj_t[0]) & (u <= traj_t[-1])
    residuals, prior = flat_profile_fit(
        u[inside], depth[inside], noise_sigma_m=0.06, z_rate_sigma_m_per_s=2.6e-4
    )
    assert residuals.size == sync.used and prior >= 0.0
    gain = sync.used * (mean_huber_cost(residuals, 0.06) - mean_huber_cost(sync.residuals_m, 0.06))
    assert gain > 10 * DepthOptions().min_evidence
    # A truly flat dive leaves the trajectory nothing to explain: no gain at all.
    flat = simulate_dive(seed=4, time_offset_s=TRUE_OFFSET_S, flat=True)
    traj_t, traj_z, dive_t, depth = relative_inputs(flat)
    sync = fit_depth_sync(traj_t, traj_z, dive_t, depth, initial_offset_s=TRUE_OFFSET_S)
    u = sync.camera_time_s(dive_t)
    inside = (u >= traj_t[0]) & (u <= traj_t[-1])
    residuals, _ = flat_profile_fit(
        u[inside], depth[inside], noise_sigma_m=0.06, z_rate_sigma_m_per_s=None
    )
    gain = sync.used * (mean_huber_cost(residuals, 0.06) - mean_huber_cost(sync.residuals_m, 0.06))
    assert abs(gain) < 1.0


def _aliased_dive(folder):
    """A 20 min dive with an 8 s finning bob that 10 s samples alias: +8 s fits as well."""
    rng = np.random.default_rng(0)
    epoch_s = 1_700_000_000.0

    def depth_at(t_s):
        return 12.0 + 0.2 * np.sin(2 * np.pi * t_s / 8.0) + 0.6 * np.tanh((t_s - 600.0) / 150.0)

    traj_t = np.arange(0.0, 1200.0, 0.2)
    z = -(depth_at(traj_t) - depth_at(0.0))
    poses = np.repeat(np.eye(4)[None], traj_t.size, axis=0)
    poses[:, 2, 3] = z
    offset_s = 41.7
    dive_t = np.arange(-300.0, 1500.0, 10.0) + 0.3
    depth = np.round(depth_at(dive_t - offset_s) + rng.normal(0.0, 0.02, dive_t.size), 1)
    stamps_ns = np.rint((epoch_s + traj_t) * 1e9).astype(np.int64)
    trajectory = write_tum(folder / "trajectory.tum", Trajectory(stamps_ns, poses))
    profile = DiveProfile(
        stamps_s=epoch_s + dive_t,
        depth_m=depth,
        temperature_c=np.full(dive_t.size, 27.0),
        start_iso=stamp_s_to_iso(epoch_s + dive_t[0] - 10.0),
        model="Simulated Perdix",
        serial="SIM0001",
        fingerprint="00000001",
        source="test",
        sample_interval_s=10.0,
    )
    write_dive(folder / "dives", profile)
    return trajectory, folder / "dives", offset_s, (traj_t, z, dive_t, depth)


def test_an_offset_one_bob_period_away_is_reported(tmp_path, caplog):
    trajectory, dives, offset_s, arrays = _aliased_dive(tmp_path)
    traj_t, traj_z, dive_t, depth = arrays
    solution = solve_clock_offset(traj_t, traj_z, [(dive_t, depth)], max_offset_s=3600.0)
    ambiguity = solution.ambiguity
    # The coarse search keeps one minimum per sample interval: the alias is not among
    # the candidates, so the assessment alone would call the answer certain.
    assert not ambiguity.ambiguous and ambiguity.evidence > DepthOptions().min_evidence
    assert abs(solution.sync.time_offset_s - offset_s) < 0.5
    assert ambiguity.near_offset_s == pytest.approx(offset_s + 8.0, abs=0.5)
    assert ambiguity.near_evidence < DepthOptions().min_evidence
    assert ambiguity.near_depth_offset_m is not None
    assert abs(ambiguity.near_depth_offset_m - solution.sync.depth_offset_m) < 0.05
    with caplog.at_level("WARNING", logger="postproc.depth.stage"):
        doc = json.loads(
            run(
                DepthOptions(fuse=False, plot=False), trajectory, dives, tmp_path / "out"
            ).read_text()
        )
    assert "known only to within 8 s" in caplog.text
    assert doc["offset_ambiguity"]["near_offset_s"] == pytest.approx(offset_s + 8.0, abs=0.5)
