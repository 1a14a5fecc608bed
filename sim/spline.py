"""Smooth continuous trajectories: uniform B-splines on R^3 and cumulative B-splines on SO(3).

Pure math, no I/O. A `SplineTrajectory` gives the pose of the body (IMU) frame in the
world, `world_from_body(t)`, and its exact derivatives (world velocity and acceleration,
body angular rate) at any time, so the simulated IMU is computed from the same functions
that the rendered images come from, not from finite differences.

Position: p(t) = sum_j B_j(u) c_{i+j}, a uniform B-spline of order k (degree k-1) with
knot spacing `knot_interval_s`; u in [0, 1) is the fraction of segment i.

Rotation: the cumulative form on SO(3),
    R(t) = R_i * prod_{j=1}^{k-1} exp(Btilde_j(u) * d_j),   d_j = log(R_{i+j-1}^T R_{i+j}),
whose body angular velocity follows the recursion w <- A_j^T w + Btilde_j'(u)/dt * d_j with
A_j = exp(Btilde_j(u) d_j) (Sommer et al., "Efficient Derivative Computation for
Cumulative B-Splines on Lie Groups", CVPR 2020).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.clock import ns_from_seconds, seconds_from_ns
from shared.geometry import so3_exp, so3_log

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def bspline_basis_matrix(order: int) -> FloatArray:
    """Blending matrix M (order x order) of a uniform B-spline: weights_j(u) = sum_n M[j,n] u^n.

    Row j is the control point offset inside a segment, column n the power of u.
    """
    k = order
    m = np.zeros((k, k), dtype=np.float64)
    for j in range(k):
        for n in range(k):
            total = 0.0
            for s in range(j, k):
                total += (-1) ** (s - j) * math.comb(k, s - j) * (k - s - 1) ** (k - 1 - n)
            m[j, n] = math.comb(k - 1, n) * total / math.factorial(k - 1)
    return m


def cumulative_basis_matrix(order: int) -> FloatArray:
    """Cumulative blending matrix: Mtilde[j, n] = sum_{s >= j} M[s, n] (row 0 is the constant 1)."""
    m = bspline_basis_matrix(order)
    return np.cumsum(m[::-1], axis=0)[::-1].copy()


def _power_rows(u: FloatArray, order: int, derivative: int) -> FloatArray:
    """(N, order) rows of d^m/du^m [1, u, u^2, ...] for each u."""
    powers = np.zeros((u.size, order), dtype=np.float64)
    for n in range(derivative, order):
        coef = math.perm(n, derivative)
        powers[:, n] = coef * u ** (n - derivative)
    return powers


@dataclass(frozen=True)
class SplineTrajectory:
    """Pose of the body in the world as uniform B-splines (position) and cumulative SO(3).

    start_ns: time of the start of the first segment, int64 ns (the trajectory's clock).
    knot_interval_s: segment length in seconds.
    position_ctrl_m: (M, 3) position control points in the world (m).
    rotation_ctrl: (M, 3, 3) rotation control points `world_from_body`.
    order: spline order k (4 = cubic, 6 = quintic); valid over M - k + 1 segments.
    """

    start_ns: int
    knot_interval_s: float
    position_ctrl_m: FloatArray
    rotation_ctrl: FloatArray
    order: int = 6

    def __post_init__(self) -> None:
        if self.position_ctrl_m.ndim != 2 or self.position_ctrl_m.shape[1] != 3:
            raise ValueError(f"position_ctrl_m: expected (M,3), got {self.position_ctrl_m.shape}")
        if self.rotation_ctrl.shape != (len(self.position_ctrl_m), 3, 3):
            raise ValueError(
                f"rotation_ctrl: expected ({len(self.position_ctrl_m)},3,3), "
                f"got {self.rotation_ctrl.shape}"
            )
        if len(self.position_ctrl_m) < self.order:
            raise ValueError(f"need at least {self.order} control points")
        if self.knot_interval_s <= 0:
            raise ValueError("knot_interval_s must be positive")

    @property
    def num_segments(self) -> int:
        return len(self.position_ctrl_m) - self.order + 1

    @property
    def end_ns(self) -> int:
        """End of the valid time range (int64 ns, exclusive)."""
        return self.start_ns + ns_from_seconds(self.num_segments * self.knot_interval_s)

    def _segments(self, t_ns: npt.ArrayLike) -> tuple[IntArray, FloatArray]:
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        if t.size and (t.min() < self.start_ns or t.max() > self.end_ns):
            raise ValueError(
                f"time outside the spline's range [{self.start_ns}, {self.end_ns}] ns: "
                f"[{t.min()}, {t.max()}]"
            )
        x = seconds_from_ns(t - self.start_ns) / self.knot_interval_s
        seg = np.minimum(np.floor(x).astype(np.int64), self.num_segments - 1)
        return seg, x - seg

    def _position_derivative(self, t_ns: npt.ArrayLike, derivative: int) -> FloatArray:
        seg, u = self._segments(t_ns)
        m = bspline_basis_matrix(self.order)
        weights = _power_rows(u, self.order, derivative) @ m.T  # (N, k)
        idx = seg[:, None] + np.arange(self.order)[None, :]
        out: FloatArray = np.einsum("nk,nkd->nd", weights, self.position_ctrl_m[idx])
        return out / self.knot_interval_s**derivative

    def position_m(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,3) body position in the world (m) at times t_ns (int64 ns)."""
        return self._position_derivative(t_ns, 0)

    def velocity_m_s(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,3) body velocity in the world (m/s)."""
        return self._position_derivative(t_ns, 1)

    def acceleration_m_s2(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,3) body acceleration in the world (m/s^2), gravity not included."""
        return self._position_derivative(t_ns, 2)

    def rotation_and_rate(self, t_ns: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        seg, u = self._segments(t_ns)
        mt = cumulative_basis_matrix(self.order)
        lam = _power_rows(u, self.order, 0) @ mt.T  # (N, k)
        dlam = _power_rows(u, self.order, 1) @ mt.T / self.knot_interval_s
        rotation = self.rotation_ctrl[seg].copy()
        omega = np.zeros((len(seg), 3), dtype=np.float64)
        for j in range(1, self.order):
            prev = self.rotation_ctrl[seg + j - 1]
            cur = self.rotation_ctrl[seg + j]
            d = so3_log(np.swapaxes(prev, 1, 2) @ cur)
            a = so3_exp(lam[:, j, None] * d)
            rotation = rotation @ a
            omega = np.einsum("nji,nj->ni", a, omega) + dlam[:, j, None] * d
        return rotation, omega

    def rotation(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,3,3) `world_from_body` rotations."""
        return self.rotation_and_rate(t_ns)[0]

    def angular_velocity_body_rad_s(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,3) angular velocity of the body in the body frame (rad/s): what a gyro measures."""
        return self.rotation_and_rate(t_ns)[1]

    def world_from_body(self, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,4,4) poses `world_from_body` at times t_ns (int64 ns)."""
        rotation, _ = self.rotation_and_rate(t_ns)
        poses = np.tile(np.eye(4), (len(rotation), 1, 1))
        poses[:, :3, :3] = rotation
        poses[:, :3, 3] = self.position_m(t_ns)
        return poses
