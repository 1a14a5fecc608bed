"""Start-up maths: gravity alignment, rotation-known baselines, visual-inertial alignment."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.slam.backend import BackendOptions, VisualInertialBackend
from postproc.slam.initialization import (
    align_visual_inertial,
    imu_stillness,
    is_still,
    mean_specific_force,
    preintegrate,
    session_from_body_rotation,
    translation_direction,
)
from postproc.slam.types import ImuSamples
from shared.errors import StageError
from shared.geometry import so3_exp
from sim.features import DiverMotion, SyntheticOptions, sequence_imu, simulate_sequence


def test_gravity_becomes_z_and_body_x_keeps_zero_yaw() -> None:
    R_W_B = so3_exp([0.2, -0.3, 1.1])
    accel_body = R_W_B.T @ np.array([0.0, 0.0, 9.81])
    R_S_B = session_from_body_rotation(accel_body)
    np.testing.assert_allclose(R_S_B @ accel_body, [0.0, 0.0, 9.81], atol=1e-12)
    np.testing.assert_allclose(R_S_B @ R_S_B.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R_S_B) == pytest.approx(1.0)
    x_in_s = R_S_B[:, 0]
    assert abs(x_in_s[1]) < 1e-12 and x_in_s[0] > 0
    # Body x pointing straight up: yaw comes from body y instead.
    vertical = session_from_body_rotation(np.array([9.81, 0.0, 0.0]))
    np.testing.assert_allclose(vertical @ [9.81, 0, 0], [0, 0, 9.81], atol=1e-12)
    with pytest.raises(StageError, match="gravity"):
        session_from_body_rotation(np.zeros(3))


def test_mean_specific_force_removes_rotation_during_the_window() -> None:
    motion = DiverMotion()
    options = SyntheticOptions(
        gyroscope_noise_density=0.0,
        accelerometer_noise_density=0.0,
        gyroscope_random_walk=0.0,
        accelerometer_random_walk=0.0,
        gyro_bias_rad_s=0.0,
        accel_bias_m_s2=0.0,
    )
    stamps = motion.start_ns + np.arange(0, 2_000_000_000, 5_000_000, dtype=np.int64)
    imu = sequence_imu(motion, stamps, options, np.random.default_rng(0))
    mean = mean_specific_force(imu, int(stamps[0]), 1.0)
    R_W_B0 = motion.world_from_body(stamps[:1])[0, :3, :3]
    # Truth: mean of (a - g) over the window, in B0; the diver's own acceleration is small.
    up_true = R_W_B0.T @ np.array([0.0, 0.0, 1.0])
    angle = np.arccos(mean @ up_true / np.linalg.norm(mean))
    assert angle < 0.015  # radians; about 0.1 m/s^2 of diver acceleration remains
    with pytest.raises(StageError, match="no IMU samples"):
        mean_specific_force(imu, int(stamps[-1]) + 1, 1.0)
    empty = ImuSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(StageError, match="no IMU samples"):
        mean_specific_force(empty, 0, 1.0)


def test_still_threshold() -> None:
    assert is_still(derotated_flow_px=0.4, max_flow_px=1.5)
    assert not is_still(derotated_flow_px=3.0, max_flow_px=1.5)


def test_translation_direction_with_known_rotation() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform([-2, -1, 3], [2, 1, 6], size=(80, 3))
    baseline = np.array([0.3, 0.05, -0.1])
    rays_a = points
    rays_b = points - baseline
    rays_b[:5] = rng.normal(size=(5, 3))  # outliers
    d, inliers = translation_direction(rays_a, rays_b, rng=rng)
    np.testing.assert_allclose(d, baseline / np.linalg.norm(baseline), atol=1e-6)
    assert inliers >= 75
    few, count = translation_direction(rays_a[:5], rays_b[:5], rng=rng)
    assert count == 0 and np.all(np.isnan(few))


def test_alignment_recovers_velocity_and_accel_bias() -> None:
    seq = simulate_sequence(
        SyntheticOptions(
            duration_s=4.0,
            gyroscope_noise_density=0.0,
            accelerometer_noise_density=0.0,
            gyroscope_random_walk=0.0,
            accelerometer_random_walk=0.0,
            gyro_bias_rad_s=0.0,
            accel_bias_m_s2=0.05,
            seed=5,
        )
    )
    motion = DiverMotion()
    frames = [0, 30, 60, 90, 120]
    T = seq.world_from_body[frames]
    # Work in a world-aligned S: R_S_B0 is the true rotation, positions from the first.
    R0 = T[0, :3, :3]
    later = [int(seq.frame_stamps_ns[i]) for i in frames[1:]]
    pre = preintegrate(seq.imu, int(seq.frame_stamps_ns[0]), later, np.zeros(3))
    centres = (T @ seq.imu_from_cam)[:, :3, 3]
    directions = [(c - centres[0]) / np.linalg.norm(c - centres[0]) for c in centres[1:]]
    result = align_visual_inertial(
        session_from_body0=np.block([[R0, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]),
        imu_from_cam=seq.imu_from_cam,
        directions_s=directions,
        preintegrated=pre,
        gravity_m_s2=9.81,
    )
    v_true = motion.velocity_m_s(seq.frame_stamps_ns[:1])[0]
    np.testing.assert_allclose(result.velocity_m_s, v_true, atol=0.01)
    np.testing.assert_allclose(result.accel_bias_m_s2, seq.accel_bias_m_s2[0], atol=0.01)
    np.testing.assert_allclose(
        result.scales_m, np.linalg.norm(centres[1:] - centres[0], axis=1), rtol=0.02
    )
    assert result.condition > 1e-3


def test_backend_recovers_an_indeterminate_imu_only_chain() -> None:
    # A wrong gravity direction (identity rotation on a tilted body) and no landmarks:
    # the IMU-only chain diverges until GTSAM finds the system indeterminate. Since
    # issue #7 the backend rebuilds with weak priors and goes on (it used to raise a
    # StageError; the error paths that remain are tested in test_backend.py).
    seq = simulate_sequence(SyntheticOptions(duration_s=14.0, seed=1))
    backend = VisualInertialBackend(
        BackendOptions(), focal_px=450.0, imu_from_cam=seq.imu_from_cam, imu_noise=seq.imu_noise()
    )
    none = np.zeros(0, np.int64)
    xy = np.zeros((0, 2))
    backend.start(seq.frames[0].stamp_ns, np.eye(3), none, xy)
    frames = seq.frames[31::31]
    for frame in frames:
        backend.add_keyframe(frame.stamp_ns, seq.imu, none, xy)
    assert backend.stats.recovered_updates >= 1
    assert backend.num_keyframes == len(frames) + 1
    assert backend.stats.blind_keyframes == len(frames)
    assert np.all(np.isfinite(backend.session_from_body(backend.num_keyframes - 1)))


def test_imu_stillness_sees_rest_its_bias_and_noise_and_not_a_turn() -> None:
    rng = np.random.default_rng(2)
    stamps = 10**18 + np.arange(0, 2_000_000_000, 5_000_000, dtype=np.int64)  # 200 Hz, 2 s
    t_s = (stamps - stamps[0]) * 1e-9
    bias = np.array([0.004, -0.002, 0.003])
    gyro = bias + 0.002 * rng.standard_normal((len(t_s), 3))
    accel = np.array([0.3, -9.7, 0.5]) + 0.01 * rng.standard_normal((len(t_s), 3))
    moving = t_s >= 1.0  # the hand starts to move after 1 s
    gyro[moving] += 0.5 * np.sin(3.0 * t_s[moving])[:, None]
    accel[moving] += 1.0 * np.sin(4.0 * t_s[moving])[:, None]
    imu = ImuSamples(stamps, gyro, accel)
    rest = imu_stillness(imu, int(stamps[0]), int(stamps[0]) + 950_000_000)
    assert rest.still
    np.testing.assert_allclose(rest.gyro_mean_rad_s, bias, atol=3 * 0.002 / np.sqrt(190))
    assert rest.gyro_bias_sigma_rad_s >= 1e-3
    # Upper bounds on the white noise (the largest piece's spread): 0.002 and 0.01 per
    # sample at 200 Hz are 1.4e-4 rad/s/sqrt(Hz) and 7.1e-4 m/s^2/sqrt(Hz).
    assert 1.4e-4 <= rest.gyro_noise_density < 1.4e-4 * 1.3
    assert 7.1e-4 * 0.95 <= rest.accel_noise_density < 7.1e-4 * 1.3
    # The window's last quarter second moves: the pieces see it, the mean would not.
    late = imu_stillness(imu, int(stamps[0]) + 250_000_000, int(stamps[0]) + 1_250_000_000)
    assert not late.still and np.isnan(late.accel_noise_density)
    # A steady turn has a small spread but is no rest.
    turning = ImuSamples(stamps, np.tile([0.0, 0.0, 0.3], (len(t_s), 1)), accel)
    assert not imu_stillness(turning, int(stamps[0]), int(stamps[0]) + 900_000_000).still
    # Too little data is never rest.
    assert not imu_stillness(imu, int(stamps[0]), int(stamps[0]) + 300_000_000).still
