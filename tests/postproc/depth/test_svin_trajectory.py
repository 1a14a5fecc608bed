"""`wreckmap-post depth` on an SVIn2 trajectory (unpadded nanoseconds), as the paper's pipeline
hands it over."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from postproc.depth.stage import DepthOptions, run
from shared.geometry import quat_xyzw_from_matrix
from shared.trajectory import Trajectory
from sim.dive import simulate_dive

from .inputs import write_inputs

REPO = Path(__file__).resolve().parents[3]


def write_svin(path: Path, trajectory: Trajectory) -> Path:
    """The text SVIn2's pose graph saves: its header, then `sec.nsec` with nsec unpadded."""
    quats = quat_xyzw_from_matrix(trajectory.rotations)
    lines = ["#timestamp tx ty tz qx qy qz qw"]
    for k, stamp in enumerate(trajectory.stamps_ns.tolist()):
        sec, nsec = divmod(stamp, 10**9)
        numbers = " ".join(f"{v:.9f}" for v in (*trajectory.positions[k], *quats[k]))
        lines.append(f"{sec}.{nsec} {numbers}")
    path.write_text("\n".join(lines) + "\n")
    return path


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


def test_depth_cli_reads_an_svin2_trajectory(tmp_path: Path) -> None:
    sim = simulate_dive(seed=43, time_offset_s=2 * 3600.0 - 7.3, trajectory_duration_s=900.0)
    tum, dives = write_inputs(tmp_path, sim)
    svin = write_svin(tmp_path / "svin.txt", sim.trajectory)
    nsec = sim.trajectory.stamps_ns % 10**9
    assert np.any(nsec < 10**8)  # stamps whose digits would sort wrongly as decimals
    out = tmp_path / "svin_out"
    done = _cli("--trajectory", str(svin), "--dive", str(dives), "--out", str(out))
    assert done.returncode == 0, done.stderr
    doc = json.loads((out / "sync.json").read_text())
    assert doc["trajectory_read"]["stamps"] == "svin"
    assert doc["reference_time_ns"] == int(sim.trajectory.stamps_ns[0])
    assert abs(doc["time_offset_s"] - sim.time_offset_s) < 0.5
    # The same answer as from the TUM file of the same poses.
    reference = json.loads(
        run(DepthOptions(fuse=False, plot=False), tum, dives, tmp_path / "tum_out").read_text()
    )
    assert abs(doc["time_offset_s"] - reference["time_offset_s"]) < 1e-3
    assert abs(doc["depth_offset_m"] - reference["depth_offset_m"]) < 1e-4
    # Told the stamps are decimal seconds, the stage refuses in one line and says what to do.
    wrong = _cli(
        "--trajectory",
        str(svin),
        "--dive",
        str(dives),
        "--out",
        str(tmp_path / "wrong"),
        "--trajectory-format",
        "tum",
    )
    assert wrong.returncode == 1
    errors = [line for line in wrong.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and errors[0].startswith("wreckmap-post: error: svin.txt:")
    assert "--trajectory-format svin" in errors[0]
    assert "looks otherwise" in wrong.stderr  # the warning that the format given is doubtful
    assert not (tmp_path / "wrong").exists()
