"""Synthetic dives with known truth, for the tests and the benchmark of the depth stage.

A diver swims over a wreck: descent, a bottom phase wandering between about
6 and 18 m (slow changes of tens of metres a minute plus finning bobs of a few
centimetres), an ascent with a safety stop. The camera trajectory covers part
of the dive on the camera clock, expressed in a VIO frame (gravity aligned,
origin and yaw at the first pose) with an optional random walk in z (VIO
drift). The dive computer logs every `sample_interval_s` on its own clock
(offset and drift against the camera), quantised to 0.1 m, with noise and a
few spikes. Pure math, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.formats.diveprofile import DiveProfile, stamp_s_to_iso
from shared.geometry import make_pose
from shared.trajectory import Trajectory

FloatArray = npt.NDArray[np.float64]

CAMERA_EPOCH_S = 1_700_000_000.0


@dataclass
class SyntheticDive:
    """A simulated dive and its truth.

    trajectory: the VIO estimate, camera clock, frame S (z = 0 at the first pose).
    truth_world: the true poses in the world frame (z = -depth), same stamps.
    dives: the dive computer's log, oldest first; `dive_index` is the one that overlaps.
    time_offset_s, drift_ppm: the dive clock against the camera clock at the
        trajectory's first stamp (dive minus camera).
    depth_offset_m: true depth of the first pose (the origin of S).
    """

    trajectory: Trajectory
    truth_world: Trajectory
    dives: list[DiveProfile]
    dive_index: int
    time_offset_s: float
    drift_ppm: float
    depth_offset_m: float


def _smooth(x: FloatArray, sigma_samples: float) -> FloatArray:
    radius = int(4 * sigma_samples) + 1
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_samples) ** 2)
    k /= k.sum()
    padded = np.concatenate([np.full(radius, x[0]), x, np.full(radius, x[-1])])
    return np.convolve(padded, k, mode="valid")


def _dive_depth(
    rng: np.random.Generator,
    t: FloatArray,
    *,
    flat: bool,
    surface_break: bool,
    bottom_range_m: float | None = None,
) -> FloatArray:
    """True depth (m) on a 1 s grid t (seconds from the dive start).

    `bottom_range_m`: the bottom phase wanders over this many metres (peak to
    peak of the slow changes; the finning bobs come on top) instead of 6-18 m.
    """
    total = t[-1]
    bottom_start, bottom_end = 120.0, total - 420.0
    if flat:
        bottom = np.full_like(t, 12.0)
    elif bottom_range_m is not None:
        # A diver holding one depth along a wreck's deck: slow changes of a metre or so.
        wander = np.zeros_like(t)
        for _ in range(4):
            period = rng.uniform(90.0, 600.0)
            wander += rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * t / period + rng.uniform(0, 6.3))
        during = (t >= bottom_start) & (t <= bottom_end)
        low, high = float(wander[during].min()), float(wander[during].max())
        bottom = rng.uniform(10.0, 13.0) + bottom_range_m * (wander - low) / (high - low)
    else:
        bottom = np.full_like(t, rng.uniform(10.0, 13.0))
        for _ in range(6):
            period = rng.uniform(60.0, 600.0)
            bottom += rng.uniform(0.5, 2.0) * np.sin(2 * np.pi * t / period + rng.uniform(0, 6.3))
        bottom = np.clip(bottom, 6.0, 18.0)
    depth = np.where(
        t < bottom_start, bottom[np.searchsorted(t, bottom_start)] * t / bottom_start, bottom
    )
    # Ascent: to a 5 m safety stop (3 min), then to the surface.
    stop_start = bottom_end + 120.0
    ascent = (t >= bottom_end) & (t < stop_start)
    depth[ascent] = np.interp(t[ascent], [bottom_end, stop_start], [bottom[t >= bottom_end][0], 5])
    depth[(t >= stop_start) & (t < stop_start + 180.0)] = 5.0
    last = t >= stop_start + 180.0
    depth[last] = np.interp(t[last], [stop_start + 180.0, total], [5.0, 0.0])
    if surface_break:
        # The diver goes up to the surface for two minutes in the middle of the dive.
        mid = 0.5 * (bottom_start + bottom_end)
        window = np.clip(1.0 - np.abs(t - mid) / 180.0, 0.0, 1.0)
        depth = depth * (1.0 - np.minimum(1.0, 2.0 * window))
    depth = _smooth(depth, 8.0)
    if not flat:
        # Finning bobs: a few centimetres at periods of seconds.
        depth += 0.05 * np.sin(2 * np.pi * t / 4.0) + 0.03 * np.sin(2 * np.pi * t / 9.0 + 1.0)
    return np.maximum(depth, 0.0)


def simulate_dive(
    *,
    seed: int,
    time_offset_s: float,
    drift_ppm: float = 0.0,
    dive_duration_s: float = 2700.0,
    trajectory_start_s: float = 240.0,
    trajectory_duration_s: float = 1800.0,
    rate_hz: float = 5.0,
    sample_interval_s: float = 10.0,
    depth_noise_m: float = 0.05,
    outlier_fraction: float = 0.01,
    vio_z_drift_m_per_sqrt_s: float = 0.0,
    earlier_dives: int = 0,
    surface_break: bool = False,
    flat: bool = False,
    bottom_range_m: float | None = None,
    vio_z_drift_per_m: float = 0.0,
    vio_z_wobble_m: float = 0.0,
) -> SyntheticDive:
    """Simulate one dive (plus `earlier_dives` on the same day, 1 h surface intervals).

    `trajectory_start_s` is when the camera trajectory starts after the dive
    start (seconds); the camera clock reads CAMERA_EPOCH_S at the dive start.
    `flat`: the bottom phase at exactly 12 m (nothing to sync on);
    `bottom_range_m`: the bottom phase wanders over this many metres only.
    VIO z error, besides the random walk `vio_z_drift_m_per_sqrt_s`: a steady
    drift of `vio_z_drift_per_m` metres per metre swum (up or down at random;
    0.004 is the 0.4 % of the distance a good VIO drifts) and a smooth wobble of
    `vio_z_wobble_m` RMS (Gaussian-correlated over about 10 s).
    """
    rng = np.random.default_rng(seed)
    t_dive = np.arange(0.0, dive_duration_s + 1.0, 1.0)
    depth_true = _dive_depth(
        rng, t_dive, flat=flat, surface_break=surface_break, bottom_range_m=bottom_range_m
    )

    # Camera trajectory (camera clock, absolute seconds).
    n = round(trajectory_duration_s * rate_hz) + 1
    rel = trajectory_start_s + np.arange(n) / rate_hz
    # A little jitter on the stamps, as a keyframe-based VIO has.
    rel[1:-1] += rng.uniform(-0.2, 0.2, n - 2) / rate_hz
    stamps_ns = np.rint((CAMERA_EPOCH_S + rel) * 1e9).astype(np.int64)
    z_world = -np.interp(rel, t_dive, depth_true)
    heading = np.cumsum(rng.normal(0.0, 0.02, n))
    speed = 0.3
    x = np.cumsum(speed * np.cos(heading) / rate_hz)
    y = np.cumsum(speed * np.sin(heading) / rate_hz)
    c, s = np.cos(heading), np.sin(heading)
    R = np.zeros((n, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    truth = Trajectory(stamps_ns, make_pose(R, np.column_stack([x, y, z_world])))

    # VIO frame: origin and yaw at the first pose, plus drift in z.
    R0 = R[0]
    p0 = truth.positions[0]
    positions = (truth.positions - p0) @ R0  # rows: R0.T @ (p - p0)
    if vio_z_drift_m_per_sqrt_s > 0.0:
        steps = rng.normal(0.0, vio_z_drift_m_per_sqrt_s / np.sqrt(rate_hz), n)
        steps[0] = 0.0
        positions[:, 2] += np.cumsum(steps)
    if vio_z_drift_per_m > 0.0:
        travelled_m = speed * (rel - rel[0])
        positions[:, 2] += rng.choice([-1.0, 1.0]) * vio_z_drift_per_m * travelled_m
    if vio_z_wobble_m > 0.0:
        wobble = _smooth(rng.normal(0.0, 1.0, n), 10.0 * rate_hz)
        wobble -= wobble[0]
        positions[:, 2] += vio_z_wobble_m * wobble / max(float(np.std(wobble)), 1e-12)
    vio = Trajectory(stamps_ns, make_pose(np.swapaxes(R0, 0, 1)[None] @ R, positions))

    # Dive computer: samples every interval on its own clock.
    t_ref = CAMERA_EPOCH_S + rel[0]
    dives: list[DiveProfile] = []
    for k in range(earlier_dives + 1):
        # Earlier dives: the same profile shape shifted back by dive + 1 h surface interval.
        back = (earlier_dives - k) * (dive_duration_s + 3600.0)
        start_cam = CAMERA_EPOCH_S - back
        start_dive = start_cam + time_offset_s + drift_ppm * 1e-6 * (start_cam - t_ref)
        start_dive = float(np.floor(start_dive))
        v = start_dive + sample_interval_s * np.arange(
            1, int(dive_duration_s / sample_interval_s) + 1
        )
        u = t_ref + (v - t_ref - time_offset_s) / (1.0 + drift_ppm * 1e-6)
        inside = (u >= start_cam) & (u <= start_cam + dive_duration_s)
        v, u = v[inside], u[inside]
        if k < earlier_dives:
            other = _dive_depth(
                rng, t_dive, flat=flat, surface_break=False, bottom_range_m=bottom_range_m
            )
            d = np.interp(u - start_cam, t_dive, other)
        else:
            d = np.interp(u - start_cam, t_dive, depth_true)
        d = d + rng.normal(0.0, depth_noise_m, d.size)
        spikes = rng.random(d.size) < outlier_fraction
        d[spikes] += rng.uniform(1.0, 5.0, int(spikes.sum()))
        d = np.maximum(np.round(d, 1), 0.0)
        if surface_break:
            # Dive computers stop logging near the surface.
            keep = d >= 0.5
            v, d = v[keep], d[keep]
        dives.append(
            DiveProfile(
                stamps_s=v,
                depth_m=d,
                temperature_c=np.full(d.size, 27.0),
                start_iso=stamp_s_to_iso(start_dive),
                model="Simulated Perdix",
                serial="SIM0001",
                fingerprint=f"{int(start_dive) & 0xFFFFFFFF:08X}",
                source=f"simulate_dive(seed={seed})",
                sample_interval_s=sample_interval_s,
            )
        )
    return SyntheticDive(
        trajectory=vio,
        truth_world=truth,
        dives=dives,
        dive_index=earlier_dives,
        time_offset_s=time_offset_s,
        drift_ppm=drift_ppm,
        depth_offset_m=float(-z_world[0]),
    )
