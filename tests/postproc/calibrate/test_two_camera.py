"""Clock offset and rotation between two rigs' gyros, on a simulated motion."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.calibrate.two_camera import RigSyncOptions, estimate_rig_sync
from shared.errors import StageError
from shared.geometry import rotation_angle_rad
from sim.calibration import two_gyros


@pytest.mark.parametrize(("seed", "offset_s"), [(0, 3.1234567), (1, -17.25), (2, 0.0004)])
def test_offset_and_rotation_between_rigs(seed, offset_s):
    stamps0, gyro0, stamps1, gyro1, truth = two_gyros(seed, offset_s)
    result = estimate_rig_sync(stamps0, gyro0, stamps1, gyro1)
    assert abs(result.offset_s - offset_s) < 0.002
    assert np.degrees(rotation_angle_rad(result.imu1_from_imu0 @ truth.T)) < 0.5
    assert result.peak_correlation > 0.95
    assert result.overlap_s > 10.0


def test_prior_offset_centres_the_search():
    stamps0, gyro0, stamps1, gyro1, _ = two_gyros(4, 120.5)
    with pytest.raises(StageError, match="do not overlap"):
        estimate_rig_sync(stamps0, gyro0, stamps1, gyro1, RigSyncOptions(max_offset_s=30.0))
    result = estimate_rig_sync(
        stamps0, gyro0, stamps1, gyro1, RigSyncOptions(max_offset_s=5.0, prior_offset_s=118.0)
    )
    assert abs(result.offset_s - 120.5) < 0.002


def test_short_overlap_is_an_error():
    # Rig 1 records 5.3 s: enough to correlate, but not 5.2 s once the fit keeps a margin.
    stamps0, gyro0, stamps1, gyro1, _ = two_gyros(5, 0.3, duration1_s=5.3)
    with pytest.raises(StageError, match=r"share 5\.0 s .*need 5\.2 s"):
        estimate_rig_sync(stamps0, gyro0, stamps1, gyro1, RigSyncOptions(min_overlap_s=5.2))
    stamps0, gyro0, stamps1, gyro1, _ = two_gyros(5, 0.3, duration1_s=3.0)
    with pytest.raises(StageError, match="do not overlap"):
        estimate_rig_sync(stamps0, gyro0, stamps1, gyro1)


def test_rotation_about_one_axis_only_is_an_error():
    t = np.arange(4000) * 5_000_000
    rate = np.column_stack((np.zeros(4000), np.sin(np.arange(4000) / 37.0), np.zeros(4000)))
    rate[:, 1] += 0.3 * np.sin(np.arange(4000) / 11.0)
    with pytest.raises(StageError, match="one axis only"):
        estimate_rig_sync(t, rate, t + 2_000_000, rate)


def test_too_few_samples_is_an_error():
    with pytest.raises(StageError, match="at least 2 samples"):
        estimate_rig_sync(np.array([0]), np.zeros((1, 3)), np.array([0, 1]), np.zeros((2, 3)))


def test_gyros_of_different_motions_are_an_error():
    stamps0, gyro0, stamps1, _, _ = two_gyros(6, 1.0)
    unrelated = np.random.default_rng(6).normal(0.0, 1.0, (len(stamps1), 3))
    with pytest.raises(StageError, match="do not correlate"):
        estimate_rig_sync(stamps0, gyro0, stamps1, unrelated)
