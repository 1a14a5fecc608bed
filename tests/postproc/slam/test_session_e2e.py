"""The whole real-camera path on known truth: simulated GoPro MP4 -> import -> SLAM -> ATE.

`wreckmap-field sim survey` writes session_00/gopro/GX010001.MP4 (H.264 frames,
GPMF IMU in GoPro chip axes with their ORIN, written so that the importer's
axis mapping gives back the survey's body frame B: see truth.json's
"imu_axes"); `wreckmap-field gopro import` turns it into a session folder (MCAP
with /cam0/video in Annex B and /imu0); `wreckmap-post slam` reads the session
(H.264 decoded by SessionVideo) and estimates T_S_B.

Calibration given to the importer: the survey's camchain with the time shift
set to 0: the importer stamps frames and IMU on one media clock, on which a
frame and the IMU sample of its exposure carry the same stamp.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shared.calibration.kalibr import CameraCalibration, read_camchain, write_camchain
from shared.formats.tum import read_tum
from shared.trajectory import Trajectory, ate

REPO = Path(__file__).resolve().parents[3]


def _cli(*args: str) -> None:
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    done = subprocess.run(
        [sys.executable, "-m", *args], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, f"{args[:3]}: {done.stderr[-2000:]}"


@pytest.mark.slow
def test_simulated_gopro_session_matches_truth(tmp_path: Path) -> None:
    survey = tmp_path / "survey"
    _cli(
        "field.cli", "sim", "survey", "--out", str(survey), "--sessions", "1",
        "--duration", "12", "--seed", "3", "--width", "320", "--height", "180",
        "--fps", "30", "--workers", "1", "--texel-mm", "10",
    )  # fmt: skip
    truth_info = json.loads((survey / "truth.json").read_text())
    sim_cal = read_camchain(survey / "calib" / "camchain.yaml")[0]
    calibration = CameraCalibration(
        camera=sim_cal.camera,
        cam_from_imu=sim_cal.cam_from_imu,
        timeshift_cam_imu_s=0.0,
        topic="/cam0/video",
    )
    write_camchain(tmp_path / "camchain.yaml", [calibration])
    session = tmp_path / "session"
    _cli(
        "field.cli", "gopro", "import", str(survey / "session_00" / "gopro" / "GX010001.MP4"),
        "--out", str(session), "--camchain", str(tmp_path / "camchain.yaml"),
        "--imu-yaml", str(survey / "calib" / "imu.yaml"),
    )  # fmt: skip
    out = tmp_path / "slam"
    _cli("postproc.cli", "slam", str(session), "--out", str(out))

    estimate = read_tum(out / "trajectory.tum")
    truth = read_tum(survey / "session_00" / "world_from_body.tum")
    # Imported stamps count media time from frame 0, whose exposure (true time) is the
    # survey's first camera stamp plus the time shift.
    clocks = truth_info["sessions"][0]["clocks"]
    first_exposure_ns = clocks["gopro"]["media_time_zero_cam_ns"] + round(
        clocks["cam0"]["timeshift_cam_imu_s"] * 1e9
    )
    on_true_clock = Trajectory(
        estimate.stamps_ns - estimate.stamps_ns[0] + first_exposure_ns, estimate.poses
    )
    error = ate(on_true_clock, truth, align="se3", max_dt_ns=3_000_000)
    path_m = truth.slice_time(
        int(on_true_clock.stamps_ns[0]), int(on_true_clock.stamps_ns[-1])
    ).path_length_m()
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] >= 300  # 12 s at 30 fps, all decoded from H.264
    assert len(error.errors_m) >= 0.9 * len(estimate)
    # The target is 1 % of the distance travelled.
    assert error.rmse_m < 0.01 * path_m, (error.rmse_m, path_m)
    # Gravity: S is z up, so the truth's z axis maps onto S's z axis.
    assert abs(error.alignment[2, 2]) > np.cos(np.radians(3.0))
