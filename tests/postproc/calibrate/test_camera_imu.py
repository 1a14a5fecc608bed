"""Camera-IMU rotation and time shift (pure math) on simulated trajectories with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.calibrate.camera_imu import (
    CameraImuOptions,
    GyroSignal,
    RotationIntervals,
    correlate_offset,
    estimate_camera_imu,
    intervals_from_orientations,
)
from shared.errors import StageError
from shared.geometry import rotation_angle_rad, so3_exp
from sim.calibration import recording

MAX_GAP_NS = 50_000_000


def _noisy_intervals(rec, rng, sigma_rad=1e-3):
    noise = so3_exp(rng.normal(0.0, sigma_rad, (len(rec.world_from_cam), 3)))
    return intervals_from_orientations(
        rec.frame_stamps_ns, rec.world_from_cam[:, :3, :3] @ noise, max_gap_ns=MAX_GAP_NS
    )


def _rotation_error_deg(estimate, truth):
    return np.degrees(rotation_angle_rad(estimate @ truth[:3, :3].T))


@pytest.mark.parametrize(("seed", "shift_s"), [(0, 0.0237), (1, -0.1412), (2, 0.3)])
def test_rotation_and_shift_from_noisy_poses(seed, shift_s):
    rec = recording(seed=seed, duration_s=6.0, timeshift_cam_imu_s=shift_s, render=False)
    intervals = _noisy_intervals(rec, np.random.default_rng(seed))
    result = estimate_camera_imu(intervals, rec.imu_stamps_ns, rec.gyro_rad_s)
    assert _rotation_error_deg(result.cam_from_imu_rotation, rec.cam_from_imu) < 0.5
    assert abs(result.timeshift_cam_imu_s - rec.timeshift_cam_imu_s) < 0.002
    # The coarse step alone lands within a few grid steps.
    assert abs(result.coarse_timeshift_s - rec.timeshift_cam_imu_s) < 0.01
    assert result.peak_correlation > 0.9
    # The simulated gyro bias starts at (0.004, -0.003, 0.002) rad/s and walks slowly.
    np.testing.assert_allclose(result.gyro_bias_rad_s, [0.004, -0.003, 0.002], atol=0.0015)
    assert result.intervals_used >= 0.95 * result.intervals_total


def test_outlier_pairs_do_not_bias_the_fit():
    rec = recording(seed=7, duration_s=6.0, render=False)
    rng = np.random.default_rng(7)
    intervals = _noisy_intervals(rec, rng)
    # One pair in eight replaced by a wrong rotation of about 1-3 degrees.
    corrupted = intervals.start_from_end.copy()
    bad = np.arange(0, len(intervals), 8)
    corrupted[bad] = corrupted[bad] @ so3_exp(rng.normal(0.0, 0.03, (len(bad), 3)))
    result = estimate_camera_imu(
        RotationIntervals(intervals.start_ns, intervals.end_ns, corrupted),
        rec.imu_stamps_ns,
        rec.gyro_rad_s,
    )
    assert _rotation_error_deg(result.cam_from_imu_rotation, rec.cam_from_imu) < 0.5
    assert abs(result.timeshift_cam_imu_s - rec.timeshift_cam_imu_s) < 0.002
    assert result.intervals_used <= result.intervals_total - len(bad) // 2


def test_gyro_signal_integral_is_exact_for_piecewise_linear_rates():
    stamps = np.arange(0, 11) * 100_000_000  # 0..1 s, 10 Hz
    rates = np.column_stack((np.linspace(0, 1, 11), np.ones(11), np.zeros(11)))
    signal = GyroSignal(stamps, rates, origin_ns=0)
    # Integral of t over [0.25, 0.85] = (0.85^2 - 0.25^2) / 2; of 1 = 0.6.
    mean = signal.mean_rate([0.25], [0.85])[0]
    np.testing.assert_allclose(mean, [(0.85**2 - 0.25**2) / 2 / 0.6, 1.0, 0.0], atol=1e-12)
    assert np.isnan(signal.integral([1.5])).all()
    # A constant rate about z integrates to a rotation of rate * time about z.
    constant = GyroSignal(stamps, np.tile([0.0, 0.0, 0.7], (11, 1)), origin_ns=0)
    rotation = constant.rotation([0.1], [0.6], np.zeros(3), substeps=4)[0]
    np.testing.assert_allclose(rotation, so3_exp([0.0, 0.0, 0.35]), atol=1e-12)


def test_correlate_offset_finds_a_sub_sample_shift():
    step = 0.01
    t = np.arange(0.0, 20.0, step)
    rng = np.random.default_rng(3)
    # A smooth random signal (sum of sines) and the same signal delayed by 0.1234 s.
    freqs, phases = rng.uniform(0.2, 3.0, 8), rng.uniform(0, 2 * np.pi, 8)

    def signal(times):
        return np.sin(np.outer(times, freqs) * 2 * np.pi + phases).sum(axis=1)

    reference = signal(t)
    other = signal(t - 0.1234 + 5.0)  # other(t') with t' = t + d, d = 0.1234 - 5.0
    estimate = correlate_offset(reference, 0.0, other, 0.0, step, max_offset_s=6.0, min_overlap=100)
    assert abs(estimate.offset_s - (0.1234 - 5.0)) < 0.1 * step
    assert estimate.peak_correlation > 0.99


def test_too_few_intervals_is_an_error():
    rec = recording(seed=0, duration_s=6.0, render=False)
    intervals = _noisy_intervals(rec, np.random.default_rng(0))
    few = intervals.subset(np.arange(len(intervals)) < 5)
    with pytest.raises(StageError, match="only 5 frame pairs"):
        estimate_camera_imu(few, rec.imu_stamps_ns, rec.gyro_rad_s)


def test_rotation_about_one_axis_only_is_an_error():
    stamps = np.arange(0, 300) * 33_333_333
    angles = 0.8 * np.sin(np.arange(300) / 15.0)
    orientations = so3_exp(np.column_stack((np.zeros(300), angles, np.zeros(300))))
    intervals = intervals_from_orientations(stamps, orientations, max_gap_ns=MAX_GAP_NS)
    gyro_stamps = np.arange(0, 2000) * 5_000_000
    gyro = np.zeros((2000, 3))
    with pytest.raises(StageError, match="one axis only"):
        estimate_camera_imu(intervals, gyro_stamps, gyro)


def test_gyro_far_from_the_frames_in_time_is_an_error():
    rec = recording(seed=0, duration_s=6.0, render=False)
    intervals = _noisy_intervals(rec, np.random.default_rng(0))
    late = rec.imu_stamps_ns + 3_600_000_000_000  # an hour later: outside the search
    with pytest.raises(StageError, match="do not overlap"):
        estimate_camera_imu(intervals, late, rec.gyro_rad_s, CameraImuOptions())


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="end_ns > start_ns"):
        RotationIntervals(
            np.array([5], dtype=np.int64), np.array([5], dtype=np.int64), np.eye(3)[None]
        )
    with pytest.raises(ValueError, match="disagree"):
        RotationIntervals(
            np.array([1, 2], dtype=np.int64), np.array([3], dtype=np.int64), np.eye(3)[None]
        )
    with pytest.raises(StageError, match="fewer than 2"):
        GyroSignal(np.array([0]), np.zeros((1, 3)), origin_ns=0)
    with pytest.raises(ValueError, match=r"\(N,3\)"):
        GyroSignal(np.array([0, 1]), np.zeros((2, 2)), origin_ns=0)


def test_a_gyro_that_does_not_follow_the_camera_is_an_error():
    rec = recording(seed=0, duration_s=6.0, render=False)
    intervals = _noisy_intervals(rec, np.random.default_rng(0))
    # Same clock and rate, but white noise instead of the motion (another sensor, say).
    unrelated = np.random.default_rng(1).normal(0.0, 1.0, rec.gyro_rad_s.shape)
    with pytest.raises(StageError, match="do not correlate"):
        estimate_camera_imu(intervals, rec.imu_stamps_ns, unrelated)


def test_a_fit_that_explains_too_little_is_refused():
    rec = recording(seed=0, duration_s=6.0, render=False)
    # 3 mrad of noise per frame leaves a few percent of the rotation power unexplained.
    intervals = _noisy_intervals(rec, np.random.default_rng(0), sigma_rad=3e-3)
    result = estimate_camera_imu(intervals, rec.imu_stamps_ns, rec.gyro_rad_s)
    assert 0.9 < result.explained_fraction < 0.995
    with pytest.raises(StageError, match=r"explains only 9\d %"):
        estimate_camera_imu(
            intervals, rec.imu_stamps_ns, rec.gyro_rad_s, CameraImuOptions(min_explained=0.995)
        )


def test_outliers_cannot_fake_the_excitation():
    # The camera truly turns about y only; every third pair is a wrong rotation about a
    # random axis (failed tracking), which makes the camera's rates look 3-axis.
    def angle(t):
        return 0.8 * np.sin(2 * np.pi * 0.5 * t) + 0.3 * np.sin(2 * np.pi * 1.3 * t)

    def rate(t):
        return 0.8 * np.pi * np.cos(np.pi * t) + 0.3 * 2.6 * np.pi * np.cos(2.6 * np.pi * t)

    frame_t = np.arange(240) / 30.0
    axis_y = np.array([0.0, 1.0, 0.0])
    orientations = so3_exp(angle(frame_t)[:, None] * axis_y)
    intervals = intervals_from_orientations(
        np.round(frame_t * 1e9).astype(np.int64), orientations, max_gap_ns=MAX_GAP_NS
    )
    rng = np.random.default_rng(5)
    wrong = intervals.start_from_end.copy()
    wrong[::3] = so3_exp(rng.normal(0.0, 0.05, (len(wrong[::3]), 3)))
    corrupted = RotationIntervals(intervals.start_ns, intervals.end_ns, wrong)
    gyro_t = np.arange(-100, 1700) / 200.0
    gyro = rate(gyro_t)[:, None] * axis_y
    with pytest.raises(StageError, match="agree with the gyro turn about one axis only"):
        estimate_camera_imu(corrupted, np.round(gyro_t * 1e9).astype(np.int64), gyro)
