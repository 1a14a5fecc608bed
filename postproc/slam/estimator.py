"""Frame-by-frame visual-inertial estimation: keyframe rule, start-up, backend, frame poses.

Pure computation (no files): feed `FrameTracks` in time order to
`SlamEstimator.process`, then call `finish` for the keyframe poses, the
frame-rate body trajectory and the landmarks, all in the session frame S.

Clocks: frame stamps are on the camera clock; the IMU and the backend run on
the IMU clock, t_imu = t_cam + timeshift_cam_imu_s (Kalibr). Results carry the
camera-clock stamps of the images they belong to.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from postproc.slam.backend import BackendOptions, KeyframeState, VisualInertialBackend
from postproc.slam.initialization import (
    AlignmentResult,
    align_visual_inertial,
    is_still,
    mean_specific_force,
    preintegrate,
    session_from_body_rotation,
    translation_direction,
)
from postproc.slam.keyframes import KeyframeDecision, KeyframeOptions, KeyframeSelector
from postproc.slam.loop_closure import Descriptors, LoopClosureOptions, LoopDetector
from postproc.slam.types import FloatArray, FrameTracks, ImuSamples, IntArray
from shared.calibration.kalibr import ImuNoise
from shared.errors import StageError
from shared.geometry import make_pose, so3_exp, so3_log


@dataclass(kw_only=True)
class EstimatorOptions:
    """How frames become keyframes and states.

    keyframes / backend / loop_closure: see KeyframeOptions, BackendOptions,
        LoopClosureOptions.
    gravity_window_s: accelerometer averaging window after the first keyframe (s; cut
        to the IMU data), each sample turned into the first keyframe's frame by the gyro.
        Long, because a start is not always at rest: the Karma drone sample accelerates
        at 2-3 m/s^2 for its first 5 s, which tilts a 1 s mean by 11-16 degrees (and the
        0.03 rad tilt prior then holds that error); over 10 s the tilt left is
        Delta-v / (g T), 4 degrees there, and the smoother takes it out. Simulated
        dives (bench_slam, 30 s): feature-level ATE 0.8 / 2.7 / 9.6 mm with 1 s, 0.8 /
        2.4 / 9.5 mm with 10 s; rendered 3.7 mm vs 4.1 mm (max error 10.2 vs 8.6 mm).
    init_min_keyframes: keyframes buffered before the visual-inertial alignment is tried.
    init_min_parallax_deg: median ray angle to the first keyframe needed to try it.
    init_min_condition: smallest accepted conditioning of the alignment (scale observable).
    init_max_s: after this long without a good alignment, start from rest (v = 0): a
        hovering diver never gives scale, and waiting forever would lose the start.
    still_max_flow_px: median feature motion (frontend pixels) between keyframes, with
        the gyro-predicted rotation removed, below which the camera counts as not
        translating (zero-velocity update).
    timeshift_cam_imu_s: Kalibr's camera-to-IMU time shift (t_imu = t_cam + shift).
    blind_keyframe_interval_s: while frames carry no tracks (open water, the camera
        blocked), at most one keyframe per this many seconds (0: no limit). Blind
        keyframes hold nothing but IMU; at the selector's rate (up to 5 per second,
        "few tracks") their chain of short, stiff IMU factors left the smoother's
        system so ill-conditioned (position drift ~12 m against 1e10 bias-walk
        information) that ISAM2's Cholesky failed after about 20 s blind (issue #7).
        One long IMU factor per interval carries the same information, well scaled.
    """

    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    backend: BackendOptions = field(default_factory=BackendOptions)
    loop_closure: LoopClosureOptions = field(default_factory=LoopClosureOptions)
    gravity_window_s: float = 10.0
    still_max_flow_px: float = 1.5
    timeshift_cam_imu_s: float = 0.0
    init_min_keyframes: int = 4
    init_min_parallax_deg: float = 2.0
    init_min_condition: float = 1e-3
    init_max_s: float = 5.0
    blind_keyframe_interval_s: float = 5.0


@dataclass
class _BufferedKeyframe:
    imu_ns: int
    track_ids: IntArray
    xy_normalised: FloatArray
    still: bool


@dataclass
class SlamResult:
    """What the estimator produced (session frame S, camera-clock stamps).

    frame_stamps_ns / session_from_body: body poses T_S_B at every processed frame.
    keyframe_stamps_ns / keyframe_session_from_cam: camera poses T_S_C of keyframes.
    landmark_ids / landmarks_s: sparse map (track ids, (L, 3) metres in S).
    """

    frame_stamps_ns: IntArray
    session_from_body: FloatArray
    keyframe_stamps_ns: IntArray
    keyframe_session_from_body: FloatArray
    keyframe_session_from_cam: FloatArray
    landmark_ids: IntArray
    landmarks_s: FloatArray
    stats: dict[str, float | int | str | dict[str, int]]


class SlamEstimator:
    """Keyframe visual-inertial SLAM on already tracked features."""

    def __init__(
        self,
        options: EstimatorOptions,
        *,
        focal_px: float,
        imu_from_cam: FloatArray,
        imu: ImuSamples,
        imu_noise: ImuNoise,
    ) -> None:
        if len(imu) < 2:
            raise StageError("visual-inertial SLAM needs IMU samples (got fewer than 2)")
        self.options = options
        self.imu = imu
        self.imu_from_cam = np.asarray(imu_from_cam, dtype=np.float64)
        self.selector = KeyframeSelector(options.keyframes)
        self.backend = VisualInertialBackend(
            options.backend, focal_px=focal_px, imu_from_cam=imu_from_cam, imu_noise=imu_noise
        )
        self._shift_ns = round(options.timeshift_cam_imu_s * 1e9)
        self._frame_stamps: list[int] = []
        self._keyframe_frame_index: list[int] = []
        self._last_kf_xy: dict[int, FloatArray] = {}
        self._reasons: dict[str, int] = {}
        self._imu_end_ns = int(imu.stamps_ns[-1])
        self._buffer: list[_BufferedKeyframe] = []
        self.loops = LoopDetector(
            options.loop_closure, focal_px=focal_px, imu_from_cam=self.imu_from_cam
        )
        self.loop_closures: list[tuple[int, int, int]] = []  # (old, new, inliers)
        self._rng = np.random.default_rng(0)
        self.init_report: dict[str, float | int | str] = {}
        self._imu_start_ns = int(imu.stamps_ns[0])
        self._last_kf_blind = False
        self._last_kf_imu_ns = 0
        self._blind_skipped = 0  # keyframes the selector asked for while blind, not made

    def process(
        self,
        frame: FrameTracks,
        describe: Callable[[], tuple[IntArray, Descriptors]] | None = None,
    ) -> KeyframeDecision:
        """Take one frame; returns the keyframe decision (keyframes update the backend).

        `describe`, called only for keyframes, returns (rows of `frame` kept,
        their binary descriptors) for loop closure; None disables it for the
        frame. Frames outside the IMU's time span are skipped (decision "no IMU").
        """
        imu_ns = frame.stamp_ns + self._shift_ns
        if imu_ns < self._imu_start_ns or imu_ns > self._imu_end_ns:
            return KeyframeDecision(False, 0.0, 0.0, "no IMU")
        if self._frame_stamps and frame.stamp_ns <= self._frame_stamps[-1]:
            raise StageError(
                f"frame at {frame.stamp_ns} ns is not after the previous "
                f"{self._frame_stamps[-1]} ns"
            )
        decision = self.selector.decide(frame)
        self._frame_stamps.append(frame.stamp_ns)
        if not decision.is_keyframe:
            return decision
        blind = len(frame.track_ids) == 0
        if blind and self._last_kf_blind and self.backend.num_keyframes:
            since_s = (imu_ns - self._last_kf_imu_ns) * 1e-9
            if since_s < self.options.blind_keyframe_interval_s:
                self._blind_skipped += 1
                return KeyframeDecision(False, decision.overlap, decision.match_ratio, "blind")
        self._last_kf_blind = blind
        self._last_kf_imu_ns = imu_ns
        self._reasons[decision.reason] = self._reasons.get(decision.reason, 0) + 1
        still = bool(self._keyframe_frame_index) and self._still_since_last_keyframe(frame, imu_ns)
        keyframe = _BufferedKeyframe(imu_ns, frame.track_ids, frame.xy_normalised, still)
        if self.backend.num_keyframes == 0:
            self._buffer.append(keyframe)
            self._try_start()
        else:
            self.backend.add_keyframe(
                imu_ns, self.imu, frame.track_ids, frame.xy_normalised, still=still
            )
        self._keyframe_frame_index.append(len(self._frame_stamps) - 1)
        if describe is not None and self.options.loop_closure.enabled:
            rows, descriptors = describe()
            index = len(self._keyframe_frame_index) - 1
            self.loops.add_keyframe(
                index, frame.stamp_ns, frame.track_ids[rows], frame.xy_normalised[rows], descriptors
            )
            if index < self.backend.num_keyframes:
                self._close_loops(index)
        self._last_kf_xy = dict(zip(frame.track_ids.tolist(), frame.xy_normalised, strict=True))
        return decision

    def _close_loops(self, index: int) -> None:
        """Verify loop candidates for keyframe `index`; add the first verified one."""
        backend = self.backend
        o = self.options.loop_closure
        if self.loop_closures and index - self.loop_closures[-1][1] < o.min_keyframes_between_loops:
            return
        poses = backend.cached_poses()  # gating only needs metres, not millimetres
        for old in self.loops.candidates(index, poses):
            loop = self.loops.verify(
                old,
                index,
                old_session_from_body=backend.session_from_body(old),
                landmark=backend.landmark_position,
            )
            if loop is None:
                continue
            backend.add_loop(
                old,
                index,
                loop.old_from_new,
                rotation_sigma_rad=o.rotation_sigma_rad,
                translation_sigma_m=o.translation_sigma_m,
                cauchy_k=o.cauchy_k,
            )
            self.loop_closures.append((old, index, loop.inliers))
            return

    def _try_start(self, *, force: bool = False) -> None:
        """Align the buffered keyframes with the IMU; start the backend when it succeeds."""
        o = self.options
        first = self._buffer[0]
        accel = mean_specific_force(self.imu, first.imu_ns, o.gravity_window_s)
        R_S_B0 = session_from_body_rotation(accel)
        span_s = (self._buffer[-1].imu_ns - first.imu_ns) * 1e-9
        alignment = None
        if len(self._buffer) >= o.init_min_keyframes and not all(k.still for k in self._buffer[1:]):
            alignment = self._align(R_S_B0)
        accepted = alignment is not None and alignment.condition >= o.init_min_condition
        if not accepted and not force and span_s < o.init_max_s:
            return
        velocity = alignment.velocity_m_s if accepted and alignment else np.zeros(3)
        bias = alignment.accel_bias_m_s2 if accepted and alignment else np.zeros(3)
        self.init_report = {
            "init": "visual-inertial alignment" if accepted else "from rest",
            "init_keyframes": len(self._buffer),
            "init_span_s": span_s,
            "init_condition": alignment.condition if alignment else 0.0,
            "init_speed_m_s": float(np.linalg.norm(velocity)),
        }
        self.backend.start(
            first.imu_ns,
            R_S_B0,
            first.track_ids,
            first.xy_normalised,
            velocity_m_s=velocity,
            accel_bias_m_s2=bias,
        )
        for kf in self._buffer[1:]:
            self.backend.add_keyframe(
                kf.imu_ns, self.imu, kf.track_ids, kf.xy_normalised, still=kf.still
            )
        self._buffer = []

    def _align(self, R_S_B0: FloatArray) -> AlignmentResult | None:
        """Linear alignment of the buffered keyframes (None without enough parallax)."""
        first = self._buffer[0]
        later = self._buffer[1:]
        pre = preintegrate(self.imu, first.imu_ns, [k.imu_ns for k in later], np.zeros(3))
        R_B_C = self.imu_from_cam[:3, :3]
        first_index = {t: i for i, t in enumerate(first.track_ids.tolist())}
        directions = []
        parallax = 0.0
        for kf, p in zip(later, pre, strict=True):
            pairs = [
                (first_index[t], j) for j, t in enumerate(kf.track_ids.tolist()) if t in first_index
            ]
            if len(pairs) < 15:
                return None
            ia, ib = np.array(pairs).T
            rays_a = (
                np.column_stack([first.xy_normalised[ia], np.ones(len(ia))]) @ (R_S_B0 @ R_B_C).T
            )
            R_S_Bk = R_S_B0 @ p.delta_rotation
            rays_b = np.column_stack([kf.xy_normalised[ib], np.ones(len(ib))]) @ (R_S_Bk @ R_B_C).T
            d, inliers = translation_direction(rays_a, rays_b, rng=self._rng)
            if inliers < 15 or not np.all(np.isfinite(d)):
                return None
            directions.append(d)
            cos = np.einsum("ij,ij->i", rays_a, rays_b) / (
                np.linalg.norm(rays_a, axis=1) * np.linalg.norm(rays_b, axis=1)
            )
            parallax = float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))
        if parallax < self.options.init_min_parallax_deg:
            return None
        result = align_visual_inertial(
            session_from_body0=make_pose(R_S_B0, np.zeros(3)),
            imu_from_cam=self.imu_from_cam,
            directions_s=directions,
            preintegrated=pre,
            gravity_m_s2=self.options.backend.gravity_m_s2,
        )
        if np.any(result.scales_m <= 0):
            return None
        return result

    def _still_since_last_keyframe(self, frame: FrameTracks, imu_ns: int) -> bool:
        """Zero-velocity test: median feature motion since the last keyframe, rotation removed."""
        common = [
            (self._last_kf_xy[t], xy)
            for t, xy in zip(frame.track_ids.tolist(), frame.xy_normalised, strict=True)
            if t in self._last_kf_xy
        ]
        if len(common) < 10:
            return False
        prev_imu_ns = self._frame_stamps[self._keyframe_frame_index[-1]] + self._shift_ns
        if self.backend.num_keyframes:
            R_prev_now = self.backend.predicted_rotation(self.imu, imu_ns)
        else:
            R_prev_now = preintegrate(self.imu, prev_imu_ns, [imu_ns], np.zeros(3))[
                0
            ].delta_rotation
        R_B_C = self.imu_from_cam[:3, :3]
        # Rays of the last keyframe seen from the current camera orientation.
        R_now_prev_cam = R_B_C.T @ R_prev_now.T @ R_B_C
        old = np.array([c[0] for c in common])
        new = np.array([c[1] for c in common])
        rays = np.column_stack([old, np.ones(len(old))]) @ R_now_prev_cam.T
        rotated = rays[:, :2] / rays[:, 2:3]
        flow_px = self.backend.focal_px * np.linalg.norm(rotated - new, axis=1)
        return is_still(
            derotated_flow_px=float(np.median(flow_px)),
            max_flow_px=self.options.still_max_flow_px,
        )

    def finish(self) -> SlamResult:
        """Final optimisation; keyframe and frame-rate poses in S, landmarks."""
        backend = self.backend
        if self._buffer:
            self._try_start(force=True)
        if backend.num_keyframes < 2:
            raise StageError(
                f"only {backend.num_keyframes} keyframe(s): the sequence is too short or no "
                "frame overlaps the IMU data"
            )
        backend.finish()
        states = backend.keyframe_states()
        kf_stamps_cam = np.array(
            [self._frame_stamps[i] for i in self._keyframe_frame_index], dtype=np.int64
        )
        kf_poses = np.array([s.session_from_body for s in states])
        frame_poses = self._frame_poses(states)
        ids, points = backend.landmarks()
        stats: dict[str, float | int | str | dict[str, int]] = {
            "frames": len(self._frame_stamps),
            "keyframes": backend.num_keyframes,
            "landmarks": len(ids),
            "projection_factors": backend.stats.projection_factors,
            "still_keyframes": backend.stats.still_keyframes,
            "rejected_triangulations": backend.stats.rejected_triangulations,
            "gated_observations": backend.stats.gated_observations,
            "loop_closures": backend.stats.loop_closures,
            "pose_graph_loops": backend.stats.pose_graph_loops,
            "retired_keyframes": backend.stats.retired_keyframes,
            "frozen_landmarks": backend.stats.frozen_landmarks,
            "window_rebuilds": backend.stats.window_rebuilds,
            "blind_keyframes": backend.stats.blind_keyframes,
            "recovered_updates": backend.stats.recovered_updates,
            "blind_keyframes_skipped": self._blind_skipped,
            "loop_attempts": self.loops.attempts,
            "keyframe_reasons": dict(self._reasons),
            **self.init_report,
            "final_accel_bias_m_s2": float(np.linalg.norm(states[-1].accel_bias_m_s2)),
            "final_gyro_bias_rad_s": float(np.linalg.norm(states[-1].gyro_bias_rad_s)),
        }
        return SlamResult(
            frame_stamps_ns=np.array(self._frame_stamps, dtype=np.int64),
            session_from_body=frame_poses,
            keyframe_stamps_ns=kf_stamps_cam,
            keyframe_session_from_body=kf_poses,
            keyframe_session_from_cam=kf_poses @ self.imu_from_cam,
            landmark_ids=ids,
            landmarks_s=points,
            stats=stats,
        )

    def _frame_poses(self, states: list[KeyframeState]) -> FloatArray:
        """T_S_B at every frame: IMU prediction from the previous keyframe, its end error
        spread linearly over the interval so the trajectory passes through every keyframe."""
        import gtsam

        backend = self.backend
        poses = np.zeros((len(self._frame_stamps), 4, 4))
        kf_idx = self._keyframe_frame_index
        for j, start in enumerate(kf_idx):
            end = kf_idx[j + 1] if j + 1 < len(kf_idx) else len(self._frame_stamps) - 1
            state = states[j]
            nav = gtsam.NavState(gtsam.Pose3(state.session_from_body), state.velocity_m_s)
            bias = backend.bias_of(j)
            t0 = self._frame_stamps[start] + self._shift_ns
            predicted = []
            for f in range(start, end + 1):
                t = self._frame_stamps[f] + self._shift_ns
                pim = backend.preintegrate(self.imu, t0, t, bias)
                predicted.append(pim.predict(nav, bias).pose().matrix())
            if j + 1 < len(kf_idx):
                target = states[j + 1].session_from_body
                end_pred = predicted[-1]
                d_rot = so3_log(end_pred[:3, :3].T @ target[:3, :3])
                d_pos = target[:3, 3] - end_pred[:3, 3]
                t_end = self._frame_stamps[end] - self._frame_stamps[start]
                for n, f in enumerate(range(start, end + 1)):
                    alpha = (self._frame_stamps[f] - self._frame_stamps[start]) / t_end
                    P = predicted[n]
                    poses[f] = make_pose(
                        P[:3, :3] @ so3_exp(alpha * d_rot), P[:3, 3] + alpha * d_pos
                    )
            else:
                for n, f in enumerate(range(start, end + 1)):
                    poses[f] = predicted[n]
        return poses
