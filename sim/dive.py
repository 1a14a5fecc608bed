"""Simulated dives and the dive computer's log of them: the truth the depth stage is tested on.

Pure math, no I/O. One dive-computer model: it samples every `sample_interval_s` on *its
own clock* (an offset from seconds to hours, as a zone error gives, and a drift of up to
+-50 ppm), adds sensor noise (and, if asked, spikes), quantises depth to 0.1 m and never
logs above the surface (`log_depth`, `logged_profile`). Two dives feed it:

- the survey's (`simulate_dive_profile`, used by `sim.survey`): the diver's depth is `-z_W`
  of the body (IMU) origin during the filmed part (`SplineTrajectory`), preceded by a
  descent from the surface and followed by an ascent with a safety stop; the computer's
  clock is a `ClockModel` of true time;
- the depth stage's (`simulate_dive`, for its tests and bench): a whole dive, descent, a
  bottom phase wandering between about 6 and 18 m (slow changes of tens of metres a
  minute plus finning bobs of a few centimetres), an ascent with a safety stop; the
  camera trajectory covers part of it on the camera clock, expressed in a VIO frame
  (gravity aligned, origin and yaw at the first pose) with optional VIO drift in z; the
  computer's clock is an offset and drift against the camera clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.clock import NS_PER_S, ClockModel, ns_from_seconds, seconds_from_ns
from shared.formats.diveprofile import DiveProfile, stamp_s_to_iso
from shared.geometry import make_pose
from shared.trajectory import Trajectory
from sim.spline import SplineTrajectory

FloatArray = npt.NDArray[np.float64]

CAMERA_EPOCH_S = 1_700_000_000.0


def log_depth(
    depth_m: FloatArray,
    rng: np.random.Generator,
    *,
    noise_m: float,
    step_m: float = 0.1,
    outlier_fraction: float | None = None,
) -> FloatArray:
    """What the computer logs of true depths (m): Gaussian noise of `noise_m`, then (with
    `outlier_fraction`, even 0) that share of spikes 1-5 m too deep, quantised to `step_m`
    and to 0.1 m, never above the surface. Draws the noise, then the spikes, from `rng`."""
    noisy = depth_m + rng.normal(0.0, noise_m, size=depth_m.shape)
    if outlier_fraction is not None:
        spikes = rng.random(noisy.size) < outlier_fraction
        noisy[spikes] += rng.uniform(1.0, 5.0, int(spikes.sum()))
    logged: FloatArray = np.maximum(np.round(np.round(noisy / step_m) * step_m, 1), 0.0)
    return logged


def logged_profile(
    stamps_s: npt.ArrayLike,
    depth_m: npt.ArrayLike,
    temperature_c: npt.ArrayLike,
    *,
    start_s: float,
    model: str,
    serial: str,
    source: str,
    sample_interval_s: float,
) -> DiveProfile:
    """The dive as the computer stores it: samples on its clock (seconds since the epoch),
    the start (its clock, whole seconds) and a fingerprint made from the start."""
    return DiveProfile(
        stamps_s=np.asarray(stamps_s, dtype=np.float64),
        depth_m=np.asarray(depth_m, dtype=np.float64),
        temperature_c=np.asarray(temperature_c, dtype=np.float64),
        start_iso=stamp_s_to_iso(start_s),
        model=model,
        serial=serial,
        fingerprint=f"{int(start_s) & 0xFFFFFFFF:08X}",
        source=source,
        sample_interval_s=sample_interval_s,
    )


# ----------------------------------------------------------------- the survey's dive


@dataclass(kw_only=True)
class DiveComputerOptions:
    """Simulated dive computer.

    sample_interval_s: logging interval (Shearwater: 10 s); depth_step_m: resolution of the
    logged depth; depth_noise_m: standard deviation of the sensor noise (m);
    descent_s / bottom_before_s: time from the surface to the filming depth / hovering
    there before filming starts; bottom_after_s, ascent_rate_m_s, safety_stop_*: after.
    """

    sample_interval_s: float = 10.0
    depth_step_m: float = 0.1
    depth_noise_m: float = 0.04
    descent_s: float = 150.0
    bottom_before_s: float = 120.0
    bottom_after_s: float = 90.0
    ascent_rate_m_s: float = 0.15
    safety_stop_depth_m: float = 5.0
    safety_stop_s: float = 180.0
    model: str = "Shearwater Perdix 2"
    serial: str = "5A1B2C3D"


def true_depth_m(
    trajectory: SplineTrajectory,
    film_start_ns: int,
    film_end_ns: int,
    t_ns: npt.ArrayLike,
    options: DiveComputerOptions,
) -> FloatArray:
    """The diver's true depth (m, positive down) at true times `t_ns` over the whole dive."""
    t = np.asarray(t_ns, dtype=np.int64)
    first = float(-trajectory.position_m([film_start_ns])[0, 2])
    last = float(-trajectory.position_m([film_end_ns])[0, 2])
    depth = np.zeros(t.shape, dtype=np.float64)
    rel_s = seconds_from_ns(t - film_start_ns)
    after_s = seconds_from_ns(t - film_end_ns)
    filming = (t >= film_start_ns) & (t <= film_end_ns)
    if filming.any():
        depth[filming] = -trajectory.position_m(t[filming])[:, 2]
    before = t < film_start_ns
    # Descent with eased ends, then hovering a little deeper than the filming start.
    hover = first + 0.6
    descent_end = -options.bottom_before_s
    descent_start = descent_end - options.descent_s
    x = np.clip((rel_s - descent_start) / options.descent_s, 0.0, 1.0)
    eased = x * x * (3 - 2 * x)
    wander = 0.3 * np.sin(rel_s / 37.0) * np.clip(-rel_s / 30.0, 0.0, 1.0)
    blend = np.clip((rel_s - descent_end) / options.bottom_before_s, 0.0, 1.0)
    depth_before = eased * hover + wander + blend * (first - hover)
    depth[before] = depth_before[before]
    after = t > film_end_ns
    stop_m = options.safety_stop_depth_m
    leave_s = options.bottom_after_s
    to_stop_s = max(last - stop_m, 0.0) / options.ascent_rate_m_s
    stop_end_s = leave_s + to_stop_s + options.safety_stop_s
    surface_s = stop_end_s + stop_m / options.ascent_rate_m_s
    depth_after = np.select(
        [
            after_s <= leave_s,
            after_s <= leave_s + to_stop_s,
            after_s <= stop_end_s,
            after_s <= surface_s,
        ],
        [
            last + 0.4 * np.sin(after_s / 23.0),
            last - (after_s - leave_s) * options.ascent_rate_m_s,
            np.full_like(after_s, stop_m),
            stop_m - (after_s - stop_end_s) * options.ascent_rate_m_s,
        ],
        0.0,
    )
    # Join the filmed part smoothly: the wander term starts at zero.
    depth[after] = np.maximum(depth_after[after], 0.0)
    return np.maximum(depth, 0.0)


