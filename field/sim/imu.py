"""A simulated IMU, computed exactly from a continuous trajectory.

Pure math, no I/O. The ideal measurements at time t are
    gyro_B  = omega_B(t)                       body angular rate (rad/s)
    accel_B = R_WB(t)^T (a_W(t) - g_W)         specific force (m/s^2), g_W = (0, 0, -9.81)
taken from the spline's analytic derivatives. Noise follows Kalibr's continuous-time model
(`shared.calibration.kalibr.ImuNoise`) discretised at the sample interval dt
(Euler-Maruyama): white noise sigma_d = density / sqrt(dt), bias random walk
b_{k+1} = b_k + random_walk * sqrt(dt) * N(0, I).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from field.sim.spline import SplineTrajectory
from shared.calibration.kalibr import ImuNoise

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Gravity in the world frame of the simulation (m/s^2), z up.
GRAVITY_W_MPS2 = np.array([0.0, 0.0, -9.81])


@dataclass
class ImuSamples:
    """IMU samples on the IMU clock.

    stamps_ns: (N,) int64 ns; gyro_radps, accel_mps2: (N,3) measurements in the body frame;
    gyro_bias_radps, accel_bias_mps2: (N,3) the true biases inside those measurements.
    """

    stamps_ns: IntArray
    gyro_radps: FloatArray
    accel_mps2: FloatArray
    gyro_bias_radps: FloatArray
    accel_bias_mps2: FloatArray


def ideal_imu(
    trajectory: SplineTrajectory,
    stamps_ns: npt.ArrayLike,
    *,
    gravity_w_mps2: npt.ArrayLike = GRAVITY_W_MPS2,
) -> tuple[FloatArray, FloatArray]:
    """Noise-free (gyro (N,3) rad/s, accel (N,3) m/s^2) of `trajectory` at `stamps_ns`."""
    rotation, omega = trajectory.rotation_and_rate(stamps_ns)
    accel_w = trajectory.acceleration_mps2(stamps_ns) - np.asarray(gravity_w_mps2)[None, :]
    accel_b = np.einsum("nji,nj->ni", rotation, accel_w)
    return omega, accel_b


def simulate_imu(
    trajectory: SplineTrajectory,
    stamps_ns: npt.ArrayLike,
    *,
    noise: ImuNoise | None,
    rng: np.random.Generator | None = None,
    gyro_bias0_radps: npt.ArrayLike = (0.0, 0.0, 0.0),
    accel_bias0_mps2: npt.ArrayLike = (0.0, 0.0, 0.0),
    gravity_w_mps2: npt.ArrayLike = GRAVITY_W_MPS2,
) -> ImuSamples:
    """IMU samples at `stamps_ns` (int64 ns, trajectory clock, evenly spaced).

    noise: Kalibr noise densities (None: ideal measurements with constant initial biases);
    rng: the random source (required with `noise`); *_bias0: biases at the first sample.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    gyro, accel = ideal_imu(trajectory, stamps, gravity_w_mps2=gravity_w_mps2)
    n = len(stamps)
    gyro_bias = np.tile(np.asarray(gyro_bias0_radps, dtype=np.float64), (n, 1))
    accel_bias = np.tile(np.asarray(accel_bias0_mps2, dtype=np.float64), (n, 1))
    if noise is not None:
        if rng is None:
            raise ValueError("simulate_imu: noise given without an rng")
        dt = 1.0 / noise.update_rate_hz
        steps = rng.standard_normal((4, n, 3))
        walk_g = noise.gyroscope_random_walk * np.sqrt(dt) * steps[0]
        walk_a = noise.accelerometer_random_walk * np.sqrt(dt) * steps[1]
        walk_g[0] = 0.0
        walk_a[0] = 0.0
        gyro_bias += np.cumsum(walk_g, axis=0)
        accel_bias += np.cumsum(walk_a, axis=0)
        gyro = gyro + noise.gyroscope_noise_density / np.sqrt(dt) * steps[2]
        accel = accel + noise.accelerometer_noise_density / np.sqrt(dt) * steps[3]
    return ImuSamples(
        stamps_ns=stamps,
        gyro_radps=gyro + gyro_bias,
        accel_mps2=accel + accel_bias,
        gyro_bias_radps=gyro_bias,
        accel_bias_mps2=accel_bias,
    )
