"""The paper's merging method (Mapping Pamir, "Trajectory Correlation"), for comparison.

Pure math: no I/O. As published:

1. Per observation, a pose per tag (PnP on that tag's 4 corners); the
   target's pose is the arithmetic mean of the tags' translations and of
   their roll, pitch and yaw angles.
2. Per target, across observations: drop those whose distance to the mean
   translation is beyond one standard deviation from the mean distance; then
   drop those with any of roll, pitch or yaw beyond one standard deviation
   from that angle's mean; average the rest (translations and Euler angles).
3. Per shared target, `T_A_B = T_A_m @ inv(T_B_m)`; the candidates' Euler
   angles and translations are averaged arithmetically.

Euler angles are roll-pitch-yaw about fixed x, y, z: `R = Rz(yaw) Ry(pitch) Rx(roll)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.merge.target_pose import estimate_target_pose
from shared.calibration.aprilgrid_detection import GridObservation
from shared.calibration.cameras import CameraModel
from shared.geometry import make_pose

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def euler_rpy_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """(roll, pitch, yaw) in rad of rotations (..., 3, 3), `R = Rz(yaw) Ry(pitch) Rx(roll)`."""
    M = np.asarray(R, dtype=np.float64)
    roll = np.arctan2(M[..., 2, 1], M[..., 2, 2])
    pitch = np.arcsin(np.clip(-M[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(M[..., 1, 0], M[..., 0, 0])
    return np.stack((roll, pitch, yaw), axis=-1)


def matrix_from_euler_rpy(rpy: npt.ArrayLike) -> FloatArray:
    """Rotation (3, 3) of (roll, pitch, yaw) in rad: `Rz(yaw) Ry(pitch) Rx(roll)`."""
    roll, pitch, yaw = np.asarray(rpy, dtype=np.float64)
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    result: FloatArray = Rz @ Ry @ Rx
    return result


def euler_mean_pose(poses: npt.ArrayLike) -> FloatArray:
    """Arithmetic mean of translations and of roll, pitch, yaw of poses (N, 4, 4)."""
    T = np.asarray(poses, dtype=np.float64)
    rpy = euler_rpy_from_matrix(T[:, :3, :3]).mean(axis=0)
    return make_pose(matrix_from_euler_rpy(rpy), T[:, :3, 3].mean(axis=0))


def per_tag_target_pose(camera: CameraModel, observation: GridObservation) -> FloatArray | None:
    """`T_C_m` from one PnP per tag (4 corners, in target coordinates), Euler-averaged.

    None when no tag gives a pose.
    """
    poses = []
    for obj, img in zip(observation.object_points_m, observation.image_points_px, strict=True):
        estimate = estimate_target_pose(camera, obj, img, min_outlier_px=np.inf)
        if estimate is not None:
            poses.append(estimate.cam_from_target)
    if not poses:
        return None
    return euler_mean_pose(np.array(poses))


@dataclass(frozen=True)
class PaperAverage:
    """The paper's per-target mean: `pose` (4, 4) and the `inliers` (N,) kept."""

    pose: FloatArray
    inliers: BoolArray


def one_sigma_average(poses: npt.ArrayLike) -> PaperAverage:
    """Step 2: one-sigma rejection on translation distance, then on each Euler angle."""
    T = np.asarray(poses, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] == 0:
        raise ValueError(f"one_sigma_average: expected (N, 4, 4) poses, got {T.shape}")
    translations = T[:, :3, 3]
    distance = np.linalg.norm(translations - translations.mean(axis=0), axis=1)
    inliers = np.abs(distance - distance.mean()) <= distance.std()
    rpy = euler_rpy_from_matrix(T[:, :3, :3])
    kept = rpy[inliers]
    within = np.all(np.abs(rpy - kept.mean(axis=0)) <= kept.std(axis=0), axis=1)
    inliers &= within
    if not np.any(inliers):
        inliers = np.ones(len(T), dtype=bool)
    return PaperAverage(pose=euler_mean_pose(T[inliers]), inliers=inliers)


def combine_candidates(candidates: npt.ArrayLike) -> FloatArray:
    """Step 3: the Euler/arithmetic mean of per-target candidates `T_A_B` (M, 4, 4)."""
    return euler_mean_pose(candidates)
