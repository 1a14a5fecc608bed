"""The merge stage: put several SLAM sessions into one frame through AprilGrid targets
and through the structure they both filmed (natural features).

Inputs: SLAM result folders (`keyframes.tum` with camera poses `T_S_C`,
`keyframes/<timestamp_ns>.png`, `calib/camchain.yaml`; cam0 took the
keyframes) and Kalibr AprilGrid target YAMLs (with `tagIdOffset` when two
grids share a wreck). Each target's name is its YAML file's stem.

Per keyframe: detect the tags, assign them to targets, PnP over all the
corners of each target at once (through the camera model), and
`T_S_m = T_S_C @ T_C_m`. Per session and target: a robust mean with its
covariance (`averaging.robust_pose_mean`) picks the inliers. The SLAM drifts
from where it defines its frame (the session's first pose), so a keyframe far
in time from that anchor tells less about the target's pose in the frame: a
random-walk drift model, fitted per session from the passes over its targets,
weighs the inliers by generalised least squares and gives a covariance that
includes the drift (`averaging.estimate_drift_model`, `drift_weighted_mean`).
The robust mean's rule cuts the passes the walk carried furthest from the mean,
so each sighting is then tested again against that model (predicted from the
target's other sightings, `averaging.drift_inliers`) and the model refitted.
Then sessions are placed in the reference session's frame
(`align.place_sessions`): 4 DoF (yaw and translation) when the sessions are
depth-fused (gravity-aligned with absolute z), otherwise 6 DoF; with
`tilt_sigma_deg` (the SLAM's roll/pitch uncertainty) a 6-DoF fit whose
relative roll and pitch get that gravity prior. Where a session's drift was
measured, its targets share that drift (their means lean on the same first
passes), so the sessions are placed by the joint estimate below, with the
targets' edges only, which counts that correlation in the covariance.
With `natural_features` ("auto", the default, when the targets leave a session
unplaced or there are none; True: always) every pair of sessions is also matched
through the wreck itself (`places`, `natural`: bag-of-words recognition over a
vocabulary built from the sessions, PnP RANSAC against the other session's
triangulated keyframe features, the gravity check, pairwise consistency, a
drift-aware mean), and the session transforms come from every constraint at
once (`joint.solve_joint`: target poses per session, natural-feature pairs,
the gravity prior on roll/pitch, the depth prior on z for depth-fused
sessions, each edge's covariance carrying its session's drift, and the edges of
one session correlated through the drift they share), robustly, with a residual
per constraint. Targets are then optional.
`method="paper"` runs the paper's recipe instead (`paper.py`): per-tag poses,
one-sigma rejection, Euler averaging, sessions placed only through targets
shared with the reference.

Depth-fused sessions: when a folder's depth stage output is found beside it
(`<slam>/depth/` or `<slam>/../depth/` holding `trajectory_world_fused.tum`
or `trajectory_world.tum`, the world trajectory of `<slam>/trajectory.tum`),
keyframe poses are moved into that world frame first:
`T_W_C(t) = T_W_B(t) @ inv(T_S_B(t)) @ T_S_C(t)`.

Outputs in `out_dir`:

* `transforms.json`: {"reference", "method", "dof", "depth_fused",
  "tilt_prior_sigma_deg" (the gravity prior on roll/pitch, null when none),
  "covariance_convention", "sessions": {folder name: {"placed", "T_W_S"
  (4x4 row-major nested lists), "covariance" (6x6, rotation first, rad and
  m), "targets", "via", "residuals", "diagnostic_6dof"...}}}, and with
  natural features "estimator": "joint", "pairs" (per pair of sessions the
  evidence: candidate scores, inlier counts, consistent matches, mergeable or
  not and why) and "constraints" (per constraint its residual, whitened norm and
  robust weight). Sessions with no chain of constraints to the reference have
  "placed": false and the reason. Written last: its presence means the stage
  is done.
* `targets.json`: per target its world pose `T_W_m`, covariance, and per
  session the observations used and rejected.
* `<session>/keyframes_merged.tum`: the keyframe camera poses in W.
* `merge_top.png`, `merge_side.png`: all sessions and targets seen from above
  and from the side.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import numpy.typing as npt

from postproc.merge.align import (
    Placement,
    TargetEstimate,
    compose_with_covariance,
    place_sessions,
    rotation_difference_rad,
)
from postproc.merge.averaging import (
    DriftModel,
    PoseAverage,
    calibrate_drift_model,
    clustered_covariance,
    drift_inliers,
    drift_weighted_mean,
    drift_weights,
    estimate_drift_model,
    fuse_pose_estimates,
    local_frame_variance,
    pose_residuals,
    robust_pose_mean,
)
from postproc.merge.joint import DriftShare, Edge, JointEstimate, solve_joint
from postproc.merge.options import MergeOptions as MergeOptions
from postproc.merge.places import PairEvidence
from shared.clock import ns_from_seconds, seconds_from_ns
from shared.errors import InputError, StageError
from shared.folders import MergeFolder, SlamFolder, rebuild, result_stamp
from shared.trajectory import Trajectory

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

COVARIANCE_CONVENTION = (
    "6x6 of [dtheta, dt]: R = Exp(dtheta) R_mean, t = t_mean + dt, both in the parent "
    "frame (W); rotation first; radians and metres"
)


@dataclass
class Session:
    """One input folder: its name, camera, keyframe poses and images."""

    name: str
    folder: Path
    camera: Any
    keyframes: Trajectory
    images: dict[int, Path]
    depth_fused: bool = False
    keyframes_slam: Trajectory | None = None
    anchor_ns: int = 0


@dataclass
class Observation:
    """One target seen in one keyframe (session frame `T_S_m`)."""

    session: str
    stamp_ns: int
    target: str
    tag_count: int
    corner_count: int
    reprojection_rms_px: float
    session_from_target: FloatArray
    paper_session_from_target: FloatArray | None = None
    pnp_variance: FloatArray | None = None


@dataclass(frozen=True)
class _Sightings:
    """One target's observations in one session as arrays, taken once, and their robust
    mean (whose `inliers` the drift model may choose again)."""

    poses: FloatArray  # (N, 4, 4) T_S_m
    times_s: FloatArray  # (N,) seconds since the session's anchor
    passes: npt.NDArray[np.int64]  # (N,) pass labels
    pnp: FloatArray  # (N, 6) PnP variances in the session frame
    average: PoseAverage

    @property
    def inlier_times(self) -> FloatArray:
        return self.times_s[self.average.inliers]

    @property
    def inlier_passes(self) -> npt.NDArray[np.int64]:
        return self.passes[self.average.inliers]

    @property
    def inlier_pnp(self) -> FloatArray:
        return self.pnp[self.average.inliers]


def run(
    options: MergeOptions,
    slam_dirs: Sequence[Path | str],
    targets: Sequence[Path | str],
    out_dir: Path | str,
    *,
    overwrite: bool = False,
) -> Path:
    """Merge the sessions in `slam_dirs` through the targets (may be empty with natural
    features) and the structure they share; returns transforms.json.

    The resume rule of every stage (`shared.folders.rebuild`): a complete result of the
    same inputs (the SLAM folders with their depth/, the targets) and options is kept;
    another is refused unless `overwrite`, then rebuilt beside it and swapped in. Raises
    InputError for unreadable folders or target files, StageError for invalid options
    (unknown reference, method or dof, no input).
    """
    folder = MergeFolder(out_dir)
    _check_options(options, slam_dirs, targets)
    stamp = result_stamp("merge", options, slam=list(slam_dirs), targets=list(targets))
    with rebuild(folder, stamp, overwrite=overwrite) as work:
        if work is not None:
            _build(options, slam_dirs, targets, work)
    return folder.transforms


def _build(
    options: MergeOptions,
    slam_dirs: Sequence[Path | str],
    targets: Sequence[Path | str],
    out: MergeFolder,
) -> None:
    """The merge itself, written into the empty folder `out`."""
    from shared.calibration.kalibr import read_target_yaml

    target_names = [Path(t).stem for t in targets]
    if len(set(target_names)) != len(target_names):
        raise InputError(
            f"target files {[str(t) for t in targets]}: two share a name (the file stem names "
            "the target; rename one)"
        )
    grids = [read_target_yaml(t) for t in targets]
    _check_disjoint_ids(grids, targets)
    sessions = _load_sessions(options, [Path(d) for d in slam_dirs])
    reference = options.reference or sessions[0].name
    if reference not in {s.name for s in sessions}:
        raise StageError(
            f"merge: reference {reference!r} is not one of the inputs "
            f"({', '.join(s.name for s in sessions)})"
        )
    depth_fused = all(s.depth_fused for s in sessions)
    if options.dof != "auto":
        dof: Literal[4, 6] = options.dof
    elif options.tilt_sigma_deg is not None and options.method == "ours":
        dof = 6
    else:
        dof = 4 if depth_fused else 6
    tilt_prior_deg = None if dof == 4 else options.tilt_sigma_deg
    observations = _observe(options, sessions, grids, target_names) if grids else []
    drift_models: dict[str, DriftModel] = {}
    shares: dict[tuple[str, str], DriftShare] = {}

    if options.method == "ours":
        averages = _average_ours(
            options, sessions, target_names, observations, drift_models, shares
        )
    else:
        averages = _average_paper(sessions, target_names, observations)
    estimates = {
        s.name: {m: TargetEstimate(a.pose, a.covariance) for m, a in averages[s.name].items()}
        for s in sessions
    }
    joint: JointEstimate | None = None
    pairs: list[PairEvidence] = []
    use_natural = options.method == "ours" and options.natural_features is True
    target_placements: dict[str, Any] | None = None
    if options.method == "ours" and options.natural_features == "auto":
        if targets:
            target_placements = place_sessions(
                estimates,
                reference,
                dof=dof,
                tilt_prior_sigma_rad=(
                    None if tilt_prior_deg is None else np.deg2rad(tilt_prior_deg)
                ),
            )
        use_natural = target_placements is None or any(
            s.name not in target_placements for s in sessions
        )
        if use_natural:
            log.info("merge: the targets do not place every session; matching natural features")
    # Targets alone where a session's drift was measured: its targets share that drift
    # (both lean on its first passes), and placed one by one as independent the session
    # frame's covariance was too small (squared Mahalanobis over 6: 1.23 on 32 draws of
    # the wreck scene, 1.02 this way; docs/benchmarks.md, "Merge"), so they too go
    # through the joint estimate, which counts the shared drift (`joint.DriftShare`).
    if use_natural or (options.method == "ours" and shares):
        rates = _drift_rates(options, sessions, drift_models)
        if use_natural:
            from postproc.merge.natural import match_sessions

            # Gravity on the pairs' roll/pitch: the IMUs' tilt error (2σ² for the
            # relative tilt), unless the joint estimate puts that prior on each session.
            if tilt_prior_deg is not None or dof == 4:
                tilt_variance = 1.0
            else:
                tilt_variance = 2.0 * np.deg2rad(options.places.gravity_sigma_deg) ** 2
            # Each keyframe's own pose error where the targets measured it (their drift
            # model's per-observation noise), else the places' prior.
            pairs = match_sessions(
                options.places,
                sessions,
                drift_rates=rates,
                tilt_variance_rad2=tilt_variance,
                keyframe_noise={name: model.scaled_noise for name, model in drift_models.items()},
            )
        joint = _solve_joint(
            options, sessions, reference, dof, tilt_prior_deg, estimates, pairs, shares, rates
        )
        placements = _joint_placements(joint, sessions)
    elif target_placements is not None:
        placements = target_placements
    elif options.method == "ours":
        placements = place_sessions(
            estimates,
            reference,
            dof=dof,
            tilt_prior_sigma_rad=None if tilt_prior_deg is None else np.deg2rad(tilt_prior_deg),
        )
    else:
        placements = _place_paper(estimates, reference)
    for session in sessions:
        if session.name not in placements:
            log.warning(
                "%s: no chain of shared targets or natural-feature matches to the reference: "
                "not placed",
                session.name,
            )

    for session in sessions:
        placement = placements.get(session.name)
        if placement is None:
            continue
        merged = session.keyframes.transformed(placement.world_from_session)
        out.write_merged_keyframes(session.name, merged)
    world_targets = _world_targets(estimates, placements)
    targets_doc = _targets_document(
        target_names, targets, sessions, averages, observations, world_targets
    )
    out.write_targets(targets_doc)
    if options.plot:
        from postproc.merge.plots import plot_merge

        plot_merge(
            out.top_plot,
            out.side_plot,
            trajectories={
                s.name: s.keyframes.transformed(placements[s.name].world_from_session).positions
                for s in sessions
                if s.name in placements
            },
            targets={name: pose for name, (pose, _) in world_targets.items()},
            extents={name: grid.extent_m for name, grid in zip(target_names, grids, strict=True)},
        )
    document = _transforms_document(
        options, sessions, reference, dof, depth_fused, placements, estimates, tilt_prior_deg
    )
    for name, model in drift_models.items():
        document["sessions"][name]["drift_model"] = _drift_model_entry(model)
    document["natural_features"] = use_natural
    if joint is not None:
        document.update(_joint_document(joint, pairs))
        for name, entry in document["sessions"].items():
            if entry["placed"]:
                _joint_session_entry(entry, name, joint, dof)
            elif use_natural:
                entry["reason"] = (
                    "no chain of shared targets or consistent natural-feature matches to the "
                    "reference (see pairs for the evidence)"
                )
    # transforms.json last: the folder's completeness marker.
    out.write_transforms(document)


def _check_options(
    options: MergeOptions, slam_dirs: Sequence[Path | str], targets: Sequence[Path | str]
) -> None:
    if options.method not in ("ours", "paper"):
        raise StageError(f"merge: unknown method {options.method!r} (expected 'ours' or 'paper')")
    if options.dof not in ("auto", 4, 6):
        raise StageError(f"merge: dof must be 'auto', 4 or 6, got {options.dof!r}")
    if options.rotation_mean not in ("chordal", "quaternion"):
        raise StageError(f"merge: unknown rotation_mean {options.rotation_mean!r}")
    if options.outlier_rule not in ("mad", "chi2"):
        raise StageError(f"merge: unknown outlier_rule {options.outlier_rule!r}")
    if options.min_tags < 1:
        raise StageError(f"merge: min_tags must be at least 1, got {options.min_tags}")
    for name in (
        "max_reprojection_rms_px",
        "max_distance_m",
        "mad_threshold",
        "pass_gap_s",
        "drift_rotation_sigma_deg",
        "drift_translation_sigma_m",
        "drift_rate_rotation_deg_per_sqrt_s",
        "drift_rate_translation_m_per_sqrt_s",
    ):
        value = getattr(options, name)
        if not (value > 0 and np.isfinite(value)):
            raise StageError(f"merge: {name} must be a positive number, got {value}")
    if options.tilt_sigma_deg is not None and not (
        options.tilt_sigma_deg > 0 and np.isfinite(options.tilt_sigma_deg)
    ):
        raise StageError(
            f"merge: tilt_sigma_deg must be a positive number or None, got {options.tilt_sigma_deg}"
        )
    if not slam_dirs:
        raise StageError("merge: no SLAM folder given")
    if options.natural_features not in (True, False, "auto"):
        raise StageError(
            f"merge: natural_features must be true, false or 'auto', got "
            f"{options.natural_features!r}"
        )
    if not targets and (options.method == "paper" or options.natural_features is False):
        raise StageError(
            "merge: no target YAML given (expected at least one --targets file; only "
            "method 'ours' with natural features merges without targets)"
        )
    if not (options.depth_sigma_m > 0 and np.isfinite(options.depth_sigma_m)):
        raise StageError(
            f"merge: depth_sigma_m must be a positive number, got {options.depth_sigma_m}"
        )


def _check_disjoint_ids(grids: Sequence[Any], paths: Sequence[Path | str]) -> None:
    owner: dict[int, int] = {}
    for index, grid in enumerate(grids):
        for tag_id in grid.tag_ids():
            if tag_id in owner:
                raise InputError(
                    f"{paths[index]}: tag id {tag_id} also belongs to {paths[owner[tag_id]]} "
                    "(give each grid its own tagIdOffset)"
                )
            owner[tag_id] = index


def session_names(folders: Sequence[Path]) -> list[str]:
    """Folder names, made unique by prefixing parent folders where two collide.

    `results/dive1/slam` and `results/dive2/slam` become `dive1_slam` and
    `dive2_slam`. Raises InputError for the same folder given twice.
    """
    resolved = [f.resolve() for f in folders]
    if len(set(resolved)) != len(resolved):
        raise InputError(f"the same SLAM folder is given twice: {[str(f) for f in folders]}")
    depth = 1
    while True:
        names = ["_".join(p.parts[-depth:]) for p in resolved]
        if len(set(names)) == len(names) or depth >= max(len(p.parts) for p in resolved):
            return names
        depth += 1


def _load_sessions(options: MergeOptions, folders: Sequence[Path]) -> list[Session]:
    names = session_names(folders)
    sessions = []
    for name, folder in zip(names, folders, strict=True):
        if not folder.is_dir():
            raise InputError(f"{folder}: not a folder (expected a SLAM result folder)")
        slam = SlamFolder(folder)
        keyframes_path = slam.keyframes_tum
        camchain_path = slam.camchain
        for path, what in ((keyframes_path, "keyframe poses"), (camchain_path, "camera model")):
            if not path.is_file():
                raise InputError(f"{folder}: no {path.relative_to(folder)} ({what} expected)")
        keyframes = slam.read_keyframes()
        cameras = {c.name: c for c in slam.read_camchain()}
        if options.camera not in cameras:
            raise InputError(
                f"{camchain_path}: no camera {options.camera!r} (found: {', '.join(cameras)})"
            )
        images = {}
        image_dir = slam.keyframes
        for stamp in keyframes.stamps_ns.tolist():
            path = slam.keyframe_image(stamp)
            if path.is_file():
                images[int(stamp)] = path
        if not images:
            raise InputError(
                f"{image_dir}: no keyframe images (expected <timestamp_ns>.png for the "
                f"stamps of {keyframes_path.name})"
            )
        if len(images) < len(keyframes):
            log.warning(
                "%s: %d of %d keyframes have no image",
                folder,
                len(keyframes) - len(images),
                len(keyframes),
            )
        session = Session(name, folder, cameras[options.camera].camera, keyframes, images)
        session.anchor_ns = _anchor_ns(folder, keyframes)
        _apply_depth(options, session)
        sessions.append(session)
    fused = [s.depth_fused for s in sessions]
    if options.depth_fused is None and any(fused) and not all(fused):
        log.warning(
            "only some sessions are depth-fused (%s): using the SLAM frames for all",
            ", ".join(s.name for s in sessions if s.depth_fused),
        )
        for session in sessions:
            _undo_depth(session)
    return sessions


def _anchor_ns(folder: Path, keyframes: Trajectory) -> int:
    """Where the SLAM frame is defined (its drift is zero): the first pose of the session.

    The first stamp of `trajectory.tum` when it is there and readable (every
    tracked frame), else the first keyframe.
    """
    first = int(keyframes.stamps_ns[0])
    slam = SlamFolder(folder)
    path = slam.trajectory
    if path.is_file():
        try:
            return min(first, int(slam.read_trajectory().stamps_ns[0]))
        except InputError:
            log.warning("%s: unreadable, the session anchor is the first keyframe", path)
    return first


def find_depth_world(folder: Path) -> tuple[Path, Trajectory] | None:
    """The depth stage's world trajectory for the SLAM folder `folder`, if any: the
    depth-fused one, else the one at true depth (with the file it came from)."""
    for depth in SlamFolder(folder).depth_folders():
        if depth.trajectory_world_fused.is_file():
            return depth.trajectory_world_fused, depth.read_world_fused()
        if depth.trajectory_world.is_file():
            return depth.trajectory_world, depth.read_world()
    return None


def _apply_depth(options: MergeOptions, session: Session) -> None:
    if options.depth_fused is False:
        return
    found = find_depth_world(session.folder)
    body_path = SlamFolder(session.folder).trajectory
    if found is None or not body_path.is_file():
        if options.depth_fused:
            depth = SlamFolder(session.folder).depth
            raise InputError(
                f"{session.folder}: depth fusion requested but no depth world trajectory "
                f"({depth.trajectory_world_fused.name} or {depth.trajectory_world.name} in "
                f"depth/ or ../depth/) and {body_path.name}"
            )
        return
    world_path, world = found
    body = SlamFolder(session.folder).read_trajectory()
    stamps = session.keyframes.stamps_ns
    start = max(int(world.stamps_ns[0]), int(body.stamps_ns[0]))
    end = min(int(world.stamps_ns[-1]), int(body.stamps_ns[-1]))
    inside = (stamps >= start) & (stamps <= end)
    if not np.any(inside):
        raise InputError(
            f"{world_path}: no overlap with the keyframe stamps of {session.folder}/keyframes.tum"
        )
    kept = stamps[inside]
    world_from_session = world.interpolate(kept).poses @ np.linalg.inv(body.interpolate(kept).poses)
    session.keyframes_slam = session.keyframes
    session.keyframes = Trajectory(kept, world_from_session @ session.keyframes.poses[inside])
    session.depth_fused = True
    log.info("%s: keyframes moved into the depth-fused world frame (%s)", session.name, world_path)


def _undo_depth(session: Session) -> None:
    if session.depth_fused and session.keyframes_slam is not None:
        session.keyframes = session.keyframes_slam
        session.depth_fused = False


def _observe(
    options: MergeOptions,
    sessions: Sequence[Session],
    grids: Sequence[Any],
    target_names: Sequence[str],
) -> list[Observation]:
    """Detect, assign and PnP every keyframe of every session (with a progress bar).

    Reading and detection run over a thread pool, one keyframe a task (OpenCV releases
    the GIL; 300 keyframes of the 10-minute bench dive: 6.0 s against 7.9 s in one
    thread, whose detector already uses parts of both cores); the rest follows in
    keyframe order."""
    import concurrent.futures
    import os

    import cv2

    from postproc.merge.paper import per_tag_target_pose
    from postproc.merge.target_pose import estimate_target_pose
    from shared.calibration.aprilgrid_detection import TagDetection, detect_tags, group_by_target
    from shared.progress import progress_bar

    def detect(path: Path) -> list[TagDetection]:
        # IMREAD_GRAYSCALE always decodes to 8-bit.
        image = cast(npt.NDArray[np.uint8] | None, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
        if image is None:
            raise InputError(f"{path}: cannot read the keyframe image")
        return detect_tags(image, options.detection)

    total = sum(len(s.images) for s in sessions)
    observations: list[Observation] = []
    foreign: dict[int, int] = {}
    bar = progress_bar(total=total, desc="merge: keyframes", unit="kf")
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1)
    try:
        for session in sessions:
            index_of = {int(s): i for i, s in enumerate(session.keyframes.stamps_ns.tolist())}
            keyframes = [(t, p) for t, p in sorted(session.images.items()) if t in index_of]
            bar.update(len(session.images) - len(keyframes))
            found = pool.map(detect, [path for _, path in keyframes])
            for (stamp, _), detections in zip(keyframes, found, strict=True):
                bar.update(1)
                grid_observations, others = group_by_target(
                    detections, grids, min_tags=options.min_tags
                )
                for tag_id in others:
                    foreign[tag_id] = foreign.get(tag_id, 0) + 1
                session_from_cam = session.keyframes.poses[index_of[stamp]]
                for grid_observation in grid_observations:
                    estimate = estimate_target_pose(
                        session.camera,
                        grid_observation.object_points_m.reshape(-1, 3),
                        grid_observation.image_points_px.reshape(-1, 2),
                    )
                    if estimate is None:
                        continue
                    if estimate.reprojection_rms_px > options.max_reprojection_rms_px:
                        continue
                    if np.linalg.norm(estimate.cam_from_target[:3, 3]) > options.max_distance_m:
                        continue
                    paper_pose = None
                    if options.method == "paper":
                        cam_from_target = per_tag_target_pose(session.camera, grid_observation)
                        if cam_from_target is None:
                            continue
                        paper_pose = session_from_cam @ cam_from_target
                    # The PnP covariance's diagonal in the session frame (rotation, then
                    # translation: both rotate with the camera).
                    rotation = session_from_cam[:3, :3]
                    pnp = np.zeros(6)
                    for block in (slice(0, 3), slice(3, 6)):
                        pnp[block] = np.diag(
                            rotation @ estimate.covariance[block, block] @ rotation.T
                        )
                    observations.append(
                        Observation(
                            session=session.name,
                            stamp_ns=stamp,
                            target=target_names[grid_observation.target_index],
                            tag_count=len(grid_observation.tag_ids),
                            corner_count=estimate.corner_count,
                            reprojection_rms_px=estimate.reprojection_rms_px,
                            session_from_target=session_from_cam @ estimate.cam_from_target,
                            paper_session_from_target=paper_pose,
                            pnp_variance=pnp if np.all(np.isfinite(pnp)) else None,
                        )
                    )
    finally:
        pool.shutdown(cancel_futures=True)
        bar.close()
    if foreign:
        log.info(
            "rejected tags of no target: %s",
            ", ".join(f"id {k} ({v}x)" for k, v in sorted(foreign.items())),
        )
    for session in sessions:
        for name in target_names:
            count = sum(1 for o in observations if o.session == session.name and o.target == name)
            log.info("%s: target %s seen in %d keyframes", session.name, name, count)
    return observations


def _average_ours(
    options: MergeOptions,
    sessions: Sequence[Session],
    target_names: Sequence[str],
    observations: Sequence[Observation],
    models: dict[str, DriftModel] | None = None,
    shares: dict[tuple[str, str], DriftShare] | None = None,
) -> dict[str, dict[str, PoseAverage]]:
    """Per session and target: robust mean (outliers out), then the drift-weighted mean
    (or, with `drift_weighting` off, the robust mean with the local-frame variance).
    With drift weighting and `drift_rejection` the inliers are chosen again against the
    fitted drift model, and the model refitted, before its calibration.

    The drift model (per-keyframe noise, drift rate) is fitted once per session
    over all its targets' inliers, since the targets share that session's SLAM;
    `models` (when given) receives it for the sessions where it was measured, and
    `shares` per (session, target) the drift each drift-weighted mean carries.
    """
    averages: dict[str, dict[str, PoseAverage]] = {}
    for session in sessions:
        averages[session.name] = {}
        robust: dict[str, _Sightings] = {}
        for name in target_names:
            chosen = [o for o in observations if o.session == session.name and o.target == name]
            if not chosen:
                continue
            weights = np.array([o.corner_count for o in chosen], dtype=np.float64)
            poses = np.array([o.session_from_target for o in chosen])
            average = robust_pose_mean(
                poses,
                weights=weights,
                rotation_mean=options.rotation_mean,
                outlier_rule=options.outlier_rule,
                mad_threshold=options.mad_threshold,
            )
            passes = pass_labels([o.stamp_ns for o in chosen], gap_s=options.pass_gap_s)
            covariance = clustered_covariance(
                average,
                passes,
                weights=weights,
                prior_rotation_sigma_rad=np.deg2rad(options.drift_rotation_sigma_deg),
                prior_translation_sigma_m=options.drift_translation_sigma_m,
            )
            robust[name] = _Sightings(
                poses,
                _seconds(chosen, session.anchor_ns),
                passes,
                _pnp_variances(chosen),
                dataclasses.replace(average, covariance=covariance),
            )
        fit = functools.partial(
            estimate_drift_model,
            prior_rate_rotation_rad2_per_s=np.deg2rad(options.drift_rate_rotation_deg_per_sqrt_s)
            ** 2,
            prior_rate_translation_m2_per_s=options.drift_rate_translation_m_per_sqrt_s**2,
            # The sessions are gravity-aligned by their IMUs, which hold roll and pitch:
            # only the measured tilt drift counts (the targets' tilt was 2-3x looser
            # than its error against the truth with the yaw's prior on all three axes).
            prior_rate_tilt_rad2_per_s=0.0,
        )
        model = _fit_inliers(fit, robust)
        if model.pass_pairs > 0 and options.drift_weighting and options.drift_rejection:
            model = _drift_rejection(fit, robust, model)
        if model.pass_pairs > 0 and options.drift_weighting:
            model = calibrate_drift_model(
                model,
                [t.inlier_times for t in robust.values()],
                [t.inlier_passes for t in robust.values()],
                fit,
                observation_variance=[t.inlier_pnp for t in robust.values()],
            )
        if models is not None and model.pass_pairs > 0:
            models[session.name] = model
        if model.pass_pairs == 0:
            # No target filmed in two passes: the session's drift is not measured, and
            # the prior alone should not reweigh keyframes; keep the robust means.
            log.info("%s: no target seen in two passes: drift not measured", session.name)
            averages[session.name] = {name: t.average for name, t in robust.items()}
            continue
        if not options.drift_weighting:
            # Equal passes (the overlay of the maps): the targets' local frames differ by
            # the drift between them, which no rigid placement absorbs; it joins each
            # target's covariance so the placement weighs the targets for the overlay.
            variance = local_frame_variance(
                model, [float(np.mean(t.inlier_times)) for t in robust.values()]
            )
            averages[session.name] = {
                name: dataclasses.replace(
                    t.average, covariance=t.average.covariance + np.diag(extra_variance)
                )
                for (name, t), extra_variance in zip(robust.items(), variance, strict=True)
            }
            continue
        log.info(
            "%s: keyframe noise %.3f deg, %.1f mm; drift %.4f deg, %.2f mm per sqrt(s) "
            "(from %d pass pairs); variance x %.2f (rotation), %.2f (translation) for "
            "the model's own fit",
            session.name,
            np.rad2deg(np.sqrt(np.mean(model.noise[:3]))),
            1e3 * np.sqrt(np.mean(model.noise[3:])),
            np.rad2deg(np.sqrt(np.mean(model.drift_rate[:3]))),
            1e3 * np.sqrt(np.mean(model.drift_rate[3:])),
            model.pass_pairs,
            np.mean(model.calibration[:3]),
            np.mean(model.calibration[3:]),
        )
        for name, t in robust.items():
            pose, covariance = drift_weighted_mean(
                t.poses[t.average.inliers],
                t.inlier_times,
                model,
                start=t.average.pose,
                observation_variance=t.inlier_pnp,
            )
            if shares is not None:
                weights = drift_weights(t.inlier_times, model, observation_variance=t.inlier_pnp)
                shares[session.name, name] = DriftShare(
                    session.name, t.inlier_times, weights[:, :, None] * np.eye(6)[None]
                )
            averages[session.name][name] = dataclasses.replace(
                t.average,
                pose=pose,
                covariance=covariance,
                residuals=pose_residuals(t.poses, pose),
            )
    return averages


def _fit_inliers(fit: Callable[..., DriftModel], robust: dict[str, _Sightings]) -> DriftModel:
    """The session's drift model from its targets' current inliers."""
    return fit(
        [t.average.residuals[t.average.inliers] for t in robust.values()],
        [t.inlier_times for t in robust.values()],
        [t.inlier_passes for t in robust.values()],
    )


def _drift_rejection(
    fit: Callable[..., DriftModel],
    robust: dict[str, _Sightings],
    model: DriftModel,
    rounds: int = 3,
) -> DriftModel:
    """Each target's inliers again, against the drift model (`averaging.drift_inliers`),
    and the model refitted, until they settle (at most `rounds` times). `robust` is
    updated in place; returns the last model."""
    for _ in range(rounds):
        changed = False
        for name, t in robust.items():
            kept = drift_inliers(
                t.poses,
                t.times_s,
                model,
                start=t.average.pose,
                inliers=t.average.inliers,
                observation_variance=t.pnp,
            )
            if not np.array_equal(kept, t.average.inliers):
                changed = True
                robust[name] = dataclasses.replace(
                    t, average=dataclasses.replace(t.average, inliers=kept)
                )
        if not changed:
            break
        model = _fit_inliers(fit, robust)
    return model


def _pnp_variances(chosen: Sequence[Observation]) -> FloatArray:
    """(N, 6) each observation's PnP variance in the session frame (zeros where unknown)."""
    return np.array([o.pnp_variance if o.pnp_variance is not None else np.zeros(6) for o in chosen])


