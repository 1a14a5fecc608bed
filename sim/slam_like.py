"""SLAM-like result folders from the survey simulator, with known truth (tests and bench).

The SfM stage is fed what SLAM produces, without running SLAM: keyframes picked
from the simulated camera at about `keyframe_hz`, rendered as recorded (distorted), with
camera poses `T_S_C` in a gravity-aligned session frame `S` whose origin is the first
keyframe, perturbed by a drift that grows along the path (a random walk in position
and heading, as visual-inertial odometry drifts) plus small per-keyframe jitter.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from shared.folders import MergeFolder, SlamFolder
from shared.geometry import invert_pose, make_pose, so3_exp
from shared.trajectory import Trajectory
from sim.survey import SurveyOptions, SurveySimulator

FloatArray = npt.NDArray[np.float64]


@dataclass
class SlamLikeSession:
    """One written SLAM-like folder and its truth.

    world_from_session: true `T_W_S` (4, 4); truth_world_from_cam: true `T_W_C` of the
    keyframes (same stamps as `keyframes.tum`); estimate: the written `T_S_C` poses.
    """

    folder: Path
    world_from_session: FloatArray
    truth_world_from_cam: Trajectory
    estimate: Trajectory

    @property
    def truth_session_from_cam(self) -> Trajectory:
        """True keyframe poses `T_S_C` in the session frame."""
        return self.truth_world_from_cam.transformed(invert_pose(self.world_from_session))


def drifting_poses(
    session_from_cam: FloatArray,
    rng: np.random.Generator,
    *,
    drift_per_m: float,
    yaw_drift_deg_per_m: float,
    jitter_m: float,
    jitter_deg: float,
) -> FloatArray:
    """Perturb true poses `T_S_C` (N, 4, 4) by a path-proportional random-walk drift.

    The drift is applied as an error transform about the session origin (the first
    pose stays nearly exact) whose translation grows like a random walk with a standard
    deviation of `drift_per_m` times the distance travelled, plus a heading (yaw about z)
    random walk; each pose also gets independent jitter.
    """
    positions = session_from_cam[:, :3, 3]
    steps = np.r_[0.0, np.linalg.norm(np.diff(positions, axis=0), axis=1)]
    n = len(session_from_cam)
    walk = np.cumsum(rng.normal(size=(n, 3)) * np.sqrt(steps)[:, None], axis=0) * drift_per_m
    # A biased walk looks more like VIO drift (scale and heading errors grow steadily).
    bias = rng.normal(size=3)
    bias /= np.linalg.norm(bias)
    walk += np.cumsum(steps)[:, None] * bias * drift_per_m
    yaw = np.cumsum(rng.normal(size=n) * np.sqrt(steps)) * np.deg2rad(yaw_drift_deg_per_m)
    out = np.empty_like(session_from_cam)
    for i in range(n):
        error = make_pose(so3_exp([0.0, 0.0, yaw[i]]), walk[i])
        jitter = make_pose(
            so3_exp(rng.normal(size=3) * np.deg2rad(jitter_deg)), rng.normal(size=3) * jitter_m
        )
        out[i] = jitter @ error @ session_from_cam[i]
    return out


def write_slam_like_survey(
    out_dir: Path,
    *,
    sessions: int = 2,
    duration_s: float = 20.0,
    keyframe_hz: float = 2.0,
    width: int = 320,
    height: int = 240,
    texel_m: float = 0.02,
    seed: int = 1,
    drift_per_m: float = 0.02,
    yaw_drift_deg_per_m: float = 0.1,
    jitter_m: float = 0.01,
    jitter_deg: float = 0.2,
    write_stats: bool = True,
) -> list[SlamLikeSession]:
    """Render keyframes of a simulated survey into one SLAM-like folder per session.

    Writes `out_dir/session_NN/{keyframes.tum, keyframes/<ns>.png, calib/camchain.yaml,
    stats.json}`. Image stamps are the camera clock (int64 ns); `T_S_C` as SLAM would
    report them. Returns the sessions with their truth.
    """
    options = SurveyOptions(
        sessions=sessions,
        duration_s=duration_s,
        seed=seed,
        width=width,
        height=height,
        video=False,
        texel_m=texel_m,
        seafloor_texel_m=max(2.0 * texel_m, 0.005),
    )
    sim = SurveySimulator(options)
    rng = np.random.default_rng(seed + 1000)
    result: list[SlamLikeSession] = []
    for k, truth in enumerate(sim.sessions):
        stride = max(round(options.fps / keyframe_hz), 1)
        stamps = truth.frame_stamps_cam_ns[::stride].astype(np.int64)
        world_from_cam = sim.world_from_cam(k, stamps)
        # Session frame: gravity-aligned, origin at the first keyframe, an arbitrary heading.
        heading = float(rng.uniform(-np.pi, np.pi))
        world_from_session = make_pose(so3_exp([0.0, 0.0, heading]), world_from_cam[0, :3, 3])
        session_from_cam = invert_pose(world_from_session) @ world_from_cam
        estimate = drifting_poses(
            session_from_cam,
            rng,
            drift_per_m=drift_per_m,
            yaw_drift_deg_per_m=yaw_drift_deg_per_m,
            jitter_m=jitter_m,
            jitter_deg=jitter_deg,
        )
        folder = out_dir / truth.name
        slam = SlamFolder(folder)
        slam.keyframes.mkdir(parents=True, exist_ok=True)
        for stamp in stamps.tolist():
            frame = sim.render_frame(k, stamp)
            gray = cv2.cvtColor(frame.image_rgb, cv2.COLOR_RGB2GRAY)
            cv2.imwrite(str(slam.keyframe_image(stamp)), gray)
        estimate_trajectory = Trajectory(stamps, estimate)
        slam.write_keyframes(estimate_trajectory)
        slam.write_camchain([sim.calibration])
        if write_stats:
            path = Trajectory(stamps, session_from_cam).path_length_m()
            stats = {"keyframes": len(stamps), "path_length_m": path, "drift_per_m": drift_per_m}
            slam.write_stats(stats, overwrite=True)
        result.append(
            SlamLikeSession(
                folder=folder,
                world_from_session=world_from_session,
                truth_world_from_cam=Trajectory(stamps, world_from_cam),
                estimate=estimate_trajectory,
            )
        )
    return result


def write_merge_like(
    out_dir: Path,
    sessions: list[SlamLikeSession],
    *,
    placed: list[bool],
    error_m: float = 0.0,
    seed: int = 2,
) -> Path:
    """A merge-stage-like folder: `transforms.json` with `T_W_S` per session folder name
    (and the 6x6 covariance, rotation first) and `<session>/keyframes_merged.tum`.

    Placed sessions get their true `T_W_S` (translated by a random `error_m` offset);
    the others `"placed": false`. Returns `out_dir`.
    """
    rng = np.random.default_rng(seed)
    merge = MergeFolder(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries: dict[str, object] = {}
    for session, is_placed in zip(sessions, placed, strict=True):
        T = session.world_from_session.copy()
        if is_placed and error_m > 0:
            T[:3, 3] += rng.normal(size=3) * error_m
        if is_placed:
            merge.write_merged_keyframes(session.folder.name, session.estimate.transformed(T))
        entries[session.folder.name] = {
            "folder": str(session.folder),
            "placed": is_placed,
            "T_W_S": T.tolist() if is_placed else None,
            "covariance": (np.eye(6) * max(error_m, 0.01) ** 2).tolist() if is_placed else None,
        }
    merge.write_transforms({"sessions": entries}, overwrite=True)
    return out_dir
