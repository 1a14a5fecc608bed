"""Splines and the simulated IMU: exact derivatives, and an IMU that integrates back."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from shared.geometry import so3_exp, so3_log
from shared.imu import ImuSamples
from sim.imu import GRAVITY_W_M_S2, RandomBias, ideal_imu, simulate_imu
from sim.motion import builtin_route, diver_trajectory
from sim.spline import SplineTrajectory, bspline_basis_matrix
from sim.survey import default_cam_from_imu, default_imu_noise

START_NS = 1_700_000_000_000_000_000


def random_spline(order: int, seed: int = 0) -> SplineTrajectory:
    rng = np.random.default_rng(seed)
    count = 14
    return SplineTrajectory(
        start_ns=START_NS,
        knot_interval_s=0.4,
        position_ctrl_m=rng.normal(size=(count, 3)),
        rotation_ctrl=so3_exp(np.cumsum(rng.normal(scale=0.3, size=(count, 3)), axis=0)),
        order=order,
    )


@pytest.mark.parametrize("order", [4, 6])
def test_position_matches_scipy_bspline(order: int) -> None:
    spline = random_spline(order)
    t = np.linspace(spline.start_ns, spline.end_ns, 101).astype(np.int64)
    count = len(spline.position_ctrl_m)
    knots = (np.arange(count + order) - (order - 1)) * spline.knot_interval_s
    reference = BSpline(knots, spline.position_ctrl_m, order - 1)
    t_s = (t - spline.start_ns) * 1e-9
    np.testing.assert_allclose(spline.position_m(t), reference(t_s), atol=1e-12)
    np.testing.assert_allclose(spline.acceleration_m_s2(t), reference.derivative(2)(t_s), atol=1e-9)
    np.testing.assert_allclose(bspline_basis_matrix(order).sum(axis=0)[0], 1.0)


def test_angular_velocity_matches_finite_differences() -> None:
    spline = random_spline(6, seed=1)
    t = np.linspace(spline.start_ns + 10**6, spline.end_ns - 10**6, 57).astype(np.int64)
    h = 1000
    before, after = spline.rotation(t - h), spline.rotation(t + h)
    numeric = so3_log(np.swapaxes(before, 1, 2) @ after) / (2 * h * 1e-9)
    np.testing.assert_allclose(spline.angular_velocity_body_rad_s(t), numeric, atol=1e-6)


def test_time_outside_the_spline_raises() -> None:
    spline = random_spline(4)
    with pytest.raises(ValueError, match="outside"):
        spline.position_m([spline.end_ns + 1])
    with pytest.raises(ValueError, match="control points"):
        SplineTrajectory(
            start_ns=0, knot_interval_s=1.0, position_ctrl_m=np.zeros((3, 3)),
            rotation_ctrl=np.tile(np.eye(3), (3, 1, 1)), order=4,
        )  # fmt: skip


@pytest.mark.parametrize(
    ("positions", "rotations", "interval", "message"),
    [
        (np.zeros((6, 2)), np.tile(np.eye(3), (6, 1, 1)), 1.0, "position_ctrl_m"),
        (np.zeros((6, 3)), np.tile(np.eye(3), (5, 1, 1)), 1.0, "rotation_ctrl"),
        (np.zeros((6, 3)), np.tile(np.eye(3), (6, 1, 1)), 0.0, "knot_interval_s"),
    ],
)
def test_malformed_splines_raise(
    positions: np.ndarray, rotations: np.ndarray, interval: float, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        SplineTrajectory(
            start_ns=0,
            knot_interval_s=interval,
            position_ctrl_m=positions,
            rotation_ctrl=rotations,
            order=4,
        )


def integrate(stamps_ns, gyro, accel, rotation0, position0, velocity0):
    """Strapdown integration at the IMU rate: rotation with a coning correction, velocity
    and position with the trapezoidal rule on the world acceleration."""
    dt = np.diff(stamps_ns) * 1e-9
    rotation, position, velocity = rotation0.copy(), position0.copy(), velocity0.copy()
    accel_w_prev = rotation @ accel[0] + GRAVITY_W_M_S2
    positions = [position.copy()]
    for k in range(len(dt)):
        h = dt[k]
        w0, w1 = gyro[k], gyro[k + 1]
        rotation = rotation @ so3_exp(0.5 * (w0 + w1) * h + np.cross(w0, w1) * h * h / 12.0)
        accel_w = rotation @ accel[k + 1] + GRAVITY_W_M_S2
        position = position + velocity * h + h * h / 6.0 * (2 * accel_w_prev + accel_w)
        velocity = velocity + 0.5 * h * (accel_w_prev + accel_w)
        accel_w_prev = accel_w
        positions.append(position.copy())
    return rotation, np.array(positions)


def test_noise_free_imu_integrates_back_to_the_trajectory() -> None:
    trajectory = diver_trajectory(
        builtin_route(0), start_ns=START_NS, duration_s=10.0,
        cam_from_imu=default_cam_from_imu(), rng=np.random.default_rng(4),
    )  # fmt: skip
    stamps = START_NS + np.arange(0, 10 * 200 + 1) * 5_000_000
    gyro, accel = ideal_imu(trajectory, stamps)
    poses = trajectory.world_from_body(stamps)
    velocity0 = trajectory.velocity_m_s(stamps[:1])[0]
    rotation, positions = integrate(
        stamps, gyro, accel, poses[0, :3, :3], poses[0, :3, 3], velocity0
    )
    drift = np.linalg.norm(positions - poses[:, :3, 3], axis=1)
    angle = np.linalg.norm(so3_log(poses[-1, :3, :3].T @ rotation))
    path = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()
    print(f"noise-free IMU over 10 s, {path:.2f} m path: position drift {drift.max() * 1e3:.3f} mm,"
          f" attitude drift {np.rad2deg(angle) * 3600:.3f} arcsec")  # fmt: skip
    assert path > 2.0
    assert drift.max() < 0.01
    assert angle < 1e-5


def test_imu_noise_has_the_kalibr_discrete_sigmas() -> None:
    trajectory = random_spline(6, seed=2)
    noise = default_imu_noise(200.0)
    stamps = START_NS + np.arange(0, 20_000) * 5_000_000
    stamps = stamps[stamps <= trajectory.end_ns]
    ideal_gyro, ideal_accel = ideal_imu(trajectory, stamps)
    samples = simulate_imu(
        trajectory, stamps, noise=noise, rng=np.random.default_rng(0),
        gyro_bias0_rad_s=(0.01, 0.0, 0.0),
    )  # fmt: skip
    white_gyro = samples.gyro_rad_s - ideal_gyro - samples.gyro_bias_rad_s
    white_accel = samples.accel_m_s2 - ideal_accel - samples.accel_bias_m_s2
    np.testing.assert_allclose(
        white_gyro.std(), noise.gyroscope_noise_density * np.sqrt(200.0), rtol=0.05
    )
    np.testing.assert_allclose(
        white_accel.std(), noise.accelerometer_noise_density * np.sqrt(200.0), rtol=0.05
    )
    steps = np.diff(samples.accel_bias_m_s2, axis=0)
    np.testing.assert_allclose(
        steps.std(), noise.accelerometer_random_walk / np.sqrt(200.0), rtol=0.05
    )
    assert samples.gyro_bias_rad_s[0, 0] == 0.01


def test_noise_without_rng_raises() -> None:
    with pytest.raises(ValueError, match="rng"):
        simulate_imu(random_spline(4), [START_NS], noise=default_imu_noise())
    with pytest.raises(ValueError, match="RandomBias needs an rng"):
        simulate_imu(random_spline(4), [START_NS], noise=None, gyro_bias0_rad_s=RandomBias(0.1))


def test_random_initial_biases_and_a_walk_already_started() -> None:
    trajectory = random_spline(6, seed=3)
    stamps = START_NS + np.arange(400) * 5_000_000
    ideal = simulate_imu(
        trajectory, stamps, noise=None, rng=np.random.default_rng(1),
        gyro_bias0_rad_s=RandomBias(0.003), accel_bias0_m_s2=RandomBias(0.05),
    )  # fmt: skip
    assert isinstance(ideal, ImuSamples)
    # Without noise the biases stay put: random directions of the given norms.
    assert np.allclose(np.linalg.norm(ideal.gyro_bias_rad_s, axis=1), 0.003)
    assert np.allclose(np.linalg.norm(ideal.accel_bias_m_s2, axis=1), 0.05)
    assert np.ptp(ideal.gyro_bias_rad_s, axis=0).max() == 0.0
    assert not np.allclose(ideal.gyro_bias_rad_s[0] / 0.003, ideal.accel_bias_m_s2[0] / 0.05)
    noise = default_imu_noise(200.0)
    fresh = simulate_imu(
        trajectory, stamps, noise=noise, rng=np.random.default_rng(1),
        gyro_bias0_rad_s=RandomBias(0.003), accel_bias0_m_s2=RandomBias(0.05),
    )  # fmt: skip
    started = simulate_imu(
        trajectory, stamps, noise=noise, rng=np.random.default_rng(1),
        gyro_bias0_rad_s=RandomBias(0.003), accel_bias0_m_s2=RandomBias(0.05),
        walk_before_first=True,
    )  # fmt: skip
    # The same draws: the first bias is the initial one, or one walk step past it.
    np.testing.assert_array_equal(fresh.gyro_bias_rad_s[0], ideal.gyro_bias_rad_s[0])
    step = started.gyro_bias_rad_s[0] - fresh.gyro_bias_rad_s[0]
    assert 0.0 < np.linalg.norm(step) < 10 * noise.gyroscope_random_walk / np.sqrt(200.0)
    np.testing.assert_allclose(
        np.diff(started.gyro_bias_rad_s, axis=0)[1:], np.diff(fresh.gyro_bias_rad_s, axis=0)[1:]
    )


def test_diver_moves_like_a_diver() -> None:
    trajectory = diver_trajectory(
        builtin_route(1), start_ns=START_NS, duration_s=30.0,
        cam_from_imu=default_cam_from_imu(), rng=np.random.default_rng(1),
    )  # fmt: skip
    t = START_NS + np.arange(0, 30 * 50) * 20_000_000
    speed = np.linalg.norm(trajectory.velocity_m_s(t), axis=1)
    assert 0.2 <= speed.mean() <= 0.5
    assert speed.max() < 0.8
    assert np.abs(trajectory.angular_velocity_body_rad_s(t)).max() < 1.5
    with pytest.raises(ValueError, match="duration_s"):
        diver_trajectory(
            builtin_route(0), start_ns=0, duration_s=0.0, cam_from_imu=np.eye(4),
            rng=np.random.default_rng(0),
        )  # fmt: skip
