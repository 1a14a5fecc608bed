"""Visual-only baseline (`--no-imu`): the same frontend, keyframes and landmarks, no IMU.

Pure computation (no files). It exists to show what the IMU buys, so it is
deliberately the VIO pipeline minus the inertial terms rather than a tuned
monocular SLAM:

- start: two-view geometry between the first keyframe and the first later one
  with enough parallax (essential matrix, RANSAC), the keyframes in between
  placed by PnP on the two-view points;
- the gauge: the first pose fixed, the baseline of that pair fixed to 1
  (monocular scale is arbitrary: compare with a Sim(3) alignment);
- later keyframes: PnP RANSAC on the current landmarks for the initial guess
  (constant velocity when PnP fails), projection factors as in the VIO;
- a very weak zero-motion factor between consecutive keyframes keeps ISAM2
  solvable through stretches with few landmarks;
- frames between keyframes: poses interpolated (slerp and linear).

The frame S is the first keyframe's body frame (no gravity without an IMU).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np

from postproc.slam.backend import (
    BackendOptions,
    BackendStats,
    KeyframeState,
    VisualInertialBackend,
    gtsam_reason,
)
from postproc.slam.estimator import EstimatorOptions, SlamResult
from postproc.slam.keyframes import KeyframeDecision, KeyframeSelector
from postproc.slam.types import FloatArray, FrameTracks, IntArray
from shared.errors import StageError
from shared.geometry import invert_pose, make_pose, so3_exp
from shared.trajectory import Trajectory

VISUAL_INIT_PARALLAX_DEG = 5.0


class VisualBackend(VisualInertialBackend):
    """Keyframe poses and landmarks only (no velocity, no bias, no IMU factor)."""

    def __init__(self, options: BackendOptions, *, focal_px: float, imu_from_cam: FloatArray):
        # Borrow the machinery; the IMU parameters are built from dummy values and unused.
        from shared.calibration.kalibr import ImuNoise

        # Two views suffice: the next keyframe's PnP needs landmarks right after the start.
        super().__init__(
            dataclasses.replace(options, min_observations=2),
            focal_px=focal_px,
            imu_from_cam=imu_from_cam,
            imu_noise=ImuNoise(
                accelerometer_noise_density=1.0,
                accelerometer_random_walk=1.0,
                gyroscope_noise_density=1.0,
                gyroscope_random_walk=1.0,
                update_rate_hz=1.0,
            ),
        )
        self.stats = BackendStats()

    def start_visual(self, stamp_ns: int, track_ids: IntArray, xy_normalised: FloatArray) -> None:
        """First keyframe: body frame = S, fixed."""
        gtsam = self.gtsam
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(
            gtsam.PriorFactorPose3(
                self._X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)
            )
        )
        values.insert(self._X(0), gtsam.Pose3())
        self._isam.update(graph, values)
        self._stamps_ns.append(int(stamp_ns))
        self._poses.append(np.eye(4))
        self._velocities.append(np.zeros(3))
        self._biases.append(gtsam.imuBias.ConstantBias())
        for tid, xy in zip(track_ids.tolist(), xy_normalised, strict=True):
            self._pending[int(tid)] = [(0, xy.copy())]
        self.stats.keyframes = 1

    def add_visual_keyframe(
        self,
        stamp_ns: int,
        pose_guess: FloatArray,
        track_ids: IntArray,
        xy_normalised: FloatArray,
        *,
        fix_position: bool = False,
    ) -> None:
        """Add a keyframe with an initial pose `T_S_B`; `fix_position` sets the scale gauge."""
        gtsam = self.gtsam
        k = len(self._stamps_ns)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        values.insert(self._X(k), gtsam.Pose3(pose_guess))
        # Weak: only keeps the system solvable when a keyframe sees few landmarks.
        graph.add(
            gtsam.BetweenFactorPose3(
                self._X(k - 1), self._X(k), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
            )
        )
        if fix_position:
            graph.add(
                gtsam.PriorFactorPose3(
                    self._X(k),
                    gtsam.Pose3(pose_guess),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1] * 3 + [1e-3] * 3)),
                )
            )
        self._stamps_ns.append(int(stamp_ns))
        self._poses.append(np.asarray(pose_guess, dtype=np.float64))
        self._velocities.append(np.zeros(3))
        self._biases.append(self._biases[-1])
        self._add_visual_factors(k, track_ids, xy_normalised, graph, values)
        try:
            self._isam.update(graph, values)
            for i in range(max(0, k - 29), k + 1):
                self._poses[i] = self._isam.calculateEstimatePose3(self._X(i)).matrix()
        except RuntimeError as error:
            raise StageError(
                f"visual-only backend failed at keyframe {k}: {gtsam_reason(error)}"
            ) from error
        self.stats.keyframes = k + 1

    def finish(self) -> None:
        self._estimate = self._isam.calculateEstimate()
        for k in range(self.num_keyframes):
            self._poses[k] = self._estimate.atPose3(self._X(k)).matrix()

    def keyframe_states(self) -> list[KeyframeState]:
        return [
            KeyframeState(s, p.copy(), np.zeros(3), np.zeros(3), np.zeros(3))
            for s, p in zip(self._stamps_ns, self._poses, strict=True)
        ]


def _pnp(points: FloatArray, xy: FloatArray, focal_px: float) -> tuple[FloatArray, int] | None:
    """`T_C_S` of a camera seeing `points` (N, 3) at `xy` (N, 2) normalised; None if it fails."""
    if len(points) < 12:
        return None
    cv2.setRNGSeed(0)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        points,
        xy,
        np.eye(3),
        None,
        reprojectionError=2.0 / focal_px,
        iterationsCount=200,
        confidence=0.999,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inliers is None or len(inliers) < 12:
        return None
    inl = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(points[inl], xy[inl], np.eye(3), None, rvec, tvec)
    return make_pose(so3_exp(rvec.ravel()), tvec.ravel()), len(inl)


class VisualOnlyEstimator:
    """Same interface as SlamEstimator (`process`, `finish`) without the IMU."""

    def __init__(self, options: EstimatorOptions, *, focal_px: float, imu_from_cam: FloatArray):
        self.options = options
        self.focal_px = focal_px
        self.imu_from_cam = np.asarray(imu_from_cam, dtype=np.float64)
        self.selector = KeyframeSelector(options.keyframes)
        self.backend = VisualBackend(options.backend, focal_px=focal_px, imu_from_cam=imu_from_cam)
        self._buffer: list[FrameTracks] = []
        self._frame_stamps: list[int] = []
        self._keyframe_stamps: list[int] = []

    def process(self, frame: FrameTracks, describe: Any = None) -> KeyframeDecision:
        """Take one frame (`describe` is ignored: no loop closure in the baseline)."""
        del describe
        if self._frame_stamps and frame.stamp_ns <= self._frame_stamps[-1]:
            raise StageError(f"frame at {frame.stamp_ns} ns is not after the previous one")
        decision = self.selector.decide(frame)
        self._frame_stamps.append(frame.stamp_ns)
        if not decision.is_keyframe:
            return decision
        if self.backend.num_keyframes == 0:
            self._buffer.append(frame)
            self._try_start()
        else:
            self.backend.add_visual_keyframe(
                frame.stamp_ns, self._guess(frame), frame.track_ids, frame.xy_normalised
            )
            self._keyframe_stamps.append(frame.stamp_ns)
        return decision

    def _guess(self, frame: FrameTracks) -> FloatArray:
        points, xy = [], []
        for tid, p in zip(frame.track_ids.tolist(), frame.xy_normalised, strict=True):
            point = self.backend.landmark_position(int(tid))
            if point is not None:
                points.append(point)
                xy.append(p)
        pnp = _pnp(
            np.asarray(points, float).reshape(-1, 3),
            np.asarray(xy, float).reshape(-1, 2),
            self.focal_px,
        )
        if pnp is not None:
            return invert_pose(pnp[0]) @ invert_pose(self.imu_from_cam)
        poses = self.backend.cached_poses()
        if len(poses) < 2:
            return poses[-1]
        step = invert_pose(poses[-2]) @ poses[-1]  # constant velocity
        return poses[-1] @ step

    def _try_start(self) -> None:
        first, last = self._buffer[0], self._buffer[-1]
        _, ia, ib = np.intersect1d(first.track_ids, last.track_ids, return_indices=True)
        if len(ia) < 30:
            if len(ia) < 15 and len(self._buffer) > 2:
                self._buffer = self._buffer[-1:]  # lost the first view: start over from here
            return
        a, b = first.xy_normalised[ia], last.xy_normalised[ib]
        E, mask = cv2.findEssentialMat(
            a, b, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1.0 / self.focal_px
        )
        if E is None or E.shape != (3, 3):
            return
        ransac_inliers = int((mask.ravel() > 0).sum())
        _, R, t, mask = cv2.recoverPose(E, a, b, np.eye(3), mask=mask)
        inl = mask.ravel() > 0
        rays_a = np.column_stack([a, np.ones(len(a))])
        rays_b = np.column_stack([b, np.ones(len(b))]) @ R  # rotated back into camera a
        cos = np.einsum("ij,ij->i", rays_a, rays_b) / (
            np.linalg.norm(rays_a, axis=1) * np.linalg.norm(rays_b, axis=1)
        )
        parallax = np.degrees(np.median(np.arccos(np.clip(cos[inl], -1, 1)))) if inl.any() else 0
        # Mostly planar scenes (a hull side) make the essential matrix ambiguous at small
        # baselines: ask for more parallax than the VIO does, and for nearly all RANSAC
        # inliers in front of both cameras.
        if (
            inl.sum() < 30
            or inl.sum() < 0.9 * ransac_inliers
            or parallax < VISUAL_INIT_PARALLAX_DEG
        ):
            return
        T_B_C = self.imu_from_cam
        cam_last_from_cam_first = make_pose(R, t.ravel())
        # S = first body frame: camera 0 at T_B_C. Keyframes buffered in between are
        # dropped (their frames get interpolated poses): adding them before the pair's
        # scale is fixed would leave the gauge to the weak zero-motion factors.
        last_pose = T_B_C @ invert_pose(cam_last_from_cam_first) @ invert_pose(T_B_C)
        self.backend.start_visual(first.stamp_ns, first.track_ids, first.xy_normalised)
        self.backend.add_visual_keyframe(
            last.stamp_ns, last_pose, last.track_ids, last.xy_normalised, fix_position=True
        )
        self._keyframe_stamps = [first.stamp_ns, last.stamp_ns]
        self._buffer = []

    def finish(self) -> SlamResult:
        backend = self.backend
        if backend.num_keyframes < 2:
            raise StageError(
                f"visual-only: only {backend.num_keyframes} keyframe(s) (no two views with "
                "enough parallax to start)"
            )
        backend.finish()
        kf_poses = np.array([s.session_from_body for s in backend.keyframe_states()])
        kf_stamps = np.array(self._keyframe_stamps, dtype=np.int64)
        frames = np.array(self._frame_stamps, dtype=np.int64)
        inside = frames[(frames >= kf_stamps[0]) & (frames <= kf_stamps[-1])]
        trajectory = Trajectory(kf_stamps, kf_poses).interpolate(inside)
        ids, points = backend.landmarks()
        return SlamResult(
            frame_stamps_ns=trajectory.stamps_ns,
            session_from_body=trajectory.poses,
            keyframe_stamps_ns=kf_stamps,
            keyframe_session_from_body=kf_poses,
            keyframe_session_from_cam=kf_poses @ self.imu_from_cam,
            landmark_ids=ids,
            landmarks_s=points,
            stats={
                "frames": len(trajectory),
                "keyframes": backend.num_keyframes,
                "landmarks": len(ids),
                "projection_factors": backend.stats.projection_factors,
                "loop_closures": 0,
                "init": "two-view (visual only, arbitrary scale, S not gravity-aligned)",
            },
        )