def _drift_rates(
    options: MergeOptions, sessions: Sequence[Session], models: dict[str, DriftModel]
) -> dict[str, FloatArray]:
    """Per session the drift variance rates (6,): measured from its targets' passes when
    it has them, else the prior (`drift_rate_*`, on all three rotation axes: with roll
    and pitch held, as in `_average_ours`, the features-only rows of bench_merge lost
    translation, 2.90 -> 3.23 cm on the 120 s seeds 0-2)."""
    prior = np.array(
        [np.deg2rad(options.drift_rate_rotation_deg_per_sqrt_s) ** 2] * 3
        + [options.drift_rate_translation_m_per_sqrt_s**2] * 3
    )
    return {s.name: models[s.name].scaled_rates if s.name in models else prior for s in sessions}


def _solve_joint(
    options: MergeOptions,
    sessions: Sequence[Session],
    reference: str,
    dof: int,
    tilt_prior_deg: float | None,
    estimates: dict[str, dict[str, TargetEstimate]],
    pairs: Sequence[PairEvidence],
    shares: dict[tuple[str, str], DriftShare],
    rates: dict[str, FloatArray],
) -> JointEstimate:
    """Targets, natural-feature pairs, gravity and depth in one robust estimate.

    shares: the drift each target mean carries, rates: each session's drift rates, so
    that constraints of one session are correlated through its drift (`joint`).
    """
    edges = [
        Edge(
            "target",
            f"{name}@{session}",
            session,
            f"target:{name}",
            e.pose,
            e.covariance,
            (shares[session, name],) if (session, name) in shares else (),
        )
        for session, targets in estimates.items()
        for name, e in targets.items()
    ]
    for pair in pairs:
        if pair.mergeable and pair.a_from_b is not None and pair.covariance is not None:
            drift: tuple[DriftShare, ...] = ()
            if (
                pair.gains_a is not None
                and pair.gains_b is not None
                and pair.times_a_s is not None
                and pair.times_b_s is not None
            ):
                drift = (
                    DriftShare(pair.session_a, pair.times_a_s, pair.gains_a),
                    DriftShare(pair.session_b, pair.times_b_s, pair.gains_b),
                )
            edges.append(
                Edge(
                    "features",
                    f"{pair.session_a}-{pair.session_b}",
                    pair.session_a,
                    pair.session_b,
                    pair.a_from_b,
                    pair.covariance,
                    drift,
                )
            )
    if dof == 4:
        # Gravity-aligned, depth-fused frames: roll and pitch held (the 4-DoF limit).
        tilt_sigma_rad: float | None = 1e-5
    else:
        tilt_sigma_rad = None if tilt_prior_deg is None else float(np.deg2rad(tilt_prior_deg))
    depth_fused = all(s.depth_fused for s in sessions)
    return solve_joint(
        reference,
        [s.name for s in sessions],
        edges,
        tilt_sigma_rad=tilt_sigma_rad,
        depth_sigma_m=options.depth_sigma_m if depth_fused else None,
        drift_rates=rates,
    )


