"""Frame-by-frame visual-inertial estimation: keyframe rule, start-up, backend, frame poses.

Pure computation (no files): feed `FrameTracks` in time order to
`SlamEstimator.process`, then call `finish` for the keyframe poses, the
frame-rate body trajectory and the landmarks, all in the session frame S.

Clocks: frame stamps are on the camera clock; the IMU and the backend run on
the IMU clock, t_imu = t_cam + timeshift_cam_imu_s (Kalibr). Results carry the
camera-clock stamps of the images they belong to.

Start-up never stops the run: at rest (the IMU still around the first keyframe
and the images agreeing) the backend starts at once from the still IMU; a rest
that ended shortly before the first image is carried to it by the IMU; in
motion the buffered keyframes wait for the visual-inertial alignment (or, after
`init_max_s`, start from rest with a loose velocity prior). A start that fails
(no gravity in the accelerometer, a smoother that cannot take it) drops that
keyframe and is retried at the next. Should the smoother fail for good later
on, the keyframes so far become a finished map segment and a new segment starts
at the failing keyframe from the IMU prediction of the last state, so the
trajectory stays whole (`stats["map_segments"]`); a loop from a later segment
to a keyframe of an earlier one joins them in a final pose graph
(`stats["segment_loops"]`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from postproc.slam.backend import KeyframeState, VisualInertialBackend
from postproc.slam.initialization import (
    AlignmentResult,
    ImuStillness,
    align_visual_inertial,
    imu_stillness,
    is_still,
    mean_specific_force,
    preintegrate,
    session_from_body_rotation,
    translation_direction,
)
from postproc.slam.keyframes import KeyframeDecision, KeyframeSelector
from postproc.slam.loop_closure import Descriptors, LoopDetector
from postproc.slam.options import EstimatorOptions as EstimatorOptions
from postproc.slam.types import FloatArray, FrameTracks, ImuSamples, IntArray
from shared.calibration.kalibr import ImuNoise
from shared.clock import ns_from_seconds, seconds_from_ns
from shared.errors import StageError
from shared.geometry import invert_pose, make_pose, so3_exp, so3_log

LOG = logging.getLogger(__name__)

# What one entry of the estimator's stats (stats.json) holds.
StatValue = float | int | str | bool | list[float | None] | dict[str, int] | None


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
    stats: dict[str, StatValue]


@dataclass
class _Segment:
    """A map segment whose smoother failed for good: its keyframe states and landmarks."""

    first_keyframe: int  # global keyframe index of its keyframe 0
    states: list[KeyframeState]
    landmark_ids: IntArray
    landmarks_s: FloatArray
    counters: dict[str, int]
    _lookup: dict[int, FloatArray] | None = None

    def landmark(self, track_id: int) -> FloatArray | None:
        """Position in S (3,) of the segment's landmark of `track_id`, None if none."""
        if self._lookup is None:
            self._lookup = dict(zip(self.landmark_ids.tolist(), self.landmarks_s, strict=True))
        return self._lookup.get(int(track_id))


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
        self._focal_px = float(focal_px)
        self._imu_noise = imu_noise
        self.backend = self._new_backend()
        self._segments: list[_Segment] = []
        self._segment_start = 0  # global keyframe index of the backend's keyframe 0
        self._segment_failures: list[str] = []
        # Loops from a keyframe to one of a finished segment: (old, new, T_Bold_Bnew).
        self._segment_loops: list[tuple[int, int, FloatArray]] = []
        self._init_failures: list[str] = []
        self._shift_ns = ns_from_seconds(options.timeshift_cam_imu_s)
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

    def _new_backend(self) -> VisualInertialBackend:
        return VisualInertialBackend(
            self.options.backend,
            focal_px=self._focal_px,
            imu_from_cam=self.imu_from_cam,
            imu_noise=self._imu_noise,
        )

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
            since_s = seconds_from_ns(imu_ns - self._last_kf_imu_ns)
            if since_s < self.options.blind_keyframe_interval_s:
                self._blind_skipped += 1
                return KeyframeDecision(False, decision.overlap, decision.match_ratio, "blind")
        self._last_kf_blind = blind
        self._last_kf_imu_ns = imu_ns
        self._reasons[decision.reason] = self._reasons.get(decision.reason, 0) + 1
        still = bool(self._keyframe_frame_index) and self._still_since_last_keyframe(frame, imu_ns)
        keyframe = _BufferedKeyframe(imu_ns, frame.track_ids, frame.xy_normalised, still)
        self._keyframe_frame_index.append(len(self._frame_stamps) - 1)
        if self.backend.num_keyframes == 0:
            self._buffer.append(keyframe)
            self._try_start()
        else:
            self._add_to_backend(keyframe)
        if describe is not None and self.options.loop_closure.enabled:
            rows, descriptors = describe()
            index = len(self._keyframe_frame_index) - 1
            self.loops.add_keyframe(
                index, frame.stamp_ns, frame.track_ids[rows], frame.xy_normalised[rows], descriptors
            )
            if (
                self.backend.num_keyframes
                and index < self._segment_start + self.backend.num_keyframes
            ):
                self._close_loops(index)
        self._last_kf_xy = dict(zip(frame.track_ids.tolist(), frame.xy_normalised, strict=True))
        return decision

    def _add_to_backend(self, keyframe: _BufferedKeyframe) -> None:
        """Add a keyframe to the running smoother; a new map segment if it fails for good."""
        try:
            self.backend.add_keyframe(
                keyframe.imu_ns,
                self.imu,
                keyframe.track_ids,
                keyframe.xy_normalised,
                still=keyframe.still,
            )
        except StageError as error:
            self._start_new_segment(keyframe, error)

    def _start_new_segment(self, keyframe: _BufferedKeyframe, error: StageError) -> None:
        """Close the failed smoother's segment and start a new one at `keyframe`.

        The new segment starts from the IMU prediction of the last good state (its pose
        pinned there, so the trajectory stays continuous in S; tilt, velocity and biases
        under their usual priors), then tracks and triangulates afresh.
        """
        import gtsam

        old = self.backend
        states = old.abandon()
        ids, points = old.landmarks()
        self._segments.append(
            _Segment(
                first_keyframe=self._segment_start,
                states=states,
                landmark_ids=ids,
                landmarks_s=points,
                counters=_backend_counters(old),
            )
        )
        when_s = seconds_from_ns(keyframe.imu_ns - self._imu_start_ns)
        self._segment_failures.append(f"{when_s:.2f} s: {error}")
        LOG.warning(
            "smoother failed %.2f s into the IMU data (%s); starting map segment %d there",
            when_s,
            error,
            len(self._segments) + 1,
        )
        last = states[-1]
        bias = gtsam.imuBias.ConstantBias(last.accel_bias_m_s2, last.gyro_bias_rad_s)
        pim = old.preintegrate(self.imu, last.stamp_ns, keyframe.imu_ns, bias)
        nav = pim.predict(
            gtsam.NavState(gtsam.Pose3(last.session_from_body), last.velocity_m_s), bias
        )
        pose = nav.pose().matrix()
        self._segment_start = self._segment_start + len(states)
        self.backend = self._new_backend()
        self.backend.start(
            keyframe.imu_ns,
            pose[:3, :3],
            keyframe.track_ids,
            keyframe.xy_normalised,
            velocity_m_s=np.asarray(nav.velocity()),
            accel_bias_m_s2=last.accel_bias_m_s2,
            gyro_bias_rad_s=last.gyro_bias_rad_s,
            position_m=pose[:3, 3],
        )

    def _close_loops(self, index: int) -> None:
        """Verify loop candidates for keyframe `index` (global); add the first verified one.

        A loop within the running map segment enters the smoother; one to a keyframe
        of a finished segment is kept for the final pose graph (`_join_segments`).
        """
        backend = self.backend
        start = self._segment_start
        o = self.options.loop_closure
        if self.loop_closures and index - self.loop_closures[-1][1] < o.min_keyframes_between_loops:
            return
        # Gating only needs metres, not millimetres.
        poses = [s.session_from_body for seg in self._segments for s in seg.states]
        poses += backend.cached_poses()
        for old in self.loops.candidates(index, poses):
            if old < start:
                # A keyframe of a finished segment: the loop joins the two segments in
                # the final pose graph (`finish`).
                segment = self._segment_of(old)
                loop = self.loops.verify(
                    old,
                    index,
                    old_session_from_body=segment.states[
                        old - segment.first_keyframe
                    ].session_from_body,
                    landmark=segment.landmark,
                )
                if loop is None:
                    continue
                self._segment_loops.append((old, index, loop.old_from_new))
                self.loop_closures.append((old, index, loop.inliers))
                return
            loop = self.loops.verify(
                old,
                index,
                old_session_from_body=backend.session_from_body(old - start),
                landmark=backend.landmark_position,
            )
            if loop is None:
                continue
            backend.add_loop(
                old - start,
                index - start,
                loop.old_from_new,
                rotation_sigma_rad=o.rotation_sigma_rad,
                translation_sigma_m=o.translation_sigma_m,
                cauchy_k=o.cauchy_k,
            )
            self.loop_closures.append((old, index, loop.inliers))
            return

    def _segment_of(self, keyframe: int) -> _Segment:
        """The finished segment holding global keyframe `keyframe`."""
        for segment in self._segments:
            if segment.first_keyframe <= keyframe < segment.first_keyframe + len(segment.states):
                return segment
        raise IndexError(f"keyframe {keyframe} is in no finished segment")

    def _try_start(self, *, force: bool = False) -> None:
        """Start the backend at the first buffered keyframe once the start is known.

        At rest (the IMU around it is still): at once, gravity and gyro bias from the
        still IMU, zero velocity. In motion: when the visual-inertial alignment of the
        buffered keyframes succeeds, or, after `init_max_s` (or `force`), from rest with
        a loose velocity prior. A start that fails (no gravity in the IMU, a
        smoother that cannot take it) drops that keyframe and is retried at the next.
        """
        try:
            started = self._start_from_buffer(force=force)
        except (StageError, RuntimeError) as error:  # gtsam raises RuntimeError
            dropped = self._buffer.pop(0)
            when_s = seconds_from_ns(dropped.imu_ns - self._imu_start_ns)
            self._init_failures.append(f"{when_s:.2f} s: {error}")
            LOG.warning(
                "initialisation %.2f s into the IMU data failed (%s); retrying at the "
                "next keyframe",
                when_s,
                error,
            )
            self._keyframe_frame_index.pop(len(self._keyframe_frame_index) - 1 - len(self._buffer))
            self.backend = self._new_backend()
            # Keyframe indices shifted: the loop detector starts afresh.
            self.loops = LoopDetector(
                self.options.loop_closure, focal_px=self._focal_px, imu_from_cam=self.imu_from_cam
            )
            if self._buffer and force:
                self._try_start(force=True)
            return
        if started:
            buffered, self._buffer = self._buffer[1:], []
            for kf in buffered:
                self._add_to_backend(kf)

    def _start_from_buffer(self, *, force: bool) -> bool:
        """Start the backend at the first buffered keyframe if the start is known."""
        o = self.options
        first = self._buffer[0]
        span_s = seconds_from_ns(self._buffer[-1].imu_ns - first.imu_ns)
        found = self._last_rest(first.imu_ns)
        if found is not None and found[1] >= first.imu_ns:
            # The IMU cannot tell rest from a smooth glide at constant velocity: the
            # images must agree (the next keyframe's derotated flow is below
            # `still_max_flow_px`) before the start is taken as at rest.
            if len(self._buffer) < 2:
                return False
            if not self._buffer[1].still:
                found = None
        if found is not None:
            rest, rest_end_ns = found
            self._check_gravity(rest.accel_mean_m_s2)
            # At rest the accelerometer reads gravity plus its bias: the bias along
            # gravity is the norm's excess (a RealSense reads 10.1 m/s^2).
            up_body = rest.accel_mean_m_s2 / np.linalg.norm(rest.accel_mean_m_s2)
            accel_bias = (
                float(np.linalg.norm(rest.accel_mean_m_s2)) - o.backend.gravity_m_s2
            ) * up_body
            R_S_B0, velocity, sigma_v = self._propagate_rest(
                rest, rest_end_ns, first.imu_ns, accel_bias
            )
            before_s = seconds_from_ns(max(first.imu_ns - rest_end_ns, 0))
            self.init_report = {
                "init": "at rest (still IMU)"
                if before_s == 0
                else "at rest (still IMU), propagated to the first keyframe",
                "init_keyframes": len(self._buffer),
                "init_span_s": span_s,
                "init_rest_s": rest.duration_s,
                "init_rest_before_first_keyframe_s": before_s,
                "init_gyro_bias_rad_s": float(np.linalg.norm(rest.gyro_mean_rad_s)),
                "init_accel_bias_along_gravity_m_s2": float(np.linalg.norm(accel_bias)),
                # The noise model beside what the still IMU shows (an upper bound): a
                # density far above it leaves the scale to the images alone.
                "imu_accel_noise_density_configured": self._imu_noise.accelerometer_noise_density,
                "imu_accel_noise_density_at_rest_at_most": rest.accel_noise_density,
                "imu_gyro_noise_density_configured": self._imu_noise.gyroscope_noise_density,
                "imu_gyro_noise_density_at_rest_at_most": rest.gyro_noise_density,
                "init_speed_m_s": float(np.linalg.norm(velocity)),
            }
            self.backend.start(
                first.imu_ns,
                R_S_B0,
                first.track_ids,
                first.xy_normalised,
                velocity_m_s=velocity,
                accel_bias_m_s2=accel_bias,
                gyro_bias_rad_s=rest.gyro_mean_rad_s,
                velocity_sigma_m_s=sigma_v,
                gyro_bias_sigma_rad_s=rest.gyro_bias_sigma_rad_s,
            )
        else:
            accel = mean_specific_force(self.imu, first.imu_ns, o.gravity_window_s)
            self._check_gravity(accel)
            R_S_B0 = session_from_body_rotation(accel)
            alignment = None
            if len(self._buffer) >= o.init_min_keyframes and not all(
                k.still for k in self._buffer[1:]
            ):
                alignment = self._align(R_S_B0)
            accepted = (
                alignment is not None
                and alignment.condition >= o.init_min_condition
                and float(np.linalg.norm(alignment.accel_bias_m_s2)) <= o.init_max_accel_bias_m_s2
            )
            if not accepted and not force and span_s < o.init_max_s:
                return False
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
        return True

    def _check_gravity(self, accel_m_s2: FloatArray) -> None:
        """StageError unless a mean specific force (m/s^2) can be gravity (see options)."""
        norm = float(np.linalg.norm(accel_m_s2))
        g = self.options.backend.gravity_m_s2
        if not abs(norm - g) <= self.options.gravity_tolerance_m_s2:
            raise StageError(
                f"cannot find gravity: mean specific force {norm:.2f} m/s^2 (expected "
                f"{g:.2f} +- {self.options.gravity_tolerance_m_s2:g})"
            )

    def _last_rest(self, first_ns: int) -> tuple[ImuStillness, int] | None:
        """The latest still IMU window ending within `rest_lookback_s` before `first_ns`
        (or reaching `rest_window_s` past it), with its end (IMU clock); None if none."""
        o = self.options
        w_ns = ns_from_seconds(o.rest_window_s)
        step_ns = 100_000_000
        end_ns = min(first_ns + w_ns, self._imu_end_ns)
        while end_ns >= first_ns - ns_from_seconds(o.rest_lookback_s):
            rest = imu_stillness(
                self.imu,
                end_ns - w_ns,
                end_ns,
                max_gyro_std_rad_s=o.rest_max_gyro_std_rad_s,
                max_accel_std_m_s2=o.rest_max_accel_std_m_s2,
                min_duration_s=0.8 * o.rest_window_s,  # the IMU may start inside the window
            )
            if rest.still:
                return rest, min(end_ns, first_ns) if end_ns >= first_ns else end_ns
            end_ns -= step_ns
        return None

    def _propagate_rest(
        self, rest: ImuStillness, rest_end_ns: int, first_ns: int, accel_bias_m_s2: FloatArray
    ) -> tuple[FloatArray, FloatArray, float]:
        """`R_S_B`, velocity (S) and its sigma at the first keyframe, dead-reckoned from rest.

        At rest the attitude comes from gravity and the velocity is zero; the IMU then
        carries both to the first keyframe (with the gyro bias the rest measured). The
        result is turned about z so the first keyframe keeps S's zero yaw.
        """
        import gtsam

        o = self.options
        R_rest = session_from_body_rotation(rest.accel_mean_m_s2)
        if rest_end_ns >= first_ns:
            return R_rest, np.zeros(3), o.rest_velocity_sigma_m_s
        bias = gtsam.imuBias.ConstantBias(accel_bias_m_s2, rest.gyro_mean_rad_s)
        pim = self.backend.preintegrate(self.imu, rest_end_ns, first_ns, bias)
        nav = pim.predict(
            gtsam.NavState(gtsam.Pose3(make_pose(R_rest, np.zeros(3))), np.zeros(3)), bias
        )
        R = nav.pose().rotation().matrix()
        axis = R[:, 0] if abs(R[2, 0]) <= 0.95 else R[:, 1]
        yaw = float(np.arctan2(axis[1], axis[0]))
        c, s_ = np.cos(-yaw), np.sin(-yaw)
        R_z = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        dt_s = seconds_from_ns(first_ns - rest_end_ns)
        sigma = o.rest_velocity_sigma_m_s + o.rest_velocity_growth_m_s2 * dt_s
        return R_z @ R, R_z @ np.asarray(nav.velocity()), sigma

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
        """Final optimisation; keyframe and frame-rate poses in S, landmarks.

        Raises StageError (saying when and why) when fewer than two keyframes have
        states: nothing to make a trajectory of.
        """
        if self._buffer:
            self._try_start(force=True)
        backend = self.backend
        total = sum(len(seg.states) for seg in self._segments) + backend.num_keyframes
        if total < 2:
            reasons = "; ".join(self._init_failures[-2:] + self._segment_failures[-2:])
            span = ""
            if self._frame_stamps:
                span = (
                    f" over {len(self._frame_stamps)} frames "
                    f"({self._frame_stamps[0]} to {self._frame_stamps[-1]} ns, camera clock)"
                )
            raise StageError(
                f"only {total} keyframe(s){span}: the sequence is too short or no frame "
                "overlaps the IMU data" + (f" (initialisation: {reasons})" if reasons else "")
            )
        if backend.num_keyframes:
            backend.finish()
        states = [s for seg in self._segments for s in seg.states] + backend.keyframe_states()
        if self._segment_loops:
            states = self._join_segments(states)
        kf_index = self._keyframe_frame_index[: len(states)]
        first_frame = kf_index[0]
        kf_stamps_cam = np.array([self._frame_stamps[i] for i in kf_index], dtype=np.int64)
        kf_poses = np.array([s.session_from_body for s in states])
        frame_poses = self._frame_poses(states, kf_index)
        ids_parts = [seg.landmark_ids for seg in self._segments]
        point_parts = [seg.landmarks_s for seg in self._segments]
        if backend.num_keyframes:
            ids_now, points_now = backend.landmarks()
            ids_parts.append(ids_now)
            point_parts.append(points_now)
        ids = np.concatenate(ids_parts).astype(np.int64)
        points = np.concatenate([p.reshape(-1, 3) for p in point_parts])
        counters = _backend_counters(backend)
        for seg in self._segments:
            for key, value in seg.counters.items():
                counters[key] += value
        stats: dict[str, StatValue] = {
            "frames": len(self._frame_stamps) - first_frame,
            "frames_before_start": first_frame,
            "keyframes": len(states),
            "landmarks": len(ids),
            **counters,
            "blind_keyframes_skipped": self._blind_skipped,
            "loop_attempts": self.loops.attempts,
            "keyframe_reasons": dict(self._reasons),
            "map_segments": len(self._segments) + (1 if backend.num_keyframes else 0),
            "segment_loops": len(self._segment_loops),
            "segment_failures": "; ".join(self._segment_failures),
            "init_failures": "; ".join(self._init_failures),
            **self.init_report,
            "final_accel_bias_m_s2": float(np.linalg.norm(states[-1].accel_bias_m_s2)),
            "final_gyro_bias_rad_s": float(np.linalg.norm(states[-1].gyro_bias_rad_s)),
        }
        return SlamResult(
            frame_stamps_ns=np.array(self._frame_stamps[first_frame:], dtype=np.int64),
            session_from_body=frame_poses[first_frame:],
            keyframe_stamps_ns=kf_stamps_cam,
            keyframe_session_from_body=kf_poses,
            keyframe_session_from_cam=kf_poses @ self.imu_from_cam,
            landmark_ids=ids,
            landmarks_s=points,
            stats=stats,
        )

    def _join_segments(self, states: list[KeyframeState]) -> list[KeyframeState]:
        """Keyframe poses after a pose graph over every segment and the loops between them.

        Consecutive keyframes of one segment keep their relative pose (the backend's
        pose-graph sigmas); the step from one segment to the next, an IMU prediction,
        gets the loose `segment_join_*` sigmas; loops are robust (Cauchy). Velocities
        turn with their keyframes. On failure the poses are kept as they were.
        """
        import gtsam

        o = self.options
        b = o.backend
        lc = o.loop_closure
        X = gtsam.symbol_shorthand.X
        starts = {seg.first_keyframe for seg in self._segments[1:]} | {self._segment_start}
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(
            gtsam.PriorFactorPose3(
                X(0),
                gtsam.Pose3(states[0].session_from_body),
                gtsam.noiseModel.Isotropic.Sigma(6, 1e-6),
            )
        )

        def sigmas(rotation_rad: float, translation_m: float) -> Any:
            return gtsam.noiseModel.Diagonal.Sigmas(
                np.concatenate([np.full(3, rotation_rad), np.full(3, translation_m)])
            )

        within = sigmas(b.pose_graph_rotation_sigma_rad, b.pose_graph_translation_sigma_m)
        across = sigmas(o.segment_join_rotation_sigma_rad, o.segment_join_translation_sigma_m)
        for k, state in enumerate(states):
            values.insert(X(k), gtsam.Pose3(state.session_from_body))
            if k:
                relative = invert_pose(states[k - 1].session_from_body) @ state.session_from_body
                noise = across if k in starts else within
                graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(relative), noise))
        for old, new, old_from_new in self._segment_loops:
            robust = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Cauchy.Create(lc.cauchy_k),
                sigmas(lc.rotation_sigma_rad, lc.translation_sigma_m),
            )
            graph.add(gtsam.BetweenFactorPose3(X(old), X(new), gtsam.Pose3(old_from_new), robust))
        try:
            result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        except RuntimeError as error:
            LOG.warning("joining the map segments failed (%s); keeping them as they are", error)
            return states
        joined = []
        for k, state in enumerate(states):
            pose = result.atPose3(X(k)).matrix()
            turn = pose[:3, :3] @ state.session_from_body[:3, :3].T
            joined.append(
                dataclasses.replace(
                    state, session_from_body=pose, velocity_m_s=turn @ state.velocity_m_s
                )
            )
        return joined

    def _frame_poses(self, states: list[KeyframeState], kf_idx: list[int]) -> FloatArray:
        """T_S_B at every frame: IMU prediction from the previous keyframe, its end error
        spread linearly over the interval so the trajectory passes through every keyframe."""
        import gtsam

        backend = self.backend
        poses = np.zeros((len(self._frame_stamps), 4, 4))
        for j, start in enumerate(kf_idx):
            end = kf_idx[j + 1] if j + 1 < len(kf_idx) else len(self._frame_stamps) - 1
            state = states[j]
            nav = gtsam.NavState(gtsam.Pose3(state.session_from_body), state.velocity_m_s)
            bias = gtsam.imuBias.ConstantBias(state.accel_bias_m_s2, state.gyro_bias_rad_s)
            # One preintegration carried from frame to frame (not one from the keyframe to
            # each frame: that was quadratic in the frames between keyframes).
            t = self._frame_stamps[start] + self._shift_ns
            pim = backend.preintegrate(self.imu, t, t, bias)
            predicted = []
            for f in range(start, end + 1):
                t_next = min(self._frame_stamps[f] + self._shift_ns, self._imu_end_ns)
                backend.integrate(pim, self.imu, t, t_next)
                t = max(t, t_next)
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


def _backend_counters(backend: VisualInertialBackend) -> dict[str, int]:
    """The smoother's counters that add up over map segments (for stats.json)."""
    s = backend.stats
    return {
        "projection_factors": s.projection_factors,
        "still_keyframes": s.still_keyframes,
        "rejected_triangulations": s.rejected_triangulations,
        "gated_observations": s.gated_observations,
        "landmark_deferrals": s.landmark_deferrals,
        "loop_closures": s.loop_closures,
        "pose_graph_loops": s.pose_graph_loops,
        "retired_keyframes": s.retired_keyframes,
        "frozen_landmarks": s.frozen_landmarks,
        "window_rebuilds": s.window_rebuilds,
        "blind_keyframes": s.blind_keyframes,
        "recovered_updates": s.recovered_updates,
        "qr_fallbacks": s.qr_fallbacks,
        "final_batch_iterations": s.final_batch_iterations,
    }
