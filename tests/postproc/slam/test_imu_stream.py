"""SLAM on real IMU streams: duplicates, rows out of order, partial coverage (the cleaning
itself: tests/shared/test_imu.py)."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from postproc.slam.frontend import FrontendOptions
from postproc.slam.inputs import open_input
from postproc.slam.stage import SlamOptions, run
from shared.archive import ArchiveWriter, CompressedImage, Imu
from shared.calibration.kalibr import write_camchain, write_imu_yaml
from shared.formats.euroc import read_euroc
from shared.formats.tum import read_tum


def _session(euroc: Path, folder: Path, *, drop_start_s: float, drop_end_s: float) -> Path:
    """A session folder from the EuRoC fixture whose IMU starts late and ends early, with
    every tenth IMU message written twice and one sent again out of order."""
    data = read_euroc(euroc)
    assert data.camera is not None and data.imu_noise is not None
    first, last = int(data.image_stamps_ns[0]), int(data.image_stamps_ns[-1])
    keep = (data.imu_stamps_ns >= first + drop_start_s * 1e9) & (
        data.imu_stamps_ns <= last - drop_end_s * 1e9
    )
    folder.mkdir()
    with ArchiveWriter(folder / "recording.mcap") as writer:
        rows = np.flatnonzero(keep)
        for n, i in enumerate(rows):
            message = Imu(
                int(data.imu_stamps_ns[i]), "imu0", data.gyro_rad_s[i], data.accel_m_s2[i]
            )
            writer.write("/imu0", message)
            if n % 10 == 0:
                writer.write("/imu0", message)
            if n == 300:
                j = rows[n - 5]
                writer.write(
                    "/imu0",
                    Imu(int(data.imu_stamps_ns[j]), "imu0", data.gyro_rad_s[j], data.accel_m_s2[j]),
                )
        for stamp, path in zip(data.image_stamps_ns, data.image_paths, strict=True):
            writer.write(
                "/cam0/image", CompressedImage(int(stamp), "cam0", "png", path.read_bytes())
            )
    write_camchain(folder / "calib" / "camchain.yaml", [data.camera])
    write_imu_yaml(folder / "calib" / "imu.yaml", data.imu_noise)
    return folder


def test_an_imu_that_starts_late_and_ends_early_uses_the_frames_it_covers(
    wall_euroc: Path, tmp_path: Path
) -> None:
    session = _session(wall_euroc, tmp_path / "session", drop_start_s=0.55, drop_end_s=0.75)
    source = open_input(session)
    # The MCAP reader hands messages over in log-time order, so the re-sent message
    # arrives as one more duplicate: every tenth row twice, plus that one.
    rows = len(source.imu) + source.imu_cleaning.duplicate_rows
    assert source.imu_cleaning.duplicate_rows == -(-len(source.imu) // 10) + 1
    assert source.imu_cleaning.rows_in == rows
    assert np.all(np.diff(source.imu.stamps_ns) > 0)
    out = run(SlamOptions(frontend=FrontendOptions(width_px=0)), session, tmp_path / "slam")
    stats = json.loads((out / "stats.json").read_text())
    # 10 fps: frames at 0.0-0.5 s come before the IMU, the last 7 or 8 after it.
    assert stats["frames_before_imu"] == 6
    assert stats["frames_after_imu"] in (7, 8)
    assert stats["frames_in_imu_span"] == 80 - 6 - stats["frames_after_imu"]
    assert 0.5 < stats["imu_starts_after_first_frame_s"] < 0.6
    assert 0.6 < stats["imu_ends_before_last_frame_s"] < 0.8
    assert stats["imu_duplicate_rows_merged"] == source.imu_cleaning.duplicate_rows
    trajectory = read_tum(out / "trajectory.tum")
    assert len(trajectory) == stats["frames_in_imu_span"]
    assert trajectory.stamps_ns[0] >= source.imu.stamps_ns[0]
    assert trajectory.stamps_ns[-1] <= source.imu.stamps_ns[-1]
    shutil.rmtree(session)


def test_euroc_imu_rows_out_of_order_repeated_or_unreadable(
    wall_euroc: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    folder = tmp_path / "euroc"
    shutil.copytree(wall_euroc, folder)
    csv = folder / "mav0" / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    stamp_100 = rows[100].split(",")[0]
    odd = [rows[99], rows[50], "1234,not,a,number", f"{stamp_100},nan,0,0,0,0,9.8"]
    edited = [*rows[:100], *odd, *rows[100:]]
    csv.write_text("\n".join([header, *edited]) + "\n")
    with caplog.at_level(logging.WARNING):
        source = open_input(folder)
    # Row 99 written twice, row 50 sent again; the words and the NaN are skipped.
    assert source.imu_cleaning.duplicate_rows == 1
    assert source.imu_cleaning.out_of_order_rows == 1
    assert "skipped 2 rows" in caplog.text and "1 out-of-order rows dropped" in caplog.text
    reference = open_input(wall_euroc)
    np.testing.assert_array_equal(source.imu.stamps_ns, reference.imu.stamps_ns)
    np.testing.assert_allclose(source.imu.gyro_rad_s, reference.imu.gyro_rad_s)
