"""The depth stage end to end: files in, sync.json and world trajectories out; the CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from postproc.depth.stage import DepthOptions, run
from shared.errors import StageError
from shared.formats.diveprofile import write_dive
from shared.formats.tum import read_tum
from sim.dive import simulate_dive

from .inputs import write_inputs

REPO = Path(__file__).resolve().parents[3]


def test_stage_picks_the_overlapping_dive_and_writes_outputs(tmp_path):
    sim = simulate_dive(
        seed=31,
        time_offset_s=3 * 3600.0 + 12.5,
        drift_ppm=-30.0,
        vio_z_drift_m_per_sqrt_s=0.01,
        earlier_dives=2,
    )
    trajectory, dives = write_inputs(tmp_path, sim)
    out = tmp_path / "depth"
    sync_path = run(DepthOptions(), trajectory, dives, out)
    assert sync_path == out / "sync.json"
    doc = json.loads(sync_path.read_text())
    assert doc["dive"]["start"] == sim.dives[sim.dive_index].start_iso
    assert abs(doc["time_offset_s"] - sim.time_offset_s) < 0.5
    assert doc["reference_time_ns"] == int(sim.trajectory.stamps_ns[0])
    assert doc["depth_scale"] == 1.0
    for key in ("time_offset_sigma_s", "drift_sigma_ppm", "depth_offset_sigma_m", "residual_rms_m"):
        assert doc[key] > 0.0
    assert doc["depth_scale_free"]["value"] == pytest.approx(1.0, abs=0.05)
    # A long dive: one offset stands out by far; the earlier dives are the runners-up.
    ambiguity = doc["offset_ambiguity"]
    assert ambiguity["ambiguous"] is False and ambiguity["samples"] == doc["samples_used"]
    assert ambiguity["evidence"] > 100 * DepthOptions().min_evidence
    assert ambiguity["time_offset_sigma_s"] == doc["time_offset_sigma_s"]
    assert doc["clock_prior"] == {
        "available": True,
        "used": False,
        "window_s": 300.0,
        "zone_step_s": 900.0,
        "distance_s": pytest.approx(12.5, abs=0.5),
        "inside": True,
        "relation": doc["clock_prior"]["relation"],
    }
    world = read_tum(out / "trajectory_world.tum")
    fused = read_tum(out / "trajectory_world_fused.tum")
    true_z = sim.truth_world.positions[:, 2]
    np.testing.assert_array_equal(world.stamps_ns, sim.trajectory.stamps_ns)
    rmse_world = np.sqrt(np.mean((world.positions[:, 2] - true_z) ** 2))
    rmse_fused = np.sqrt(np.mean((fused.positions[:, 2] - true_z) ** 2))
    assert rmse_fused < 0.6 * rmse_world
    # The depth offset is the (fitted) depth of the origin: world z = -depth_offset at z = 0.
    assert world.positions[0, 2] == pytest.approx(-doc["depth_offset_m"])
    assert (out / "depth_sync.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_stage_accuracy_without_vio_drift(tmp_path):
    sim = simulate_dive(seed=32, time_offset_s=290.0, drift_ppm=40.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    csv = next(dives.glob("*.csv"))
    doc = json.loads(
        run(DepthOptions(fuse=False, plot=False), trajectory, csv, tmp_path / "out").read_text()
    )
    assert abs(doc["time_offset_s"] - 290.0) < 0.5
    assert abs(doc["depth_offset_m"] - sim.depth_offset_m) < 0.05
    assert not (tmp_path / "out" / "trajectory_world_fused.tum").exists()


def test_stage_skips_done_work_and_overwrites_on_request(tmp_path):
    sim = simulate_dive(seed=33, time_offset_s=30.0, trajectory_duration_s=900.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    options = DepthOptions(fuse=False, plot=False)
    out = tmp_path / "out"
    first = run(options, trajectory, dives, out)
    before = first.read_text()
    first.write_text(before.replace('"method"', '"method_marker"'))
    assert run(options, trajectory, dives, out) == first
    assert "method_marker" in first.read_text()  # untouched: the stage was skipped
    run(options, trajectory, dives, out, overwrite=True)
    assert json.loads(first.read_text()) == json.loads(before)


def test_paper_method_through_the_stage(tmp_path):
    sim = simulate_dive(seed=34, time_offset_s=25.94)
    trajectory, dives = write_inputs(tmp_path, sim)
    doc = json.loads(
        run(
            DepthOptions(method="paper", fuse=False), trajectory, dives, tmp_path / "out"
        ).read_text()
    )
    assert doc["method"] == "paper"
    assert abs(doc["time_offset_s"] - 25.94) < 5.0
    assert doc["time_offset_sigma_s"] is None  # the paper gives no time uncertainty
    # Hours off: no common period on the clocks as they are, unless the zone is given.
    far = simulate_dive(seed=35, time_offset_s=4 * 3600.0 + 3.0)
    far_traj, far_dives = write_inputs(tmp_path / "far_in", far)
    with pytest.raises(StageError, match=r"needs at least 60 s in common.*--time-offset"):
        run(DepthOptions(method="paper"), far_traj, far_dives, tmp_path / "far")
    doc = json.loads(
        run(
            DepthOptions(method="paper", time_offset_s=4 * 3600.0, fuse=False, plot=False),
            far_traj,
            far_dives,
            tmp_path / "far",
        ).read_text()
    )
    assert abs(doc["time_offset_s"] - far.time_offset_s) < 5.0


def test_no_overlap_is_a_stage_error(tmp_path):
    sim = simulate_dive(seed=36, time_offset_s=20 * 3600.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    with pytest.raises(StageError, match=r"does not overlap.*--time-offset SECONDS"):
        run(DepthOptions(), trajectory, dives, tmp_path / "out")
    assert not (tmp_path / "out" / "sync.json").exists()
    with pytest.raises(StageError, match="no dive has 3 samples"):
        run(DepthOptions(time_offset_s=0.0), trajectory, dives, tmp_path / "out")


def test_flat_profile_is_a_stage_error_unless_the_offset_is_given(tmp_path):
    sim = simulate_dive(seed=37, time_offset_s=77.0, flat=True)
    trajectory, dives = write_inputs(tmp_path, sim)
    with pytest.raises(StageError, match=r"too flat.*--time-offset SECONDS"):
        run(DepthOptions(), trajectory, dives, tmp_path / "out")
    doc = json.loads(
        run(
            DepthOptions(time_offset_s=77.0, fuse=False, plot=False),
            trajectory,
            dives,
            tmp_path / "out",
        ).read_text()
    )
    assert doc["time_offset_given"] is True
    assert doc["time_offset_s"] == 77.0
    assert abs(doc["depth_offset_m"] - sim.depth_offset_m) < 0.05


def test_bad_options_are_refused(tmp_path):
    sim = simulate_dive(seed=38, time_offset_s=0.0, trajectory_duration_s=300.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    with pytest.raises(StageError, match="max_offset_s must be a positive"):
        run(DepthOptions(max_offset_s=-1.0), trajectory, dives, tmp_path / "out")
    with pytest.raises(StageError, match="unknown method"):
        run(DepthOptions(method="magic"), trajectory, dives, tmp_path / "out")  # type: ignore[arg-type]
    bad = {
        "clock_prior_window_s": (0.0, "clock_prior_window_s must be a positive"),
        "clock_prior_zone_step_s": (-900.0, "clock_prior_zone_step_s must be 0 or more"),
        "min_evidence": (float("nan"), "min_evidence must be 0 or more"),
        "min_overlap_samples": (2, "min_overlap_samples must be at least 3"),
    }
    for name, (value, message) in bad.items():
        options = DepthOptions()
        setattr(options, name, value)
        with pytest.raises(StageError, match=message):
            run(options, trajectory, dives, tmp_path / "out")


def test_clock_far_from_the_prior_is_kept_with_a_warning(tmp_path, caplog):
    # 7.5 min past a quarter hour: outside the prior, but a long dive leaves no doubt.
    sim = simulate_dive(seed=42, time_offset_s=2 * 3600.0 + 450.0, trajectory_duration_s=900.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    with caplog.at_level("WARNING", logger="postproc.depth.stage"):
        doc = json.loads(
            run(
                DepthOptions(fuse=False, plot=False), trajectory, dives, tmp_path / "out"
            ).read_text()
        )
    assert abs(doc["time_offset_s"] - sim.time_offset_s) < 0.5
    assert doc["clock_prior"]["used"] is False and doc["clock_prior"]["inside"] is False
    assert doc["clock_prior"]["distance_s"] == pytest.approx(450.0, abs=1.0)
    assert "further off than expected" in caplog.text


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "WRECKMAP_PROGRESS": "0", "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "postproc.cli", "depth", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=120,
        check=False,
    )


def test_cli_runs_and_reports_errors_in_one_line(tmp_path):
    sim = simulate_dive(seed=39, time_offset_s=-3600.0 + 4.2, trajectory_duration_s=1200.0)
    trajectory, dives = write_inputs(tmp_path, sim)
    out = tmp_path / "out"
    done = _cli("--trajectory", str(trajectory), "--dive", str(dives), "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(out / "sync.json")
    doc = json.loads((out / "sync.json").read_text())
    assert abs(doc["time_offset_s"] - sim.time_offset_s) < 0.5
    assert (out / "trajectory_world_fused.tum").is_file()

    flat = simulate_dive(seed=40, time_offset_s=10.0, flat=True, trajectory_duration_s=900.0)
    flat_dir = tmp_path / "flat"
    flat_dir.mkdir()
    flat_traj, flat_dives = write_inputs(flat_dir, flat)
    failed = _cli(
        "--trajectory",
        str(flat_traj),
        "--dive",
        str(flat_dives),
        "--out",
        str(tmp_path / "flat_out"),
    )
    assert failed.returncode == 1
    lines = failed.stderr.strip().splitlines()
    assert len(lines) == 1 and "too flat" in lines[0] and "--time-offset" in lines[0]
    given = _cli(
        "--trajectory",
        str(flat_traj),
        "--dive",
        str(flat_dives),
        "--out",
        str(tmp_path / "flat_out"),
        "--time-offset",
        "10",
        "--no-fuse",
        "--no-plot",
    )
    assert given.returncode == 0, given.stderr


def test_single_dive_csv_without_index(tmp_path):
    sim = simulate_dive(seed=41, time_offset_s=12.0, trajectory_duration_s=900.0)
    trajectory, _ = write_inputs(tmp_path, sim)
    single = tmp_path / "single"
    csv = write_dive(single, sim.dives[sim.dive_index])
    (single / "dives.json").unlink()
    doc = json.loads(
        run(DepthOptions(fuse=False, plot=False), trajectory, csv, tmp_path / "out").read_text()
    )
    assert abs(doc["time_offset_s"] - 12.0) < 0.5
