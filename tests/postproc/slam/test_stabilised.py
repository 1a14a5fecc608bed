"""Stabilised-video fallback: a visual path up to scale put in a gravity-aligned (metric) frame."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.slam.estimator import SlamResult
from postproc.slam.stabilised import gravity_and_scale, imu_scale, mean_force_in_frame
from postproc.slam.types import ImuSamples
from shared.errors import StageError
from shared.geometry import invert_pose
from sim.features import DiverMotion, Sinusoids

GRAVITY = 9.81
VISUAL_SCALE = 1 / 3  # the visual path is a third of the true one


def _imu(motion: DiverMotion, duration_s: float) -> ImuSamples:
    stamps = motion.start_ns + np.arange(-20, round(duration_s * 200) + 20, dtype=np.int64) * (
        5_000_000
    )
    R_W_B = motion.world_from_body(stamps)[:, :3, :3]
    force_w = motion.acceleration_m_s2(stamps) + np.array([0.0, 0.0, GRAVITY])
    accel = np.einsum("nji,nj->ni", R_W_B, force_w)
    return ImuSamples(stamps, motion.angular_rate_body_rad_s(stamps), accel)


def _visual_result(motion: DiverMotion, duration_s: float) -> SlamResult:
    """What the visual-only estimator would give: poses in the first body frame, scaled."""
    frames = motion.start_ns + np.arange(0, round(duration_s * 30), dtype=np.int64) * 33_333_333
    keyframes = frames[::15]
    first = invert_pose(motion.world_from_body(frames[:1])[0])

    def visual(stamps: np.ndarray) -> np.ndarray:
        poses = first @ motion.world_from_body(stamps)
        poses[:, :3, 3] *= VISUAL_SCALE
        return poses

    kf = visual(keyframes)
    return SlamResult(
        frame_stamps_ns=frames,
        session_from_body=visual(frames),
        keyframe_stamps_ns=keyframes,
        keyframe_session_from_body=kf,
        keyframe_session_from_cam=kf.copy(),
        landmark_ids=np.array([7], dtype=np.int64),
        landmarks_s=np.array([[0.0, 0.0, 1.0]]),
        stats={"frames": len(frames)},
    )


def _swimming() -> DiverMotion:
    """A diver finning along and bobbing: enough acceleration to weigh the path."""
    return DiverMotion(
        x=Sinusoids(rate=0.4, amplitudes=(0.3,), frequencies_rad_s=(1.5,), phases_rad=(0.0,)),
        z=Sinusoids(offset=-10.0, amplitudes=(0.15,), frequencies_rad_s=(2.5,), phases_rad=(1.0,)),
    )


def test_the_visual_path_becomes_gravity_aligned_and_metric() -> None:
    motion = _swimming()
    result = gravity_and_scale(
        _visual_result(motion, 10.0), _imu(motion, 10.0), shift_ns=0, gravity_m_s2=GRAVITY
    )
    assert result.stats["metric_scale"] is True
    assert result.stats["imu_scale_fit"] == pytest.approx(1 / VISUAL_SCALE, rel=0.03)
    truth = motion.world_from_body(result.frame_stamps_ns)
    # z up: the body's up direction agrees with the truth's at every frame (yaw is free).
    up_est = result.session_from_body[:, 2, :3]
    up_true = truth[:, 2, :3]
    angles = np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, axis=1), -1, 1)))
    assert float(np.max(angles)) < 1.0

    # Metric: the path length matches the truth's.
    def length(poses: np.ndarray) -> float:
        return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())

    assert length(result.session_from_body) == pytest.approx(length(truth), rel=0.03)
    np.testing.assert_allclose(result.session_from_body[0, :3, 3], 0.0, atol=1e-9)
    assert np.linalg.norm(result.landmarks_s[0]) == pytest.approx(1 / VISUAL_SCALE, rel=0.03)


def test_a_steady_pace_keeps_the_visual_scale_and_says_so() -> None:
    """Constant velocity, no turning: the accelerometer cannot weigh anything."""
    motion = DiverMotion(
        x=Sinusoids(rate=0.7),
        y=Sinusoids(),
        z=Sinusoids(offset=-10.0),
        yaw=Sinusoids(),
        pitch=Sinusoids(),
        roll=Sinusoids(),
    )
    visual = _visual_result(motion, 8.0)
    imu = _imu(motion, 8.0)
    # A real accelerometer is noisy: with nothing to measure, noise is all the fit sees.
    rng = np.random.default_rng(5)
    noisy = ImuSamples(
        imu.stamps_ns, imu.gyro_rad_s, imu.accel_m_s2 + rng.normal(0, 0.05, (len(imu), 3))
    )
    result = gravity_and_scale(visual, noisy, shift_ns=0, gravity_m_s2=GRAVITY)
    assert result.stats["metric_scale"] is False
    assert "not metres" in str(result.stats["mode"])
    steps = np.linalg.norm(np.diff(result.session_from_body[:, :3, 3], axis=0), axis=1)
    steps_visual = np.linalg.norm(np.diff(visual.session_from_body[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, steps_visual, rtol=1e-9, atol=1e-12)


def test_too_few_keyframes_for_the_scale_is_a_stage_error() -> None:
    with pytest.raises(StageError, match="too few to find the metric scale"):
        imu_scale(
            np.array([0, 1], dtype=np.int64),
            np.tile(np.eye(4), (2, 1, 1)),
            _imu(_swimming(), 1.0),
            shift_ns=0,
            gravity_m_s2=GRAVITY,
        )


def test_no_imu_sample_in_the_span_is_a_stage_error() -> None:
    motion = _swimming()
    imu = _imu(motion, 1.0)
    late = np.array([imu.stamps_ns[-1] + 10**9, imu.stamps_ns[-1] + 2 * 10**9])
    with pytest.raises(StageError, match="no IMU samples"):
        mean_force_in_frame(late, np.tile(np.eye(4), (2, 1, 1)), imu, 0)