def _joint_placements(joint: JointEstimate, sessions: Sequence[Session]) -> dict[str, Placement]:
    placements = {}
    for session in sessions:
        if session.name not in joint.world_from_node:
            continue
        via = sorted(
            {
                r.edge.parent if r.edge.child == session.name else r.edge.child
                for r in joint.residuals
                if session.name in (r.edge.parent, r.edge.child) and r.weight > 0
            }
        )
        placements[session.name] = Placement(
            world_from_session=joint.world_from_node[session.name],
            covariance=joint.covariance[session.name],
            via=tuple(via),
        )
    return placements


def _joint_session_entry(
    entry: dict[str, Any], session: str, joint: JointEstimate, dof: int
) -> None:
    """Per session: the targets and pairs that placed it and their residuals."""
    entry["dof"] = dof
    entry["targets_used"] = sorted(
        r.edge.child.removeprefix("target:")
        for r in joint.residuals
        if r.edge.kind == "target" and r.edge.parent == session and r.weight > 0
    )
    entry["residuals"] = {
        r.edge.child.removeprefix("target:"): {
            "rotation_deg": r.rotation_deg,
            "translation_m": r.translation_m,
        }
        for r in joint.residuals
        if r.edge.kind == "target" and r.edge.parent == session
    }
    entry["constraints"] = [
        r.edge.label for r in joint.residuals if session in (r.edge.parent, r.edge.child)
    ]


