"""Gyro vs image rotation: time shift, focal scale and the stabilisation verdict."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.slam.gyro_check import GyroCheckOptions, check_gyro_against_images, visual_rotation
from postproc.slam.synthetic import DiverMotion, Sinusoids
from postproc.slam.types import ImuSamples
from shared.geometry import so3_exp, so3_log

START_NS = DiverMotion().start_ns
FOCAL_PX = 400.0


def _turning_motion(amplitude_rad: float = 0.4) -> DiverMotion:
    """A camera panning and tilting back and forth (about 1 rad/s at the peaks)."""
    return DiverMotion(
        yaw=Sinusoids(amplitudes=(amplitude_rad,), frequencies_rad_s=(2.1,), phases_rad=(0.0,)),
        pitch=Sinusoids(amplitudes=(0.15,), frequencies_rad_s=(3.3,), phases_rad=(0.4,)),
    )


def _imu(motion: DiverMotion, duration_s: float = 6.0) -> ImuSamples:
    stamps = START_NS + np.arange(-40, round(duration_s * 200) + 40, dtype=np.int64) * 5_000_000
    gyro = motion.angular_rate_body_rad_s(stamps)
    return ImuSamples(stamps, gyro, np.tile([0.0, 0.0, 9.81], (len(stamps), 1)))


def _frame_pairs(duration_s: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    frames = START_NS + np.arange(0, round(duration_s * 30), dtype=np.int64) * 33_333_333
    return frames[:-1], frames[1:]


def _visual(
    motion: DiverMotion,
    starts: np.ndarray,
    ends: np.ndarray,
    *,
    shift_s: float,
    gain: float,
) -> np.ndarray:
    """`R_Cnow_Cprev` the images would give (C = B): the body rotation at t_cam + shift,
    its angle multiplied by `gain` (what a focal guess `1 / gain` too short does)."""
    shift_ns = round(shift_s * 1e9)
    prev = motion.world_from_body(starts + shift_ns)[:, :3, :3]
    now = motion.world_from_body(ends + shift_ns)[:, :3, :3]
    out = []
    for R_W_prev, R_W_now in zip(prev, now, strict=True):
        R_prev_now = R_W_prev.T @ R_W_now
        out.append(so3_exp(gain * so3_log(R_prev_now)).T)
    return np.array(out)


def _check(visual: np.ndarray, starts: np.ndarray, ends: np.ndarray, imu: ImuSamples):
    return check_gyro_against_images(
        starts_ns=starts,
        ends_ns=ends,
        visual_now_from_prev=visual,
        imu=imu,
        imu_from_cam_rotation=np.eye(3),
        focal_px=FOCAL_PX,
        options=GyroCheckOptions(),
    )


def test_a_rigid_camera_gives_back_the_time_shift_and_the_focal_scale() -> None:
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=-0.046, gain=1.35)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "rigid"
    assert check.time_shift_s == pytest.approx(-0.046, abs=0.003)
    assert check.focal_scale == pytest.approx(1.35, rel=0.02)
    assert check.unexplained < 0.05
    assert check.as_stats()["gyro_check"] == "rigid"


def test_a_stabilised_video_is_not_rigid() -> None:
    """Images that turn a third as much as the body, 0.25 s late (electronic stabilisation)."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts - 250_000_000, ends - 250_000_000, shift_s=0.0, gain=0.33)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "not rigid"
    assert check.focal_scale < 0.6 or check.unexplained > 0.5


def test_swapped_axes_are_not_rigid() -> None:
    """An IMU whose x and y axes are swapped (an import bug) must not pass as rigid."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=0.0, gain=1.0)
    imu = _imu(motion)
    swapped = ImuSamples(imu.stamps_ns, imu.gyro_rad_s[:, [1, 0, 2]], imu.accel_m_s2)
    assert _check(visual, starts, ends, swapped).verdict == "not rigid"


def test_a_camera_that_hardly_turns_gives_no_verdict() -> None:
    motion = _turning_motion(amplitude_rad=0.0)
    motion.pitch = Sinusoids()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=0.0, gain=1.0)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "unknown"
    assert check.turning_pairs < GyroCheckOptions().min_pairs


def test_visual_rotation_recovers_a_rotation_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    rays = np.column_stack([rng.uniform(-0.8, 0.8, (200, 2)), np.ones(200)])
    R_now_prev = so3_exp([0.02, -0.05, 0.01])
    moved = rays @ R_now_prev.T
    xy_prev = rays[:, :2]
    xy_now = moved[:, :2] / moved[:, 2:3]
    xy_now[:40] += rng.uniform(-0.1, 0.1, (40, 2))  # 20 % gross outliers
    estimate, inliers = visual_rotation(
        xy_prev, xy_now, rng=np.random.default_rng(0), threshold_rad=0.002
    )
    assert inliers >= 155
    assert np.linalg.norm(so3_log(estimate.T @ R_now_prev)) < 1e-6


def test_visual_rotation_needs_eight_points() -> None:
    estimate, inliers = visual_rotation(
        np.zeros((5, 2)), np.zeros((5, 2)), rng=np.random.default_rng(0), threshold_rad=0.01
    )
    assert inliers == 0
    np.testing.assert_array_equal(estimate, np.eye(3))
