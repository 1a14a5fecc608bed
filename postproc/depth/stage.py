"""The depth stage: put a trajectory at its true depth with a dive computer's profile.

Inputs: any TUM trajectory in a gravity-aligned frame with z up (ours,
SVIn2's, ORB-SLAM3's with an IMU) on the camera clock, and a dive CSV or a
dive folder (`dives.json` plus CSVs; the dive that overlaps is found). The
depth estimated is the depth of the frame the TUM file holds: body (IMU)
poses for `trajectory.tum`, camera poses for `keyframes.tum`. The dive
computer on the wrist is taken to be at that frame's depth; the lever arm
between them is noise (`depth_sigma_m`).

Outputs in `out_dir`:

* `sync.json`: the dive-computer clock against the camera clock
  (`time_offset_s`: dive-computer time minus camera time at
  `reference_time_s`, the trajectory's first stamp; `drift_ppm`), the depth
  relation `depth = depth_offset_m - depth_scale * z`, the residual RMS, and
  one-sigma uncertainties (Gauss-Newton covariance scaled by the residual
  variance). `offset_ambiguity` says how well the data single out the offset
  (samples in the overlap, depth excursion in resolution steps, offset
  sigma, the best clearly different offset with its cost and depth, and the
  `evidence` between them); `clock_prior` whether the camera-against-dive
  wall-clock prior was available and used (then `search_ambiguity` holds the
  unrestricted search's measure). Written last: its presence means the stage
  is done. An ambiguous offset is a StageError (nothing written): a wrong one
  would put the whole dive metres off its depth, and the rest of the pipeline
  goes on without depth for the session (merge and SfM use depth only when
  every session has it).
* `trajectory_world.tum`: the trajectory in the world frame (z = -depth,
  0 at the surface; x, y, yaw and the camera clock kept).
* `trajectory_world_fused.tum` (when `fuse`): re-optimised with depth factors
  so vertical VIO drift is removed along the dive, not only shifted.
* `depth_sync.png`: before/after profiles and the regression scatter.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.depth.options import DepthOptions as DepthOptions
from postproc.depth.sync import (
    AmbiguityLimits,
    ClockPrior,
    ClockSolution,
    CoarseCandidate,
    DepthSync,
    OffsetAmbiguity,
    SyncError,
    fit_depth_sync,
    solve_clock_offset,
    valid_mask,
    z_rate_prior_sigma_m_per_s,
)
from shared.clock import NS_PER_S, ClockModel
from shared.errors import InputError, StageError
from shared.folders import DepthFolder, rebuild, result_stamp
from shared.formats.diveprofile import DiveProfile, read_dive_folder, read_profile
from shared.formats.svin import read_trajectory
from shared.trajectory import Trajectory

log = logging.getLogger(__name__)

# The names of the outputs, for sync.json (relative to the folder).
_FOLDER = DepthFolder(".")

# Wall-clock stamps before this (2000-01-01) are not dates: uptime, media time, relative seconds.
_EARLIEST_DATE_S = 946_684_800.0

_HINT = (
    "give the clock offset by hand with --time-offset SECONDS (dive-computer time minus camera "
    "time; options.time_offset_s), or check that the dive and the trajectory are of the same dive"
)


@dataclass
class _DiveData:
    profile: DiveProfile
    label: str
    t_s: npt.NDArray[np.float64]  # dive clock minus the reference, seconds
    depth_m: npt.NDArray[np.float64]


def run(
    options: DepthOptions,
    trajectory_path: Path | str,
    dive_path: Path | str,
    out_dir: Path | str,
    *,
    overwrite: bool = False,
) -> Path:
    """Estimate the dive clock and depth relation, write the world trajectory; returns sync.json.

    The resume rule of every stage (`shared.folders.rebuild`): a complete result of the
    same inputs and options is kept; another is refused unless `overwrite`, then rebuilt
    beside it and swapped in. Raises InputError for unreadable inputs, StageError when
    the dive does not overlap the trajectory or its profile is too flat to give a clock
    offset.
    """
    folder = DepthFolder(out_dir)
    _check_options(options)
    stamp = result_stamp("depth", options, trajectory=trajectory_path, dive=dive_path)
    with rebuild(folder, stamp, overwrite=overwrite) as work:
        if work is not None:
            _build(options, Path(trajectory_path), Path(dive_path), work)
    return folder.sync


def _build(options: DepthOptions, trajectory_path: Path, dive_path: Path, out: DepthFolder) -> None:
    """The depth stage itself, written into the empty folder `out`."""
    trajectory_text = read_trajectory(trajectory_path, format=options.trajectory_format)
    trajectory = trajectory_text.trajectory
    log.debug(
        "%s: %d poses, stamps read as %s (%s)",
        trajectory_path.name,
        len(trajectory),
        trajectory_text.stamps,
        trajectory_text.reason,
    )
    if len(trajectory) < 2:
        raise InputError(f"{trajectory_path}: {len(trajectory)} pose(s) (need at least 2)")
    reference_ns = int(trajectory.stamps_ns[0])
    traj_t = (trajectory.stamps_ns - reference_ns).astype(np.float64) / NS_PER_S
    traj_z = trajectory.positions[:, 2].copy()
    dives = _read_dives(dive_path, reference_ns)

    candidates: list[CoarseCandidate] = []
    solution: ClockSolution | None = None
    prior = _clock_prior(options, reference_ns, dives)
    if options.method == "paper":
        sync, dive = _paper(options, traj_t, traj_z, dives)
    elif options.time_offset_s is not None:
        sync, dive = _given_offset(options, traj_t, traj_z, dives)
    else:
        solution = _search(options, traj_t, traj_z, dives, prior)
        sync, dive, candidates = solution.sync, dives[solution.dive], solution.candidates

    scale_free: DepthSync | None = None
    if options.method == "ours" and not options.estimate_scale:
        scale_free = _fit(
            options,
            traj_t,
            traj_z,
            dive,
            sync.time_offset_s,
            time=False,
            scale=True,
            drift_ppm=sync.drift_ppm,
        )
        if abs(scale_free.depth_scale - 1.0) > max(3.0 * scale_free.depth_scale_sigma, 0.05):
            log.warning(
                "the depth data suggest a z scale of %.3f +- %.3f (kept at 1; "
                "use estimate_scale / --estimate-scale to apply it)",
                scale_free.depth_scale,
                scale_free.depth_scale_sigma,
            )

    world = _world_trajectory(trajectory, sync)
    out.write_world(world)
    fused: Trajectory | None = None
    sample_cam_t = sync.camera_time_s(dive.t_s)
    if options.fuse:
        fused = _fuse(options, traj_t, world, sample_cam_t, dive.depth_m)
        out.write_world_fused(fused)
    if options.plot:
        from postproc.depth.plots import plot_depth_sync

        plot_depth_sync(
            out.plot,
            traj_t_s=traj_t,
            traj_z_m=traj_z,
            dive_t_s=dive.t_s,
            dive_depth_m=dive.depth_m,
            sync=sync,
            fused_z_m=None if fused is None else fused.positions[:, 2],
            title=f"{trajectory_path.name} vs {dive.label} ({options.method})",
        )
    document = _sync_document(
        options,
        trajectory_path,
        dive,
        reference_ns,
        sync,
        scale_free,
        candidates,
        world,
        fused,
        traj_t,
        traj_z,
        sample_cam_t,
    )
    document["clock_prior"] = _prior_document(options, prior, solution)
    document["trajectory_read"] = {
        "stamps": trajectory_text.stamps,
        "reason": trajectory_text.reason,
        "pose_frame": trajectory_text.pose_frame,
        "warnings": list(trajectory_text.warnings),
    }
    document["offset_ambiguity"] = (
        None if solution is None else _ambiguity_document(solution.ambiguity, dives)
    )
    if solution is not None and solution.prior_used:
        document["search_ambiguity"] = _ambiguity_document(solution.search_ambiguity, dives)
    # sync.json last: the folder's completeness marker.
    out.write_sync(document)


def _check_options(options: DepthOptions) -> None:
    if options.method not in ("ours", "paper"):
        raise StageError(f"depth: unknown method {options.method!r} (expected 'ours' or 'paper')")
    positive = {
        "max_offset_s": options.max_offset_s,
        "depth_sigma_m": options.depth_sigma_m,
        "search_step_s": options.search_step_s,
        "node_interval_s": options.node_interval_s,
        "drift_prior_sigma_ppm": options.drift_prior_sigma_ppm,
        "max_gap_s": options.max_gap_s,
    }
    for name, value in positive.items():
        if not (value > 0.0 and math.isfinite(value)):
            raise StageError(f"depth: {name} must be a positive number, got {value}")
    if options.time_offset_s is not None and not math.isfinite(options.time_offset_s):
        raise StageError(f"depth: time_offset_s must be finite, got {options.time_offset_s}")
    window = options.clock_prior_window_s
    if window is not None and not (window > 0.0 and math.isfinite(window)):
        raise StageError(f"depth: clock_prior_window_s must be a positive number, got {window}")
    step = options.clock_prior_zone_step_s
    if not (step >= 0.0 and math.isfinite(step)):
        raise StageError(f"depth: clock_prior_zone_step_s must be 0 or more, got {step}")
    if not (options.min_evidence >= 0.0 and math.isfinite(options.min_evidence)):
        raise StageError(f"depth: min_evidence must be 0 or more, got {options.min_evidence}")
    if options.min_overlap_samples < 3:
        raise StageError(
            f"depth: min_overlap_samples must be at least 3, got {options.min_overlap_samples}"
        )


def _read_dives(path: Path, reference_ns: int) -> list[_DiveData]:
    if path.is_dir():
        profiles = read_dive_folder(path)
        labels = [f"{path.name}/{p.start_iso}" for p in profiles]
    else:
        profiles = [read_profile(path)]
        labels = [path.name]
    reference_s = reference_ns / NS_PER_S
    dives = []
    for profile, label in zip(profiles, labels, strict=True):
        keep = np.isfinite(profile.depth_m)
        if np.count_nonzero(keep) < 3:
            log.info("%s: fewer than 3 depth samples, skipped", label)
            continue
        dives.append(
            _DiveData(
                profile=profile,
                label=label,
                # Whole seconds first keeps float precision: both numbers are ~1.7e9.
                t_s=profile.stamps_s[keep] - reference_s,
                depth_m=profile.depth_m[keep],
            )
        )
    if not dives:
        raise InputError(f"{path}: no dive with at least 3 depth samples")
    return dives


def _fit(
    options: DepthOptions,
    traj_t: npt.NDArray[np.float64],
    traj_z: npt.NDArray[np.float64],
    dive: _DiveData,
    offset_s: float,
    *,
    time: bool,
    scale: bool,
    drift_ppm: float = 0.0,
) -> DepthSync:
    return fit_depth_sync(
        traj_t,
        traj_z,
        dive.t_s,
        dive.depth_m,
        initial_offset_s=offset_s,
        initial_drift_ppm=drift_ppm,
        estimate_time=time,
        estimate_drift=options.estimate_drift and time,
        estimate_scale=scale,
        drift_prior_sigma_ppm=options.drift_prior_sigma_ppm,
        z_rate_sigma_m_per_s=z_rate_prior_sigma_m_per_s(
            traj_t, options.odometry_sigma_m_per_sqrt_s
        ),
        max_gap_s=options.max_gap_s,
    )


def _clock_prior(
    options: DepthOptions, reference_ns: int, dives: list[_DiveData]
) -> ClockPrior | None:
    """The prior that both clocks read about the same wall-clock time, when it applies.

    The trajectory's stamps are the camera's clock (GoPro: its wall clock as
    set, usually local time) and the dive log holds the computer's wall clock
    read as UTC; equal readings give offset 0 in the stage's time base. Stamps
    that are not dates (a trajectory in seconds from zero) carry no prior.
    """
    if options.clock_prior_window_s is None:
        return None
    reference_s = reference_ns / NS_PER_S
    dive_starts = [d.profile.stamps_s[0] for d in dives if d.profile.stamps_s.size]
    if reference_s < _EARLIEST_DATE_S or min(dive_starts, default=0.0) < _EARLIEST_DATE_S:
        return None
    return ClockPrior(
        window_s=options.clock_prior_window_s, zone_step_s=options.clock_prior_zone_step_s
    )


def _search(
    options: DepthOptions,
    traj_t: npt.NDArray[np.float64],
    traj_z: npt.NDArray[np.float64],
    dives: list[_DiveData],
    prior: ClockPrior | None,
) -> ClockSolution:
    limits = AmbiguityLimits(
        min_evidence=options.min_evidence,
        min_samples=options.min_overlap_samples,
        min_depth_range_m=options.min_depth_range_m,
        max_time_sigma_s=options.max_time_sigma_s,
        noise_sigma_m=options.depth_sigma_m,
    )
    try:
        solution = solve_clock_offset(
            traj_t,
            traj_z,
            [(d.t_s, d.depth_m) for d in dives],
            max_offset_s=options.max_offset_s,
            prior=prior,
            limits=limits,
            labels=[d.label for d in dives],
            step_s=options.search_step_s,
            min_overlap_fraction=options.min_overlap_fraction,
            max_gap_s=options.max_gap_s,
            estimate_drift=options.estimate_drift,
            estimate_scale=options.estimate_scale,
            drift_prior_sigma_ppm=options.drift_prior_sigma_ppm,
            z_walk_sigma_m_per_sqrt_s=options.odometry_sigma_m_per_sqrt_s,
        )
    except SyncError as error:
        raise StageError(
            f"the dive profile does not overlap the trajectory within +-{options.max_offset_s:.0f}"
            f" s ({error}); {_HINT}"
        ) from None
    dive = dives[solution.dive]
    sync = solution.sync
    ambiguity = solution.ambiguity
    if ambiguity.ambiguous:
        if prior is None:
            why = (
                "no clock prior to settle it (off, or the stamps are not wall-clock dates)"
                if options.clock_prior_window_s is not None
                else "no clock prior to settle it (clock_prior_window_s is off)"
            )
        else:
            why = f"the clock prior ({prior.describe()}) did not settle it"
        raise StageError(
            f"{dive.label}: the clock offset is ambiguous, not written (a wrong one puts the dive "
            f"metres off its depth): {'; '.join(ambiguity.reasons)}; {why}; {_HINT}"
        )
    if (
        prior is not None
        and not solution.prior_used
        and not bool(prior.contains(sync.time_offset_s))
    ):
        log.warning(
            "%s: the clock offset %.1f s is %.0f s from the clock prior %s: the dive computer's "
            "clock is further off than expected (kept: the depth data single it out)",
            dive.label,
            sync.time_offset_s,
            solution.prior_distance_s,
            prior.describe(),
        )
    if ambiguity.near_offset_s is not None and ambiguity.near_evidence < options.min_evidence:
        log.warning(
            "%s: the clock offset %.1f s is known only to within %.0f s: %.1f s fits almost as "
            "well (evidence %.1f; the depth offset would move by %.3f m)",
            dive.label,
            sync.time_offset_s,
            abs(ambiguity.near_offset_s - sync.time_offset_s),
            ambiguity.near_offset_s,
            ambiguity.near_evidence,
            (ambiguity.near_depth_offset_m or 0.0) - sync.depth_offset_m,
        )
    log.info(
        "%s: clock offset %.3f +- %.3f s, drift %.1f +- %.1f ppm, depth offset %.3f m "
        "(evidence %.1f over the next offset%s)",
        dive.label,
        sync.time_offset_s,
        sync.time_offset_sigma_s,
        sync.drift_ppm,
        sync.drift_sigma_ppm,
        sync.depth_offset_m,
        ambiguity.evidence,
        ", inside the clock prior" if solution.prior_used else "",
    )
    return solution


def _prior_document(
    options: DepthOptions, prior: ClockPrior | None, solution: ClockSolution | None
) -> dict[str, Any]:
    return {
        "available": prior is not None,
        "used": bool(solution is not None and solution.prior_used),
        "window_s": options.clock_prior_window_s,
        "zone_step_s": options.clock_prior_zone_step_s,
        "distance_s": None if solution is None else solution.prior_distance_s,
        "inside": None
        if prior is None or solution is None
        else bool(prior.contains(solution.sync.time_offset_s)),
        "relation": "time_offset_s is expected within window_s of a whole multiple of "
        "zone_step_s (the two wall clocks agree apart from a time-zone difference)",
    }


def _ambiguity_document(ambiguity: OffsetAmbiguity, dives: list[_DiveData]) -> dict[str, Any]:
    runner_dive = ambiguity.runner_up_dive
    return {
        "ambiguous": ambiguity.ambiguous,
        "reasons": list(ambiguity.reasons),
        "samples": ambiguity.samples,
        "depth_range_m": ambiguity.depth_range_m,
        "z_range_m": ambiguity.z_range_m,
        "excursion_steps": ambiguity.excursion_steps,
        "time_offset_sigma_s": _number(ambiguity.time_offset_sigma_s),
        "cost_sigma_m": ambiguity.cost_sigma_m,
        "best_cost": ambiguity.best_cost,
        "runner_up_offset_s": ambiguity.runner_up_offset_s,
        "runner_up_dive": None if runner_dive is None else dives[runner_dive].label,
        "runner_up_cost": ambiguity.runner_up_cost,
        "runner_up_depth_offset_m": ambiguity.runner_up_depth_offset_m,
        "evidence": _number(ambiguity.evidence),
        "flat_evidence": _number(ambiguity.flat_evidence),
        "near_offset_s": ambiguity.near_offset_s,
        "near_evidence": _number(ambiguity.near_evidence),
        "near_depth_offset_m": ambiguity.near_depth_offset_m,
        "solutions_compared": ambiguity.solutions,
        "evidence_meaning": "samples x (mean Huber cost of the best clearly different offset - "
        "that of the answer), costs at cost_sigma_m, plus the difference of their prior costs; "
        "null: no other offset fits at all; flat_evidence: the same against a constant depth; "
        "near_*: the best fit a few sample intervals away (below min_evidence: a warning, the "
        "time is known only to that distance; the depth hardly moves)",
    }


def _overlap_count(
    traj_t: npt.NDArray[np.float64], dive: _DiveData, offset_s: float, max_gap_s: float
) -> int:
    return int(np.count_nonzero(valid_mask(traj_t, dive.t_s - offset_s, max_gap_s=max_gap_s)))


def _given_offset(
    options: DepthOptions,
    traj_t: npt.NDArray[np.float64],
    traj_z: npt.NDArray[np.float64],
    dives: list[_DiveData],
) -> tuple[DepthSync, _DiveData]:
    offset = float(options.time_offset_s or 0.0)
    counts = [_overlap_count(traj_t, d, offset, options.max_gap_s) for d in dives]
    best = int(np.argmax(counts))
    if counts[best] < 3:
        raise StageError(
            f"with the given clock offset {offset:+.1f} s no dive has 3 samples inside the "
            f"trajectory ({', '.join(d.label for d in dives)}); check --time-offset (dive-computer"
            " time minus camera time at the trajectory's first stamp)"
        )
    dive = dives[best]
    return _fit(
        options, traj_t, traj_z, dive, offset, time=False, scale=options.estimate_scale
    ), dive


def _paper(
    options: DepthOptions,
    traj_t: npt.NDArray[np.float64],
    traj_z: npt.NDArray[np.float64],
    dives: list[_DiveData],
) -> tuple[DepthSync, _DiveData]:
    from postproc.depth.paper import paper_depth_sync

    prior = float(options.time_offset_s or 0.0)
    counts = [_overlap_count(traj_t, d, prior, options.max_gap_s) for d in dives]
    dive = dives[int(np.argmax(counts))]
    try:
        sync = paper_depth_sync(
            traj_t,
            traj_z,
            dive.t_s,
            dive.depth_m,
            prior_offset_s=prior,
            max_gap_s=options.max_gap_s,
        )
    except SyncError as error:
        raise StageError(f"{dive.label}: {error}; {_HINT}") from None
    return sync, dive


def _world_trajectory(trajectory: Trajectory, sync: DepthSync) -> Trajectory:
    poses = trajectory.poses.copy()
    poses[:, 2, 3] = sync.world_z_m(trajectory.positions[:, 2])
    return Trajectory(trajectory.stamps_ns.copy(), poses)


def _fuse(
    options: DepthOptions,
    traj_t: npt.NDArray[np.float64],
    world: Trajectory,
    sample_cam_t: npt.NDArray[np.float64],
    depth_m: npt.NDArray[np.float64],
) -> Trajectory:
    from postproc.depth.factors import FusionSettings, fuse_depth

    settings = FusionSettings(
        depth_sigma_m=options.depth_sigma_m,
        odometry_sigma_m_per_sqrt_s=options.odometry_sigma_m_per_sqrt_s,
        odometry_sigma_rad_per_sqrt_s=options.odometry_sigma_rad_per_sqrt_s,
        node_interval_s=options.node_interval_s,
    )
    result = fuse_depth(traj_t, world.poses, sample_cam_t, -depth_m, settings=settings)
    log.info(
        "depth fusion: %d nodes, %d depth factors, error %.1f -> %.1f in %d iterations",
        result.nodes.size,
        result.depth_factors,
        result.error_before,
        result.error_after,
        result.iterations,
    )
    return Trajectory(world.stamps_ns.copy(), result.poses)


def _number(value: float) -> float | None:
    return None if not math.isfinite(value) else float(value)


def _sync_document(
    options: DepthOptions,
    trajectory_path: Path,
    dive: _DiveData,
    reference_ns: int,
    sync: DepthSync,
    scale_free: DepthSync | None,
    candidates: list[CoarseCandidate],
    world: Trajectory,
    fused: Trajectory | None,
    traj_t: npt.NDArray[np.float64],
    traj_z: npt.NDArray[np.float64],
    sample_cam_t: npt.NDArray[np.float64],
) -> dict[str, Any]:
    clock = ClockModel(
        offset_ns=round(sync.time_offset_s * NS_PER_S),
        drift_ppm=sync.drift_ppm,
        reference_ns=reference_ns,
    )
    profile = dive.profile
    residual = dive.depth_m - sync.depth_m(np.interp(sample_cam_t, traj_t, traj_z))
    inside = valid_mask(traj_t, sample_cam_t, max_gap_s=options.max_gap_s)
    document: dict[str, Any] = {
        "method": options.method,
        "trajectory": trajectory_path.name,
        "frame": "depth of the frame the TUM file holds (body poses: IMU; camera poses: camera)",
        "dive": {
            "label": dive.label,
            "start": profile.start_iso,
            "model": profile.model,
            "serial": profile.serial,
            "fingerprint": profile.fingerprint,
            "samples": int(dive.t_s.size),
            "samples_in_trajectory": int(np.count_nonzero(inside)),
        },
        "reference_time_s": reference_ns / NS_PER_S,
        "reference_time_ns": reference_ns,
        "time_offset_s": sync.time_offset_s,
        "time_offset_sigma_s": _number(sync.time_offset_sigma_s),
        "time_offset_given": options.time_offset_s is not None and options.method == "ours",
        "drift_ppm": sync.drift_ppm,
        "drift_sigma_ppm": _number(sync.drift_sigma_ppm),
        "depth_offset_m": sync.depth_offset_m,
        "depth_offset_sigma_m": _number(sync.depth_offset_sigma_m),
        "depth_scale": sync.depth_scale,
        "depth_scale_sigma": _number(sync.depth_scale_sigma),
        "z_rate_m_per_s": sync.z_rate_m_per_s,
        "residual_rms_m": _number(sync.residual_rms_m),
        "residual_median_abs_m": _number(float(np.median(np.abs(residual[inside]))))
        if np.any(inside)
        else None,
        "samples_used": sync.used,
        "inliers": sync.inliers,
        "relation": "dive_time = camera_time + time_offset_s + drift_ppm * 1e-6 * "
        "(camera_time - reference_time_s); depth_m = depth_offset_m - depth_scale * z "
        "(the sync fitted the samples with + z_rate_m_per_s * (camera time - the trajectory's "
        "middle) besides: the trajectory's steady z drift, which the fused trajectory removes)",
        "clock": {"source": "camera", "target": "dive computer", **asdict(clock)},
        "coarse_candidates": [asdict(c) for c in candidates],
        "options": asdict(options),
        "outputs": {"world": _FOLDER.trajectory_world.name},
    }
    if scale_free is not None:
        document["depth_scale_free"] = {
            "value": scale_free.depth_scale,
            "sigma": _number(scale_free.depth_scale_sigma),
        }
    if fused is not None:
        change = fused.positions[:, 2] - world.positions[:, 2]
        document["outputs"]["fused"] = _FOLDER.trajectory_world_fused.name
        document["fusion_z_change_rms_m"] = float(np.sqrt(np.mean(change * change)))
        document["fusion_z_change_max_m"] = float(np.max(np.abs(change)))
    if options.plot:
        document["outputs"]["plot"] = _FOLDER.plot.name
    return document
