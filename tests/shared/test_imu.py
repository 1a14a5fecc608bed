"""IMU rows made into one stream: merged gyro/accel sensors, duplicates, rows out of order."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from shared.imu import ImuSamples, clean_imu_rows

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


def test_samples_must_increase_and_match_in_length() -> None:
    stamps = np.array([1, 2, 3], dtype=np.int64)
    with pytest.raises(ValueError, match=r"expected \(3, 3\) gyro"):
        ImuSamples(stamps, np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="strictly increasing"):
        ImuSamples(np.array([1, 3, 3]), np.zeros((3, 3)), np.zeros((3, 3)))
    assert len(ImuSamples(stamps, np.zeros((3, 3)), np.zeros((3, 3)))) == 3