def dive_timeline_ns(
    film_start_ns: int, film_end_ns: int, trajectory: SplineTrajectory, options: DiveComputerOptions
) -> tuple[int, int]:
    """(dive start, dive end) in true time (int64 ns): surface to surface."""
    last = float(-trajectory.position_m([film_end_ns])[0, 2])
    to_stop_s = max(last - options.safety_stop_depth_m, 0.0) / options.ascent_rate_m_s
    after_s = (
        options.bottom_after_s
        + to_stop_s
        + options.safety_stop_s
        + options.safety_stop_depth_m / options.ascent_rate_m_s
    )
    start = film_start_ns - ns_from_seconds(options.descent_s + options.bottom_before_s)
    return start, film_end_ns + ns_from_seconds(after_s)


def simulate_dive_profile(
    trajectory: SplineTrajectory,
    *,
    film_start_ns: int,
    film_end_ns: int,
    clock: ClockModel,
    options: DiveComputerOptions,
    rng: np.random.Generator,
    source: str = "wreckmap simulator",
) -> DiveProfile:
    """The dive as the computer logs it (stamps on its clock, `clock` maps true -> computer).

    The computer starts logging at the dive start (its clock, whole seconds) and samples every
    `sample_interval_s` of its own clock until the diver surfaces.
    """
    dive_start, dive_end = dive_timeline_ns(film_start_ns, film_end_ns, trajectory, options)
    start_dc_s = float(clock.apply(dive_start) // NS_PER_S)
    end_dc_s = seconds_from_ns(clock.apply(dive_end))
    stamps_dc_s = start_dc_s + options.sample_interval_s * np.arange(
        1, int((end_dc_s - start_dc_s) / options.sample_interval_s) + 1
    )
    stamps_dc_ns = ns_from_seconds(stamps_dc_s)
    true_ns = clock.inverse(stamps_dc_ns)
    depth = true_depth_m(trajectory, film_start_ns, film_end_ns, true_ns, options)
    logged = log_depth(depth, rng, noise_m=options.depth_noise_m, step_m=options.depth_step_m)
    # Water temperature: warm surface layer over a thermocline at about 8 m.
    temperature = 14.0 + 5.0 / (1.0 + np.exp((depth - 8.0) / 1.5))
    temperature = np.round(temperature + rng.normal(0.0, 0.05, size=depth.shape), 1)
    return logged_profile(
        stamps_dc_s,
        logged,
        temperature,
        start_s=start_dc_s,
        model=options.model,
        serial=options.serial,
        source=source,
        sample_interval_s=options.sample_interval_s,
    )


# ----------------------------------------------------------- the depth stage's dive


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
    # Rounded on the product (a 256 ns grid at this epoch), not by ns_from_seconds: the
    # simulated dives, their tests and bench_depth's figures stay as they were.
    stamps_ns = np.rint((CAMERA_EPOCH_S + rel) * NS_PER_S).astype(np.int64)
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
        d = log_depth(d, rng, noise_m=depth_noise_m, outlier_fraction=outlier_fraction)
        if surface_break:
            # Dive computers stop logging near the surface.
            keep = d >= 0.5
            v, d = v[keep], d[keep]
        dives.append(
            logged_profile(
                v,
                d,
                np.full(d.size, 27.0),
                start_s=start_dive,
                model="Simulated Perdix",
                serial="SIM0001",
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
