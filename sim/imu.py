"""A simulated IMU, computed exactly from a continuous trajectory.

Pure math, no I/O. The ideal measurements at time t are
    gyro_B  = omega_B(t)                       body angular rate (rad/s)
    accel_B = R_WB(t)^T (a_W(t) - g_W)         specific force (m/s^2), g_W = (0, 0, -9.81)
taken from the trajectory's analytic derivatives (a B-spline, `sim.spline`, or the
sinusoids of the feature-level sequences, `sim.features`). Noise follows Kalibr's
continuous-time model (`shared.calibration.kalibr.ImuNoise`) discretised at the sample
interval dt (Euler-Maruyama): white noise sigma_d = density / sqrt(dt), bias random walk
b_{k+1} = b_k + random_walk * sqrt(dt) * N(0, I).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from shared.calibration.kalibr import ImuNoise
from shared.imu import ImuSamples

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Gravity in the world frame of the simulation (m/s^2), z up.
GRAVITY_W_M_S2 = np.array([0.0, 0.0, -9.81])


class ImuMotion(Protocol):
    """A body trajectory with exact derivatives (times int64 ns on the IMU clock)."""

    def rotation_and_rate(self, t_ns: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(N,3,3) `world_from_body` rotations and (N,3) body angular rates (rad/s)."""
        ...

    def acceleration_m_s2(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,3) acceleration of the body origin in the world (m/s^2), gravity not included."""
        ...


@dataclass(frozen=True)
class RandomBias:
    """An initial bias of this norm (rad/s or m/s^2) in a direction drawn from the rng."""

    norm: float


@dataclass
class SimulatedImu(ImuSamples):
    """IMU samples (`shared.imu.ImuSamples`) with the true biases inside them.

    gyro_bias_rad_s, accel_bias_m_s2: (N,3) the biases at each sample.
    """

    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray


def ideal_imu(
    motion: ImuMotion,
    stamps_ns: npt.ArrayLike,
    *,
    gravity_w_m_s2: npt.ArrayLike = GRAVITY_W_M_S2,
) -> tuple[FloatArray, FloatArray]:
    """Noise-free (gyro (N,3) rad/s, accel (N,3) m/s^2) of `motion` at `stamps_ns`."""
    rotation, omega = motion.rotation_and_rate(stamps_ns)
    accel_w = motion.acceleration_m_s2(stamps_ns) - np.asarray(gravity_w_m_s2)[None, :]
    accel_b = np.einsum("nji,nj->ni", rotation, accel_w)
    return omega, accel_b


def _initial_bias(bias0: npt.ArrayLike | RandomBias, rng: np.random.Generator | None) -> FloatArray:
    if not isinstance(bias0, RandomBias):
        return np.asarray(bias0, dtype=np.float64)
    if rng is None:
        raise ValueError("simulate_imu: a RandomBias needs an rng")
    direction = rng.normal(size=3)
    unit: FloatArray = direction / np.linalg.norm(direction)
    return bias0.norm * unit


def simulate_imu(
    motion: ImuMotion,
    stamps_ns: npt.ArrayLike,
    *,
    noise: ImuNoise | None,
    rng: np.random.Generator | None = None,
    gyro_bias0_rad_s: npt.ArrayLike | RandomBias = (0.0, 0.0, 0.0),
    accel_bias0_m_s2: npt.ArrayLike | RandomBias = (0.0, 0.0, 0.0),
    gravity_w_m_s2: npt.ArrayLike = GRAVITY_W_M_S2,
    walk_before_first: bool = False,
) -> SimulatedImu:
    """IMU samples at `stamps_ns` (int64 ns, the motion's clock, evenly spaced).

    noise: Kalibr noise densities (None: ideal measurements with constant initial biases);
    rng: the random source (required with `noise` or a `RandomBias`); *_bias0: the biases
    at the first sample, fixed or `RandomBias`; walk_before_first: the bias walk has
    already taken one step at the first sample (the feature-level sequences of
    `sim.features` were generated so).

    The rng is drawn in this order: the gyro's random bias direction (if any), its walk
    (N,3), the accelerometer's direction and walk, then the gyro's and the
    accelerometer's white noise (N,3 each).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    gyro, accel = ideal_imu(motion, stamps, gravity_w_m_s2=gravity_w_m_s2)
    n = len(stamps)
    if noise is not None and rng is None:
        raise ValueError("simulate_imu: noise given without an rng")
    gyro_bias = np.tile(_initial_bias(gyro_bias0_rad_s, rng), (n, 1))
    if noise is not None and rng is not None:
        dt = 1.0 / noise.update_rate_hz
        walk_g = noise.gyroscope_random_walk * np.sqrt(dt) * rng.standard_normal((n, 3))
        if not walk_before_first:
            walk_g[0] = 0.0
        gyro_bias += np.cumsum(walk_g, axis=0)
    accel_bias = np.tile(_initial_bias(accel_bias0_m_s2, rng), (n, 1))
    if noise is not None and rng is not None:
        walk_a = noise.accelerometer_random_walk * np.sqrt(dt) * rng.standard_normal((n, 3))
        if not walk_before_first:
            walk_a[0] = 0.0
        accel_bias += np.cumsum(walk_a, axis=0)
        gyro = gyro + noise.gyroscope_noise_density / np.sqrt(dt) * rng.standard_normal((n, 3))
        accel = accel + noise.accelerometer_noise_density / np.sqrt(dt) * rng.standard_normal(
            (n, 3)
        )
    return SimulatedImu(
        stamps_ns=stamps,
        gyro_rad_s=gyro + gyro_bias,
        accel_m_s2=accel + accel_bias,
        gyro_bias_rad_s=gyro_bias,
        accel_bias_m_s2=accel_bias,
    )
