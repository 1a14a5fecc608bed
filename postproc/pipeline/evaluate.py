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
  merge) alignment, then accuracy (share of points within d of the truth surface) and
  completeness (share of truth-surface samples inside the reconstruction's bounding box
  within d of a point), at d = 0.05, 0.10, 0.20 m, and the median distance.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.errors import InputError

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
THRESHOLDS_M = (0.05, 0.10, 0.20)


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


def camera_to_true_ns(project: Any, session: Any, entry: dict[str, Any], shift_ns: int) -> int:
    """What to add to a session's camera stamps to get true time (ns).

    EuRoC folders of the simulator are stamped on the camera clock (true = cam + shift).
    A GoPro import is stamped on the GoPro's clock: its creation time (whole seconds, in
    the imported session.yaml) plus media time, where media time 0 is frame 0 whose true
    exposure time is first_frame_cam_ns + shift.
    """
    if session.source != "gopro":
        return shift_ns
    import yaml

    path = project.output / "imports" / session.name / "session.yaml"
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
        creation_ns = int(document["clocks"]["gopro"]["creation_time_ns"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as error:
        raise InputError(
            f"{path}: no clocks.gopro.creation_time_ns ({error}); expected the imported session"
        ) from None
    return int(entry["first_frame_cam_ns"]) + shift_ns - creation_ns


def _rms(values: FloatArray) -> float:
    return float(np.sqrt(np.mean(values * values))) if values.size else float("nan")


def evaluate_project(project: Any) -> dict[str, Any]:
    """Every error measurable from the finished outputs of `project` (a dict for JSON)."""
    from shared.formats.tum import read_tum
    from shared.geometry import invert_pose

    if project.truth is None:
        return {}
    truth = read_truth(project.truth)
    shift_ns = round(float(truth["camera"]["timeshift_cam_imu_s"]) * 1e9)
    cam_from_imu = np.asarray(truth["camera"]["cam_from_imu"], dtype=np.float64)
    imu_from_cam = invert_pose(cam_from_imu)
    out = project.output
    result: dict[str, Any] = {"truth": str(project.truth), "sessions": {}}
    cam_truth: dict[str, tuple[npt.NDArray[np.int64], Any]] = {}
    for index, session in enumerate(project.sessions):
        k = session.truth_session if session.truth_session is not None else index
        if k >= len(truth["sessions"]):
            log.warning("%s: no truth session %d", session.name, k)
            continue
        entry = truth["sessions"][k]
        body = _truth_body(project.truth, entry)
        try:
            to_true_ns = camera_to_true_ns(project, session, entry, shift_ns)
        except InputError as error:
            result["sessions"][session.name] = {"note": str(error)}
            continue
        cam_truth[session.name] = (to_true_ns, body)
        errors: dict[str, Any] = {"truth_session": entry["name"]}
        slam_dir = out / "sessions" / session.name
        if (slam_dir / "trajectory.tum").is_file():
            estimate = read_tum(slam_dir / "trajectory.tum")
            poses, inside = _positions_at(body, estimate.stamps_ns + to_true_ns)
            if np.count_nonzero(inside) >= 3:
                _, e = _rigid(estimate.positions[inside], poses[:, :3, 3])
                errors["slam_ate_m"] = _rms(e)
                errors["slam_poses"] = int(np.count_nonzero(inside))
        depth_dir = slam_dir / "depth"
        if (depth_dir / "sync.json").is_file():
            sync = json.loads((depth_dir / "sync.json").read_text(encoding="utf-8"))
            dc = entry["clocks"]["dive_computer"]
            ref_cam_s = float(sync["reference_time_s"])
            # dive time - camera time = (dive - true) + (true - camera), at the reference.
            true_s = ref_cam_s + to_true_ns * 1e-9
            true_offset = (
                dc["offset_ns"] * 1e-9
                + to_true_ns * 1e-9
                + dc["drift_ppm"] * 1e-6 * (true_s - dc["reference_ns"] * 1e-9)
            )
            errors["depth_time_offset_error_s"] = float(sync["time_offset_s"]) - true_offset
            for name in ("trajectory_world_fused.tum", "trajectory_world.tum"):
                if (depth_dir / name).is_file():
                    world = read_tum(depth_dir / name)
                    poses, inside = _positions_at(body, world.stamps_ns + to_true_ns)
                    dz = world.positions[inside, 2] - poses[:, 2, 3]
                    if dz.size:
                        errors["depth_offset_error_m"] = float(np.mean(dz))
                        errors["depth_z_rms_m"] = _rms(dz)
                        errors["depth_trajectory"] = name
                    break
        result["sessions"][session.name] = errors

    def keyframe_errors(paths: dict[str, Path], label: str) -> FloatArray | None:
        est, ref, owner = [], [], []
        for name, path in paths.items():
            if name not in cam_truth or not path.is_file():
                continue
            shift, body = cam_truth[name]
            keyframes = read_tum(path)
            poses, inside = _positions_at(body, keyframes.stamps_ns + shift)
            world_from_cam = poses @ imu_from_cam
            est.append(keyframes.positions[inside])
            ref.append(world_from_cam[:, :3, 3])
            owner += [name] * int(np.count_nonzero(inside))
        if not est or sum(len(e) for e in est) < 3:
            return None
        source, target = np.concatenate(est), np.concatenate(ref)
        T, e = _rigid(source, target)
        owners = np.asarray(owner)
        result[label] = {
            "rms_m": _rms(e),
            "keyframes": len(e),
            "sessions": {n: _rms(e[owners == n]) for n in sorted(set(owner))},
        }
        return T

    merge_T = keyframe_errors(
        {s.name: out / "merge" / s.name / "keyframes_merged.tum" for s in project.sessions},
        "merge",
    )
    sfm_T = keyframe_errors(
        {
            s.name: out / "sfm" / "sessions" / s.name / "keyframes_world.tum"
            for s in project.sessions
        },
        "sfm",
    )
    alignment = sfm_T if sfm_T is not None else merge_T
    dense_dir = out / "dense"
    for name in ("mesh.ply", "fused.ply"):
        if (dense_dir / name).is_file() and alignment is not None:
            result["dense"] = evaluate_mesh(
                dense_dir / name, project.truth.parent / truth["world"]["mesh"], alignment
            )
            result["dense"]["file"] = name
            break
    return result


def evaluate_mesh(
    recon_path: Path, truth_mesh_path: Path, truth_from_recon: FloatArray
) -> dict[str, Any]:
    """Accuracy and completeness (fractions) of a PLY's vertices against the truth mesh."""
    from postproc.dense.evaluate import distance_to_mesh, evaluate, sample_surface
    from postproc.dense.ply import read_ply

    recon = read_ply(recon_path).vertices
    truth = read_ply(truth_mesh_path)
    if truth.faces is None or len(truth.faces) == 0:
        raise InputError(f"{truth_mesh_path}: no triangles (expected the truth mesh)")
    rng = np.random.default_rng(0)
    if len(recon) > 200_000:  # the scores are fractions: a fixed sample is enough
        recon = recon[rng.choice(len(recon), 200_000, replace=False)]
    points = recon @ truth_from_recon[:3, :3].T + truth_from_recon[:3, 3]
    samples, _ = sample_surface(truth.vertices, truth.faces, 0.05, seed=0)
    lo, hi = points.min(axis=0) - 0.1, points.max(axis=0) + 0.1
    samples = samples[np.all((samples >= lo) & (samples <= hi), axis=1)]
    scores = evaluate(points, truth.vertices, truth.faces, samples, thresholds_m=THRESHOLDS_M)
    distances = distance_to_mesh(points, truth.vertices, truth.faces)
    return {
        "points": len(points),
        "median_distance_m": float(np.median(distances)),
        "scores": [
            {
                "threshold_m": s.threshold_m,
                "accuracy": s.accuracy,
                "completeness": s.completeness,
                "f1": s.f1,
            }
            for s in scores
        ],
    }
