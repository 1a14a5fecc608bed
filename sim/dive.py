"""A dive computer's log of a simulated dive: the truth the depth sync is tested against.

Pure math, no I/O. The diver's depth is `-z_W` of the body (IMU) origin during the filmed
part (`SplineTrajectory`), preceded by a descent from the surface and followed by an
ascent with a safety stop, so the profile looks like a dive. The dive computer samples
every `sample_interval_s` on *its own clock* (`ClockModel` from true time: an offset from
seconds to hours, as a zone error gives, and a drift of up to +-50 ppm), quantises depth
to 0.1 m and adds sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.clock import ClockModel
from shared.formats.diveprofile import DiveProfile, stamp_s_to_iso
from sim.spline import SplineTrajectory

FloatArray = npt.NDArray[np.float64]


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
    rel_s = (t - film_start_ns).astype(np.float64) * 1e-9
    after_s = (t - film_end_ns).astype(np.float64) * 1e-9
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
    start = film_start_ns - round((options.descent_s + options.bottom_before_s) * 1e9)
    return start, film_end_ns + round(after_s * 1e9)


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
    start_dc_s = float(np.floor(clock.apply(dive_start) * 1e-9))
    end_dc_s = clock.apply(dive_end) * 1e-9
    stamps_dc_s = start_dc_s + options.sample_interval_s * np.arange(
        1, int((end_dc_s - start_dc_s) / options.sample_interval_s) + 1
    )
    stamps_dc_ns = np.rint(stamps_dc_s * 1e9).astype(np.int64)
    true_ns = clock.inverse(stamps_dc_ns)
    depth = true_depth_m(trajectory, film_start_ns, film_end_ns, true_ns, options)
    noisy = depth + rng.normal(0.0, options.depth_noise_m, size=depth.shape)
    logged = np.maximum(np.round(noisy / options.depth_step_m) * options.depth_step_m, 0.0)
    # Water temperature: warm surface layer over a thermocline at about 8 m.
    temperature = 14.0 + 5.0 / (1.0 + np.exp((depth - 8.0) / 1.5))
    temperature = np.round(temperature + rng.normal(0.0, 0.05, size=depth.shape), 1)
    start_iso = stamp_s_to_iso(start_dc_s)
    return DiveProfile(
        stamps_s=np.asarray(stamps_dc_s, dtype=np.float64),
        depth_m=np.asarray(np.round(logged, 1), dtype=np.float64),
        temperature_c=temperature,
        start_iso=start_iso,
        model=options.model,
        serial=options.serial,
        fingerprint=f"{int(start_dc_s) & 0xFFFFFFFF:08X}",
        source=source,
        sample_interval_s=options.sample_interval_s,
    )