def _joint_document(joint: JointEstimate | None, pairs: Sequence[PairEvidence]) -> dict[str, Any]:
    """The joint estimate's constraint residuals and the natural-feature evidence."""
    constraints = []
    for r in joint.residuals if joint is not None else ():
        constraints.append(
            {
                "kind": r.edge.kind,
                "label": r.edge.label,
                "parent": r.edge.parent,
                "child": r.edge.child,
                "rotation_residual_deg": r.rotation_deg,
                "translation_residual_m": r.translation_m,
                "whitened_norm": r.mahalanobis,
                "weight": r.weight,
                "rejected": r.outlier,
                "sigma_rotation_deg": float(
                    np.rad2deg(np.sqrt(np.trace(r.edge.covariance[:3, :3])))
                ),
                "sigma_translation_m": float(np.sqrt(np.trace(r.edge.covariance[3:, 3:]))),
            }
        )
    return {
        "estimator": "joint",
        "pairs": [p.summary() for p in pairs],
        "constraints": constraints,
        "iterations": joint.iterations if joint is not None else 0,
    }


def _seconds(chosen: Sequence[Observation], anchor_ns: int) -> FloatArray:
    """Seconds (N,) from the session anchor to each observation."""
    stamps = np.array([o.stamp_ns for o in chosen], dtype=np.int64)
    return seconds_from_ns(stamps - anchor_ns)


