"""Errors of a project's outputs against the survey simulator's truth (`truth.json`).

Measured when the project names a `truth` file (see `field/sim/__init__.py` for its
format), for whatever stages have finished:

- slam, per session: ATE (position RMSE after a rigid alignment, m) of `trajectory.tum`
  (body poses, camera clock) against the true body poses (true time = camera time +
  timeshift_cam_imu_s).
- depth, per session: the clock offset error (s; estimate minus the true dive-computer
  minus camera offset at the trajectory's first stamp), and the z error of
  `trajectory_world_fused.tum` (or `trajectory_world.tum`) against the true z, no
  alignment (mean = depth offset error, RMS), metres.
- merge: the merged keyframe camera positions of all sessions aligned to the truth with
  one rigid transform: RMS position error (m) overall and per session (how well the
  sessions sit together).
- sfm: the same on the refined keyframes (`sessions/<name>/keyframes_world.tum`).
- dense: mesh.ply (or fused.ply) vertices moved into the truth frame with the SfM (or
  merge) alignment, then accuracy (share of points within d of the truth surface),
  completeness (share of the filmed truth surface within d of the reconstruction: of its
  triangles for a mesh, of its points for a cloud) at d = 0.05, 0.10, 0.20 m, and the
  median distance.

  "Filmed" (`CompletenessOptions`): truth-surface samples seen by at least 3 of the
  keyframes (those the SfM, else the merge, aligned), each placed at its true camera pose
  (true body pose at the keyframe's true time times the true camera-from-IMU) with the
  true camera (truth.json's intrinsics and distortion): in front of it, inside the real
  image, within 8 m and not hidden behind another part of the truth mesh (a z-buffer of
  the mesh per keyframe at about a quarter of the image's resolution). The far side of the hull,
  the seafloor under and behind the wreck and whatever lay beyond the water's reach
  never count against the reconstruction. The earlier figure, the share of samples
  inside the reconstruction's bounding box (+- 0.1 m), is kept as `completeness_bbox`;
  without camera intrinsics in the truth file it is the only one (`completeness_basis`
  says which a figure is).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.clock import ns_from_seconds, seconds_from_ns
from shared.errors import InputError

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
THRESHOLDS_M = (0.05, 0.10, 0.20)
#: A point cloud's completeness is measured on at most this many of its points.
COMPLETENESS_MAX_POINTS = 5_000_000


@dataclass(kw_only=True)
class CompletenessOptions:
    """Which truth-surface samples count as filmed (the completeness denominator).

    min_views: keyframes that must see a sample; max_range_m: farthest camera-to-sample
    distance that counts (m). 8 m is one attenuation length of the green channel (1/0.13
    m^-1 = 7.7 m) of the simulator's water (`field.sim.render.WaterModel`; truth.json
    does not record the water), green and blue carrying most of the grey image: beyond it
    the wreck fades into the backscatter; it is also the reach bench_dense.py samples.
    image_scale: depth-map size as a fraction of the image's focal length (a quarter:
    211x119 for the demo's 640x360 camera, whose barrel distortion widens the pinhole
    that holds its view); near_m: the z-buffer's near plane (m); tolerance_m,
    tolerance_rel: occlusion tolerance (see `postproc.dense.evaluate.seen_counts`);
    sample_spacing_m: about one truth sample per sample_spacing_m^2 of surface (the
    scores are fractions: 0.1 m gives ~250 000 samples over the demo's scene, ~33 000 of
    them filmed, plenty); max_keyframes: keyframes used at most, evenly subsampled
    beyond (a sample must then be seen by min_views of that subset); it bounds the time
    on long dives (the demo's 364 keyframes are all used).
    """

    min_views: int = 3
    max_range_m: float = 8.0
    image_scale: float = 0.25
    near_m: float = 0.05
    tolerance_m: float = 0.02
    tolerance_rel: float = 0.015
    sample_spacing_m: float = 0.1
    max_keyframes: int = 1000


def read_truth(path: Path) -> dict[str, Any]:
    """The simulator's truth.json; InputError when it is not one."""
    try:
        truth = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise InputError(f"{path}: cannot read the truth file ({error})") from None
    if not isinstance(truth, dict) or truth.get("format") != "wreckmap-sim-truth":
        raise InputError(f"{path}: not a simulator truth file (expected format wreckmap-sim-truth)")
    return truth


def _truth_body(truth_path: Path, entry: dict[str, Any]) -> Any:
    from shared.formats.tum import read_tum

    return read_tum(truth_path.parent / entry["files"]["trajectory"])


def _positions_at(
    trajectory: Any, stamps_ns: npt.NDArray[np.int64]
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    from shared.geometry import interpolate_poses

    inside = (stamps_ns >= trajectory.stamps_ns[0]) & (stamps_ns <= trajectory.stamps_ns[-1])
    poses = interpolate_poses(trajectory.stamps_ns, trajectory.poses, stamps_ns[inside])
    return poses, inside


def _rigid(source: FloatArray, target: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(T_target_source 4x4, errors (N,) after alignment)."""
    from shared.geometry import umeyama_pose

    T = umeyama_pose(source, target)
    moved = source @ T[:3, :3].T + T[:3, 3]
    return T, np.linalg.norm(moved - target, axis=1)


def camera_to_true_ns(
    project: Any,
    session: Any,
    entry: dict[str, Any],
    shift_ns: int,
    stages: Mapping[str, Any] | None = None,
) -> int:
    """What to add to a session's camera stamps to get true time (ns).

    EuRoC folders of the simulator are stamped on the camera clock (true = cam + shift).
    A GoPro import is stamped on the GoPro's clock: its creation time (whole seconds, in
    the imported session.yaml) plus media time, where media time 0 is frame 0 whose true
    exposure time is first_frame_cam_ns + shift. A session folder given as such (a GoPro
    import cut by bench_pipeline.py, say) is on the GoPro's clock when its session.yaml
    has one, else on the camera clock.
    """
    import yaml

    from postproc.pipeline.stages import RunFolders
    from shared.folders import SessionFolder

    if session.source == "gopro":
        path = RunFolders(project.output, stages).imported(session.name).session_yaml
    elif session.source == "session":
        path = SessionFolder(session.paths[0]).session_yaml
        if not path.is_file():
            return shift_ns
    else:
        return shift_ns
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
        clocks = document.get("clocks") if isinstance(document, dict) else None
        if session.source == "session" and not (isinstance(clocks, dict) and "gopro" in clocks):
            return shift_ns  # a recorder's session: the camera clock
        creation_ns = int(document["clocks"]["gopro"]["creation_time_ns"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as error:
        raise InputError(
            f"{path}: no clocks.gopro.creation_time_ns ({error}); expected the imported session"
        ) from None
    return int(entry["first_frame_cam_ns"]) + shift_ns - creation_ns


def _rms(values: FloatArray) -> float:
    return float(np.sqrt(np.mean(values * values))) if values.size else float("nan")


def evaluate_project(project: Any, stages: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Every error measurable from the finished outputs of `project` (a dict for JSON);
    stages: the registry the run used (default `STAGES`; the quick look's places its
    imports in the full run's folder)."""
    from postproc.pipeline.stages import RunFolders
    from shared.geometry import invert_pose

    if project.truth is None:
        return {}
    truth = read_truth(project.truth)
    shift_ns = ns_from_seconds(float(truth["camera"]["timeshift_cam_imu_s"]))
    cam_from_imu = np.asarray(truth["camera"]["cam_from_imu"], dtype=np.float64)
    imu_from_cam = invert_pose(cam_from_imu)
    folders = RunFolders(project.output, stages)
    result: dict[str, Any] = {"truth": str(project.truth), "sessions": {}}
    cam_truth: dict[str, tuple[int, Any]] = {}
    for index, session in enumerate(project.sessions):
        k = session.truth_session if session.truth_session is not None else index
        if k >= len(truth["sessions"]):
            log.warning("%s: no truth session %d", session.name, k)
            continue
        entry = truth["sessions"][k]
        body = _truth_body(project.truth, entry)
        try:
            to_true_ns = camera_to_true_ns(project, session, entry, shift_ns, stages)
        except InputError as error:
            result["sessions"][session.name] = {"note": str(error)}
            continue
        cam_truth[session.name] = (to_true_ns, body)
        errors: dict[str, Any] = {"truth_session": entry["name"]}
        slam = folders.slam(session.name)
        if slam.trajectory.is_file():
            estimate = slam.read_trajectory()
            poses, inside = _positions_at(body, estimate.stamps_ns + to_true_ns)
            if np.count_nonzero(inside) >= 3:
                _, e = _rigid(estimate.positions[inside], poses[:, :3, 3])
                errors["slam_ate_m"] = _rms(e)
                errors["slam_poses"] = int(np.count_nonzero(inside))
        depth = folders.depth(session.name)
        if depth.sync.is_file():
            sync = depth.read_sync()
            dc = entry["clocks"]["dive_computer"]
            ref_cam_s = float(sync["reference_time_s"])
            # dive time - camera time = (dive - true) + (true - camera), at the reference.
            true_s = ref_cam_s + seconds_from_ns(to_true_ns)
            true_offset = (
                seconds_from_ns(int(dc["offset_ns"]))
                + seconds_from_ns(to_true_ns)
                + dc["drift_ppm"] * 1e-6 * (true_s - seconds_from_ns(int(dc["reference_ns"])))
            )
            errors["depth_time_offset_error_s"] = float(sync["time_offset_s"]) - true_offset
            worlds = (
                (depth.trajectory_world_fused, depth.read_world_fused),
                (depth.trajectory_world, depth.read_world),
            )
            for world_path, read_world in worlds:
                if world_path.is_file():
                    world = read_world()
                    poses, inside = _positions_at(body, world.stamps_ns + to_true_ns)
                    dz = world.positions[inside, 2] - poses[:, 2, 3]
                    if dz.size:
                        errors["depth_offset_error_m"] = float(np.mean(dz))
                        errors["depth_z_rms_m"] = _rms(dz)
                        errors["depth_trajectory"] = world_path.name
                    break
        result["sessions"][session.name] = errors

    true_keyframes: dict[str, FloatArray] = {}  # label -> true world_from_cam (K,4,4)

    def keyframe_errors(
        path: Callable[[str], Path], read: Callable[[str], Any], label: str
    ) -> FloatArray | None:
        """The error of each session's keyframes (`read(name)`, where `path(name)` is)."""
        est, ref, owner, true_poses = [], [], [], []
        for name in (s.name for s in project.sessions):
            if name not in cam_truth or not path(name).is_file():
                continue
            shift, body = cam_truth[name]
            keyframes = read(name)
            poses, inside = _positions_at(body, keyframes.stamps_ns + shift)
            world_from_cam = poses @ imu_from_cam
            est.append(keyframes.positions[inside])
            ref.append(world_from_cam[:, :3, 3])
            true_poses.append(world_from_cam)
            owner += [name] * int(np.count_nonzero(inside))
        if not est or sum(len(e) for e in est) < 3:
            return None
        true_keyframes[label] = np.concatenate(true_poses)
        source, target = np.concatenate(est), np.concatenate(ref)
        T, e = _rigid(source, target)
        owners = np.asarray(owner)
        result[label] = {
            "rms_m": _rms(e),
            "keyframes": len(e),
            "sessions": {n: _rms(e[owners == n]) for n in sorted(set(owner))},
        }
        return T

    merge, sfm = folders.merge(), folders.sfm()
    merge_T = keyframe_errors(merge.merged_keyframes, merge.read_merged_keyframes, "merge")
    sfm_T = keyframe_errors(sfm.session_keyframes_world, sfm.read_session_keyframes_world, "sfm")
    alignment = sfm_T if sfm_T is not None else merge_T
    keyframes = true_keyframes.get("sfm" if sfm_T is not None else "merge")
    dense = folders.dense()
    for dense_path in (dense.mesh, dense.fused):
        if dense_path.is_file() and alignment is not None:
            result["dense"] = evaluate_mesh(
                dense_path,
                project.truth.parent / truth["world"]["mesh"],
                alignment,
                camera=truth_camera(truth),
                world_from_cams=keyframes,
            )
            result["dense"]["file"] = dense_path.name
            break
    return result


def truth_camera(truth: dict[str, Any]) -> Any:
    """The simulator's camera (a `shared.calibration.cameras` model) from truth.json's
    `camera` entry; None when the entry holds no intrinsics (InputError for a model the
    cameras module does not know)."""
    from shared.calibration.cameras import CAMERA_MODELS

    camera = truth.get("camera", {})
    if "intrinsics_fx_fy_cx_cy" not in camera:
        return None
    model = tuple(camera.get("model", ("pinhole", "radtan")))
    if model not in CAMERA_MODELS:
        raise InputError(
            f"truth.json: camera model {model} unknown (expected one of {sorted(CAMERA_MODELS)})"
        )
    return CAMERA_MODELS[model].from_kalibr(
        (int(camera["width"]), int(camera["height"])),
        [float(x) for x in camera["intrinsics_fx_fy_cx_cy"]],
        [float(x) for x in camera["distortion_k1_k2_p1_p2"]],
    )


def evaluate_mesh(
    recon_path: Path,
    truth_mesh_path: Path,
    truth_from_recon: FloatArray,
    *,
    camera: Any = None,
    world_from_cams: FloatArray | None = None,
    options: CompletenessOptions | None = None,
) -> dict[str, Any]:
    """Accuracy and completeness (fractions) of a PLY's vertices against the truth mesh.

    camera: the true camera model (`truth_camera`); world_from_cams: (K,4,4) true poses of
    the keyframes in the truth frame. With both, completeness counts only the truth
    surface those keyframes filmed (see the module docstring and `CompletenessOptions`);
    without, it falls back to the samples inside the reconstruction's bounding box.
    `completeness_bbox` is always that bounding-box figure.
    """
    from scipy.spatial import cKDTree

    from postproc.dense.evaluate import (
        Scores,
        distance_to_mesh,
        distance_to_surface,
        sample_surface,
        seen_counts,
        undistorted_canvas,
    )
    from shared.formats.ply import read_ply

    options = options or CompletenessOptions()
    data = read_ply(recon_path)
    truth = read_ply(truth_mesh_path)
    if truth.faces is None or len(truth.faces) == 0:
        raise InputError(f"{truth_mesh_path}: no triangles (expected the truth mesh)")
    rng = np.random.default_rng(0)
    everything = data.vertices @ truth_from_recon[:3, :3].T + truth_from_recon[:3, 3]
    faces = data.faces if data.faces is not None and len(data.faces) else None
    # Accuracy is a share of the points: a fixed sample is enough. Completeness is not:
    # it needs the whole surface (a mesh's triangles), or a cloud's points, up to a cap
    # that bounds the memory of the tree over a fused cloud of many millions.
    points = everything
    if len(points) > 200_000:
        points = points[rng.choice(len(points), 200_000, replace=False)]
    cover = everything
    if faces is None and len(cover) > COMPLETENESS_MAX_POINTS:
        cover = cover[rng.choice(len(cover), COMPLETENESS_MAX_POINTS, replace=False)]
    samples, _ = sample_surface(truth.vertices, truth.faces, options.sample_spacing_m, seed=0)
    lo, hi = points.min(axis=0) - 0.1, points.max(axis=0) + 0.1
    in_box = samples[np.all((samples >= lo) & (samples <= hi), axis=1)]
    result: dict[str, Any] = {"points": len(points)}
    seen = None
    if camera is not None and world_from_cams is not None and len(world_from_cams) > 0:
        from shared.geometry import invert_pose

        poses = np.asarray(world_from_cams, dtype=np.float64)
        if len(poses) > options.max_keyframes:
            poses = poses[np.linspace(0, len(poses) - 1, options.max_keyframes).round().astype(int)]
        K, width, height, filmed = undistorted_canvas(camera, options.image_scale)
        counts = seen_counts(
            samples,
            truth.vertices,
            truth.faces,
            K,
            width,
            height,
            [invert_pose(p) for p in poses],
            filmed=filmed,
            max_range_m=options.max_range_m,
            near_m=options.near_m,
            tolerance_m=options.tolerance_m,
            tolerance_rel=options.tolerance_rel,
            progress_label="evaluate: filmed truth surface",
        )
        seen = samples[counts >= options.min_views]
        result["completeness_basis"] = (
            f"truth surface filmed: seen by >= {options.min_views} of {len(poses)} keyframes "
            f"within {options.max_range_m:g} m, occlusion tested"
        )
        result["filmed_samples"] = len(seen)
    else:
        result["completeness_basis"] = "truth surface inside the reconstruction's bounding box"
    result["truth_samples"] = len(samples)
    result["bbox_samples"] = len(in_box)
    distances = distance_to_mesh(points, truth.vertices, truth.faces)
    tree = cKDTree(cover) if faces is None else None

    def within(targets: FloatArray) -> FloatArray:
        if not len(targets):
            return np.zeros(0)
        if faces is not None:
            return distance_to_surface(targets, cover, faces)
        assert tree is not None
        return np.asarray(tree.query(targets)[0], dtype=np.float64)

    to_box = within(in_box)
    to_seen = within(seen) if seen is not None else to_box

    def share(values: FloatArray, d: float) -> float:
        return float(np.mean(values <= d)) if len(values) else 0.0

    scores = []
    for d in THRESHOLDS_M:
        s = Scores(threshold_m=d, accuracy=share(distances, d), completeness=share(to_seen, d))
        scores.append(
            {
                "threshold_m": d,
                "accuracy": s.accuracy,
                "completeness": s.completeness,
                "f1": s.f1,
                "completeness_bbox": share(to_box, d),
            }
        )
    result["median_distance_m"] = float(np.median(distances))
    result["scores"] = scores
    return result
