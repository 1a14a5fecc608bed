"""Real IMU streams: merged gyro/accel rows, duplicates, rows out of order, partial coverage."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from postproc.slam.frontend import FrontendOptions
from postproc.slam.imu_stream import clean_imu_rows
from postproc.slam.inputs import SessionInput, open_input
from postproc.slam.stage import SlamOptions, run
from shared.archive import ArchiveWriter, CompressedImage, Imu
from shared.calibration.kalibr import write_camchain, write_imu_yaml
from shared.formats.euroc import read_euroc
from shared.formats.tum import read_tum

UP = np.array([0.0, 0.0, 9.81])


def _signal(t_s: np.ndarray, phase: float) -> np.ndarray:
    return np.column_stack([np.sin(2.0 * t_s + phase), np.cos(1.3 * t_s), 0.5 * t_s])


def test_separate_gyro_and_accel_sensors_merge_into_one_stream() -> None:
    # A gyro at 200 Hz and an accelerometer at 250 Hz on their own clocks' phases,
    # interleaved in one file (sub-millisecond gaps), each row carrying one sensor.
    rng = np.random.default_rng(4)
    t_gyro = 1_000_000_000 + np.arange(0, 2_000_000_000, 5_000_000) + 137
    t_accel = 1_000_000_000 + np.arange(0, 2_000_000_000, 4_000_000) + 611_000
    t_gyro = t_gyro + rng.integers(-200_000, 200_000, len(t_gyro))
    stamps = np.concatenate([t_gyro, t_accel])
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    is_gyro = np.concatenate([np.ones(len(t_gyro), bool), np.zeros(len(t_accel), bool)])[order]
    t_s = (stamps - stamps[0]) * 1e-9
    gyro = np.where(is_gyro[:, None], _signal(t_s, 0.0), np.nan)
    accel = np.where(~is_gyro[:, None], _signal(t_s, 1.0) + UP, np.nan)
    imu, report = clean_imu_rows(stamps, gyro, accel, name="merged")
    assert np.all(np.diff(imu.stamps_ns) > 0)
    # Rows outside the other sensor's span cannot be filled in: the first gyro rows
    # (before the first accelerometer sample) and the last accelerometer rows.
    inside = (stamps >= t_accel[0]) & (stamps <= t_gyro[-1])
    assert report.edge_rows == int((~inside).sum()) > 0
    assert len(imu) == int(inside.sum())
    assert report.interpolated_values == len(imu)  # one channel missing in every row
    assert report.duplicate_rows == report.out_of_order_rows == 0
    t = (imu.stamps_ns - stamps[0]) * 1e-9
    # Linear interpolation between samples 4-5 ms apart of a 2 rad/s signal: < 1e-4.
    np.testing.assert_allclose(imu.gyro_rad_s, _signal(t, 0.0), atol=2e-4)
    np.testing.assert_allclose(imu.accel_m_s2, _signal(t, 1.0) + UP, atol=2e-4)


def test_duplicate_and_out_of_order_rows_are_dropped_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stamps = np.array([10, 20, 20, 30, 25, 40, 50, 50], dtype=np.int64)
    gyro = np.arange(24, dtype=float).reshape(8, 3)
    accel = gyro + 100.0
    gyro[2] = gyro[1]  # a message written twice
    accel[2] = accel[1]
    gyro[7] = np.nan  # a split row: accel at 50 in its own row
    accel[6] = np.nan
    with caplog.at_level(logging.WARNING):
        imu, report = clean_imu_rows(stamps, gyro, accel, name="imu0/data.csv")
    np.testing.assert_array_equal(imu.stamps_ns, [10, 20, 30, 40, 50])
    assert report.out_of_order_rows == 1  # 25 after 30
    assert report.duplicate_rows == 2
    np.testing.assert_allclose(imu.gyro_rad_s[1], gyro[1])
    np.testing.assert_allclose(imu.gyro_rad_s[4], gyro[6])
    np.testing.assert_allclose(imu.accel_m_s2[4], accel[7])
    assert "imu0/data.csv" in caplog.text and "1 out-of-order rows dropped" in caplog.text
    # Clean input passes untouched and silently.
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        clean, report = clean_imu_rows(imu.stamps_ns, imu.gyro_rad_s, imu.accel_m_s2)
    assert not report.changed and not caplog.text
    np.testing.assert_array_equal(clean.accel_m_s2, imu.accel_m_s2)


def test_a_channel_without_any_value_is_an_error() -> None:
    stamps = np.array([1, 2, 3], dtype=np.int64)
    with pytest.raises(ValueError, match="no accelerometer value"):
        clean_imu_rows(stamps, np.zeros((3, 3)), np.full((3, 3), np.nan), name="x")


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
    source = SessionInput(session)
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