def pass_labels(stamps_ns: Sequence[int], *, gap_s: float) -> npt.NDArray[np.int64]:
    """Label (N,) each stamp (int64 ns, any order) with its pass: a new pass after a gap."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(stamps)
    gaps = np.diff(stamps[order]) > ns_from_seconds(gap_s)
    labels = np.empty(len(stamps), dtype=np.int64)
    labels[order] = np.concatenate(([0], np.cumsum(gaps))) if len(stamps) else []
    return labels


def _average_paper(
    sessions: Sequence[Session],
    target_names: Sequence[str],
    observations: Sequence[Observation],
) -> dict[str, dict[str, PoseAverage]]:
    from postproc.merge.paper import one_sigma_average

    averages: dict[str, dict[str, PoseAverage]] = {}
    for session in sessions:
        averages[session.name] = {}
        for name in target_names:
            chosen = [
                o.paper_session_from_target
                for o in observations
                if o.session == session.name
                and o.target == name
                and o.paper_session_from_target is not None
            ]
            if not chosen:
                continue
            poses = np.array(chosen)
            result = one_sigma_average(poses)
            residuals = pose_residuals(poses, result.pose)
            spread = robust_pose_mean(poses[result.inliers], mad_threshold=1e9).spread_covariance
            n = max(int(np.count_nonzero(result.inliers)), 1)
            averages[session.name][name] = PoseAverage(
                pose=result.pose,
                covariance=spread / n,
                spread_covariance=spread,
                inliers=result.inliers,
                residuals=residuals,
            )
    return averages


def _place_paper(
    estimates: dict[str, dict[str, TargetEstimate]], reference: str
) -> dict[str, Placement]:
    """The paper's step 3: sessions sharing targets with the reference, Euler-averaged."""
    from postproc.merge.align import TargetPair
    from postproc.merge.paper import combine_candidates

    placements = {reference: Placement(world_from_session=np.eye(4), covariance=np.zeros((6, 6)))}
    for session, targets in estimates.items():
        if session == reference:
            continue
        shared = [m for m in sorted(targets) if m in estimates[reference]]
        if not shared:
            continue
        pairs = [
            TargetPair(
                m,
                estimates[reference][m].pose,
                estimates[reference][m].covariance,
                targets[m].pose,
                targets[m].covariance,
            )
            for m in shared
        ]
        candidates = [p.candidate() for p in pairs]
        pose = combine_candidates(np.array([c[0] for c in candidates]))
        covariance = np.mean([c[1] for c in candidates], axis=0) / len(candidates)
        placements[session] = Placement(
            world_from_session=pose, covariance=covariance, via=(reference,)
        )
    return placements


