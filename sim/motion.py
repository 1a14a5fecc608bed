"""Diver-like camera motion around the simulated wreck, as smooth splines.

Pure math, no I/O. A `DiverRoute` is a polyline of camera positions with a point to look at
for each; `diver_trajectory` turns it into a `SplineTrajectory` of the body (IMU) frame:
swimming at 0.2-0.45 m/s with a fin-kick rhythm in the speed, smoothed turns, slight
bobbing and sway, a camera that looks at the wreck (roll near zero) with small hand-held
wobbles. The routes of the built-in sessions pass both AprilGrids at 1.5-2.5 m and overlap
partly (the starboard hull and the bridge are seen in both).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from shared.clock import ns_from_seconds
from shared.geometry import look_at, so3_exp
from sim.spline import SplineTrajectory

FloatArray = npt.NDArray[np.float64]

_FINE_DT_S = 0.02


@dataclass(frozen=True)
class DiverRoute:
    """Where a diver swims (camera positions, m, world) and what the camera looks at."""

    name: str
    waypoints_m: tuple[tuple[float, float, float], ...]
    look_at_m: tuple[tuple[float, float, float], ...]


#: Session 0 swims aft along the starboard hull past the 4x2 grid, then up to the bridge
#: and its 5x4 grid. Session 1 crosses the deck from the stern, passes the bridge (5x4
#: grid), the mast and the hatches, and comes down the starboard side to the 4x2 grid.
BUILTIN_ROUTES: tuple[DiverRoute, ...] = (
    DiverRoute(
        "starboard_hull_to_bridge",
        (
            (9.0, 5.8, -14.6),
            (5.0, 5.5, -14.3),
            (2.9, 4.4, -14.5),
            (1.8, 4.3, -14.5),
            (-2.0, 5.4, -13.6),
            (-4.5, 4.9, -11.6),
            (-5.8, 3.4, -11.0),
            (-6.8, 3.4, -10.9),
            (-8.2, 4.8, -10.3),
            (-10.5, 5.6, -11.2),
        ),
        (
            (7.8, 3.5, -14.9),
            (3.8, 3.5, -14.6),
            (2.4, 3.5, -14.5),
            (2.0, 3.5, -14.5),
            (-3.0, 3.3, -14.2),
            (-5.5, 2.5, -11.3),
            (-6.2, 2.5, -11.1),
            (-6.4, 2.5, -11.1),
            (-8.8, 2.5, -10.8),
            (-11.5, 3.0, -12.8),
        ),
    ),
    DiverRoute(
        "deck_stern_to_bow_and_starboard",
        (
            (-12.5, 3.2, -10.2),
            (-10.0, 4.6, -10.1),
            (-6.9, 3.35, -10.9),
            (-5.6, 3.4, -10.9),
            (-3.0, 3.4, -10.2),
            (0.5, 2.2, -10.0),
            (4.0, 2.6, -9.9),
            (6.5, 5.0, -12.2),
            (3.0, 4.35, -14.3),
            (1.7, 4.4, -14.5),
            (0.5, 5.8, -14.5),
        ),
        (
            (-10.5, 0.0, -12.0),
            (-7.5, 2.5, -11.0),
            (-6.3, 2.5, -11.1),
            (-6.2, 2.5, -11.1),
            (-1.8, 0.5, -13.8),
            (2.0, 0.0, -11.6),
            (3.2, 0.0, -9.5),
            (4.8, 3.5, -14.0),
            (2.4, 3.5, -14.5),
            (2.2, 3.5, -14.6),
            (-0.8, 3.5, -14.8),
        ),
    ),
)


def builtin_route(index: int) -> DiverRoute:
    """Route of session `index`: the built-in ones, then the same mirrored to port (y -> -y)
    and shifted along the hull, so any number of sessions overlap partly."""
    base = BUILTIN_ROUTES[index % len(BUILTIN_ROUTES)]
    cycle = index // len(BUILTIN_ROUTES)
    if cycle == 0:
        return base
    sign = -1.0 if cycle % 2 == 1 else 1.0
    shift = 1.5 * (cycle // 2)

    def moved(
        points: tuple[tuple[float, float, float], ...],
    ) -> tuple[tuple[float, float, float], ...]:
        return tuple((x + shift, sign * y, z) for x, y, z in points)

    return DiverRoute(f"{base.name}_{cycle}", moved(base.waypoints_m), moved(base.look_at_m))


def _gaussian_smooth(values: FloatArray, sigma_samples: float) -> FloatArray:
    """Smooth each column of (N, D) `values` with a Gaussian (edges held)."""
    radius = int(np.ceil(4 * sigma_samples))
    kernel = cv2.getGaussianKernel(2 * radius + 1, sigma_samples).ravel()
    padded = np.pad(values, ((radius, radius), (0, 0)), mode="edge")
    out = np.empty_like(values)
    for d in range(values.shape[1]):
        out[:, d] = np.convolve(padded[:, d], kernel, mode="valid")
    return out


def _ping_pong(arc: FloatArray, length: float) -> FloatArray:
    """Arc length folded onto [0, length] (the diver turns back at each end)."""
    period = np.mod(arc, 2.0 * length)
    return np.where(period <= length, period, 2.0 * length - period)


def _smooth_noise(
    rng: np.random.Generator, t: FloatArray, amplitude: float, period_s: float
) -> FloatArray:
    """A smooth random signal of about `amplitude` with features every `period_s` seconds."""
    knots = np.arange(t[0] - period_s, t[-1] + 2 * period_s, period_s)
    values = rng.normal(0.0, amplitude, size=len(knots))
    # Catmull-Rom interpolation keeps the signal C1; the spline fit smooths it further.
    index = (t - knots[0]) / period_s
    i0 = np.clip(np.floor(index).astype(int), 1, len(knots) - 3)
    u = index - i0
    p0, p1, p2, p3 = values[i0 - 1], values[i0], values[i0 + 1], values[i0 + 2]
    signal: FloatArray = 0.5 * (
        2 * p1
        + (-p0 + p2) * u
        + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2
        + (-p0 + 3 * p1 - 3 * p2 + p3) * u**3
    )
    return signal


def look_rotation(forward_w: FloatArray) -> FloatArray:
    """(N,3,3) `world_from_cam` rotations with the camera z along `forward_w` and no roll
    (camera x horizontal, y pointing down as much as possible)."""
    rotation: FloatArray = look_at(np.zeros(3), forward_w)[:, :3, :3]
    return rotation


def diver_trajectory(
    route: DiverRoute,
    *,
    start_ns: int,
    duration_s: float,
    cam_from_imu: npt.ArrayLike,
    rng: np.random.Generator,
    speed_m_s: float = 0.35,
    knot_interval_s: float = 0.2,
    order: int = 6,
    margin_s: float = 2.0,
) -> SplineTrajectory:
    """The body (IMU) trajectory of a diver following `route` (world frame).

    Valid over [start_ns - margin_s, start_ns + duration_s + margin_s] so image times shifted
    by the camera-IMU time offset and the IMU's first and last samples stay inside.
    speed_m_s: mean swimming speed (m/s; the route is swum back when it is too short).
    """
    if duration_s <= 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    cam_from_imu_arr = np.asarray(cam_from_imu, dtype=np.float64)
    lead = (order - 2) / 2.0
    n_segments = int(np.ceil((duration_s + 2 * margin_s) / knot_interval_s))
    n_ctrl = n_segments + order - 1
    t0_s = -margin_s
    ctrl_t = t0_s + (np.arange(n_ctrl) - lead) * knot_interval_s
    fine_t = np.arange(ctrl_t[0] - 5.0, ctrl_t[-1] + 5.0, _FINE_DT_S)

    waypoints = np.asarray(route.waypoints_m, dtype=np.float64)
    look_at = np.asarray(route.look_at_m, dtype=np.float64)
    seg_len = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    cum = np.concatenate(([0.0], np.cumsum(seg_len)))
    length = float(cum[-1])
    # Fin kicks: speed pulses at ~0.45 Hz around the mean, never negative.
    kick_hz = rng.uniform(0.38, 0.5)
    phase = rng.uniform(0, 2 * np.pi)
    speed = speed_m_s * (1.0 + 0.25 * np.sin(2 * np.pi * kick_hz * fine_t + phase))
    speed += _smooth_noise(rng, fine_t, 0.04, 4.0)
    arc = np.cumsum(np.maximum(speed, 0.05)) * _FINE_DT_S
    arc -= np.interp(0.0, fine_t, arc)
    arc = _ping_pong(arc + 0.2, length)
    position = np.column_stack([np.interp(arc, cum, waypoints[:, d]) for d in range(3)])
    target = np.column_stack([np.interp(arc, cum, look_at[:, d]) for d in range(3)])
    sigma = 1.2 / _FINE_DT_S
    position = _gaussian_smooth(position, sigma)
    target = _gaussian_smooth(target, 1.6 / _FINE_DT_S)
    # Bobbing with the kicks and a slow sway.
    position[:, 2] += 0.06 * np.sin(2 * np.pi * kick_hz * fine_t + phase + 1.0)
    position[:, 2] += _smooth_noise(rng, fine_t, 0.08, 5.0)
    position[:, 0] += _smooth_noise(rng, fine_t, 0.05, 3.0)
    position[:, 1] += _smooth_noise(rng, fine_t, 0.05, 3.0)
    # Keep the look target in front: roll-free camera looking at it, then small wobbles.
    world_from_cam = look_rotation(target - position)
    wobble = np.column_stack(
        [
            _smooth_noise(rng, fine_t, np.deg2rad(2.5), 1.5),  # pitch (camera x)
            _smooth_noise(rng, fine_t, np.deg2rad(4.0), 2.0),  # yaw (camera y)
            _smooth_noise(rng, fine_t, np.deg2rad(2.5), 2.5),  # roll (camera z)
        ]
    )
    world_from_cam = world_from_cam @ so3_exp(wobble)
    # Sample the wanted camera motion at the control times; the body follows rigidly.
    pick = np.clip(np.rint((ctrl_t - fine_t[0]) / _FINE_DT_S).astype(int), 0, len(fine_t) - 1)
    rot_wc = world_from_cam[pick]
    pos_wc = position[pick]
    rot_wb = rot_wc @ cam_from_imu_arr[:3, :3]
    pos_wb = pos_wc + rot_wc @ cam_from_imu_arr[:3, 3]
    return SplineTrajectory(
        start_ns=int(start_ns - ns_from_seconds(margin_s)),
        knot_interval_s=knot_interval_s,
        position_ctrl_m=pos_wb,
        rotation_ctrl=rot_wb,
        order=order,
    )