def _world_targets(
    estimates: dict[str, dict[str, TargetEstimate]], placements: dict[str, Placement]
) -> dict[str, tuple[FloatArray, FloatArray]]:
    """Each target's pose in W: the fusion over the placed sessions that saw it."""
    per_target: dict[str, list[tuple[FloatArray, FloatArray]]] = {}
    for session, targets in estimates.items():
        placement = placements.get(session)
        if placement is None:
            continue
        for name, estimate in targets.items():
            per_target.setdefault(name, []).append(
                compose_with_covariance(
                    placement.world_from_session,
                    placement.covariance,
                    estimate.pose,
                    estimate.covariance,
                )
            )
    result = {}
    for name, values in per_target.items():
        if len(values) == 1:
            result[name] = values[0]
        else:
            result[name] = fuse_pose_estimates(
                np.array([v[0] for v in values]), np.array([v[1] for v in values])
            )
    return result


def _matrix(a: FloatArray) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(a)]


def _transforms_document(
    options: MergeOptions,
    sessions: Sequence[Session],
    reference: str,
    dof: int,
    depth_fused: bool,
    placements: dict[str, Placement],
    estimates: dict[str, dict[str, TargetEstimate]],
    tilt_prior_deg: float | None,
) -> dict[str, Any]:
    entries: dict[str, Any] = {}
    for session in sessions:
        placement = placements.get(session.name)
        entry: dict[str, Any] = {
            "folder": str(session.folder),
            "targets_seen": sorted(estimates[session.name]),
            "depth_fused": session.depth_fused,
        }
        if placement is None:
            entry["placed"] = False
            entry["reason"] = (
                "shares no target with the placed sessions; left for natural-feature "
                "merging in the SfM stage"
            )
        else:
            entry["placed"] = True
            entry["T_W_S"] = _matrix(placement.world_from_session)
            entry["covariance"] = _matrix(placement.covariance)
            entry["sigma_rotation_deg"] = float(
                np.rad2deg(np.sqrt(np.trace(placement.covariance[:3, :3])))
            )
            entry["sigma_translation_m"] = float(np.sqrt(np.trace(placement.covariance[3:, 3:])))
            entry["via"] = list(placement.via)
            if placement.alignment is not None:
                entry["targets_used"] = list(placement.alignment.target_names)
                entry["dof"] = placement.alignment.dof
                entry["residuals"] = {
                    name: {"rotation_deg": float(np.rad2deg(r)), "translation_m": t}
                    for name, (r, t) in zip(
                        placement.alignment.target_names,
                        placement.alignment.residuals_rad_m,
                        strict=True,
                    )
                }
            if placement.diagnostic_6dof is not None:
                six = placement.diagnostic_6dof.a_from_b
                entry["diagnostic_6dof"] = {
                    "T_W_S": _matrix(six),
                    "covariance": _matrix(placement.diagnostic_6dof.covariance),
                    "rotation_difference_deg": float(
                        np.rad2deg(rotation_difference_rad(six, placement.world_from_session))
                    ),
                    "translation_difference_m": float(
                        np.linalg.norm(six[:3, 3] - placement.world_from_session[:3, 3])
                    ),
                }
        entries[session.name] = entry
    return {
        "reference": reference,
        "method": options.method,
        "dof": dof,
        "depth_fused": depth_fused,
        "tilt_prior_sigma_deg": tilt_prior_deg,
        "covariance_convention": COVARIANCE_CONVENTION,
        "sessions": entries,
    }


def _drift_model_entry(model: DriftModel) -> dict[str, Any]:
    """A session's fitted drift model for transforms.json, per axis `[δθ, δt]`."""
    return {
        "pass_pairs": model.pass_pairs,
        "keyframe_noise_sigma": [float(v) for v in np.sqrt(model.noise)],
        "drift_sigma_per_sqrt_s": [float(v) for v in np.sqrt(model.drift_rate)],
        "variance_calibration": [float(v) for v in model.calibration],
        "units": "rad and m (per sqrt(s) for the drift); the calibration multiplies the "
        "variances of the session's target poses for the model's own fit",
    }


def _targets_document(
    target_names: Sequence[str],
    target_paths: Sequence[Path | str],
    sessions: Sequence[Session],
    averages: dict[str, dict[str, PoseAverage]],
    observations: Sequence[Observation],
    world_targets: dict[str, tuple[FloatArray, FloatArray]],
) -> dict[str, Any]:
    document: dict[str, Any] = {}
    for name, path in zip(target_names, target_paths, strict=True):
        entry: dict[str, Any] = {"file": str(path)}
        if name in world_targets:
            pose, covariance = world_targets[name]
            entry["T_W_m"] = _matrix(pose)
            entry["covariance"] = _matrix(covariance)
        per_session: dict[str, Any] = {}
        for session in sessions:
            average = averages[session.name].get(name)
            if average is None:
                continue
            chosen = [o for o in observations if o.session == session.name and o.target == name]
            per_session[session.name] = {
                "observations": len(chosen),
                "used": average.inlier_count,
                "rejected": len(chosen) - average.inlier_count,
                "rejected_stamps_ns": [
                    o.stamp_ns for o, keep in zip(chosen, average.inliers, strict=True) if not keep
                ],
                "T_S_m": _matrix(average.pose),
                "covariance": _matrix(average.covariance),
                "mean_reprojection_rms_px": float(np.mean([o.reprojection_rms_px for o in chosen])),
            }
        entry["sessions"] = per_session
        document[name] = entry
    return document
