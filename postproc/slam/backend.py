"""Keyframe visual-inertial smoother on GTSAM: IMU preintegration, projections, ISAM2.

Each keyframe k has a pose X(k) = T_S_B (body = IMU in the session frame S),
a velocity V(k) in S (m/s) and IMU biases B(k). Consecutive keyframes are tied
by a `CombinedImuFactor` (Forster et al. 2017 on-manifold preintegration, with
the bias random walk inside the factor); every landmark L(j) (a point in S,
metres) is tied to the keyframes that saw it by a `GenericProjectionFactorCal3_S2`
through the camera extrinsic T_B_C, under a Huber loss. ISAM2 (Kaess et al.
2012) keeps the smoothing solution of a sliding window current as keyframes arrive.

Bounded size (long dives): ISAM2 holds at most `window_keyframes` +
`window_step_keyframes` keyframes. When it is full, the oldest
`window_step_keyframes` are retired: their poses are frozen, the first
keyframe kept gets anchor priors on its pose, velocity and biases (fixed
sigmas, `anchor_*`: ISAM2's marginal covariance of an old variable costs about
a second), landmarks no longer seen twice in the window are frozen
(kept for the map, no longer optimised; their tracks are not re-added), and a
new ISAM2 is built from the remaining factors. Memory and update time then
stay flat however long the dive. Observations of retired keyframes are
dropped rather than marginalised exactly (the anchor priors carry the
retired part; a cheaper, slightly less informative choice than a Schur
complement, with no fill-in to manage). Loop closures are also recorded in a
global pose graph (a `BetweenFactorPose3` chain of consecutive keyframes'
relative poses plus the robust loop constraints); when a loop reaches a
retired keyframe, `finish` optimises that graph over every keyframe for the
globally consistent trajectory.

Measurements are undistorted normalised coordinates (the frontend removes the
lens model), scaled by the focal length so that the noise is in pixels: the
factors use a distortion-free `Cal3_S2(f, f, 0, 0, 0)`.

Blind keyframes (no projection factor: open water) are counted; the estimator
keeps them sparse (issue #7). Every state is anchored: the first keyframe's
pose, velocity and biases by priors, every later keyframe's through the IMU
factor chain (which ties pose, velocity and biases to the previous ones), and
every velocity also by a weak prior of its own; the bias random walks are
floored. So the system is never singular by construction. Should ISAM2 still
find it indeterminate (poorly conditioned), `add_keyframe` rebuilds it from all
its factors with weak priors on the state GTSAM names (or without the landmark
it names, and each further landmark it names), then once more with QR
factorisation, instead of failing; the
trajectory is kept and `stats.recovered_updates` / `stats.qr_fallbacks` count
these. What still fails raises StageError, and the estimator starts a new map
segment.

A landmark joins the graph only once its track has been seen in
`min_observations` keyframes with at least `min_parallax_deg` between the
extreme rays, triangulates in front of every camera and reprojects within
`max_reprojection_px`: low-parallax points make the linear system
ill-conditioned, and a diver often drifts slowly along the view direction.

No file I/O here (gtsam is imported inside the class so the CLI stays light).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.slam.options import GRAVITY_M_S2 as GRAVITY_M_S2
from postproc.slam.options import BackendOptions as BackendOptions
from postproc.slam.types import FloatArray, ImuSamples, IntArray
from shared.calibration.kalibr import ImuNoise
from shared.clock import seconds_from_ns
from shared.errors import StageError
from shared.geometry import invert_pose, make_pose

LOG = logging.getLogger(__name__)


@dataclass
class KeyframeState:
    """Estimated state of one keyframe (session frame S)."""

    stamp_ns: int  # IMU clock
    session_from_body: FloatArray  # T_S_B (4, 4)
    velocity_m_s: FloatArray  # (3,) in S
    accel_bias_m_s2: FloatArray  # (3,)
    gyro_bias_rad_s: FloatArray  # (3,)


@dataclass
class BackendStats:
    """Counters for stats.json."""

    keyframes: int = 0
    landmarks: int = 0
    projection_factors: int = 0
    still_keyframes: int = 0
    rejected_triangulations: int = 0
    gated_observations: int = 0
    landmark_deferrals: int = 0
    loop_closures: int = 0
    retired_keyframes: int = 0
    frozen_landmarks: int = 0
    window_rebuilds: int = 0
    pose_graph_loops: int = 0
    blind_keyframes: int = 0
    recovered_updates: int = 0
    qr_fallbacks: int = 0
    final_batch_iterations: int = 0
    reasons: dict[str, int] = field(default_factory=dict)


# --------------------------------------------------------------------------- pure helpers


def release_freed_memory() -> None:
    """Give memory freed by the C++ side back to the OS (glibc `malloc_trim`; else no-op).

    A discarded ISAM2 leaves its many small blocks in glibc's heap, fragmented;
    without a trim the resident size of a long dive creeps up although the live
    data stay bounded (measured: +540 MB vs +200 MB after 6,000 frames).
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to do
        return
    trim(0)


def gtsam_reason(error: BaseException | None) -> str:
    """GTSAM's multi-line exception text in one line (what failed and near which variable)."""
    return " ".join(str(error).split())[:160]


def indeterminate_symbol(error: BaseException) -> tuple[str, int] | None:
    """(character, index) of the variable an IndeterminateLinearSystemException names.

    None when `error` is another failure (GTSAM's text: "... near variable
    8646911284551352581 (Symbol: x261) ...").
    """
    text = str(error)
    if "Indeterminate linear system" not in text:
        return None
    match = re.search(r"\(Symbol: ([a-zA-Z])(\d+)\)", text)
    if match is None:
        return None
    return match.group(1), int(match.group(2))


def imu_intervals(
    imu: ImuSamples, start_ns: int, end_ns: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Piecewise-constant IMU readings covering [start_ns, end_ns] exactly.

    The interval is cut at every sample time inside it; each piece gets the
    reading linearly interpolated at its midpoint (second-order accurate, and
    the keyframe times need not fall on samples). Returns (accel (P, 3) m/s^2,
    gyro (P, 3) rad/s, dt (P,) s). Raises StageError if the IMU does not cover
    the interval.
    """
    stamps = imu.stamps_ns
    if len(stamps) < 2 or start_ns < stamps[0] or end_ns > stamps[-1]:
        raise StageError(
            f"IMU samples do not cover [{start_ns}, {end_ns}] ns (IMU spans "
            f"{stamps[0] if len(stamps) else 'nothing'} to {stamps[-1] if len(stamps) else ''})"
        )
    # Only the samples around the interval (long recordings hold millions).
    lo = max(int(np.searchsorted(stamps, start_ns, side="right")) - 1, 0)
    hi = min(int(np.searchsorted(stamps, end_ns, side="left")) + 1, len(stamps))
    stamps = stamps[lo:hi]
    inner = stamps[(stamps > start_ns) & (stamps < end_ns)]
    cuts = np.concatenate([[start_ns], inner, [end_ns]]).astype(np.int64)
    # Times relative to start keep float precision at the nanosecond level.
    rel = (stamps - start_ns).astype(np.float64)
    mid = ((cuts[:-1] - start_ns).astype(np.float64) + (cuts[1:] - start_ns).astype(np.float64)) / 2
    accel = np.column_stack([np.interp(mid, rel, imu.accel_m_s2[lo:hi, i]) for i in range(3)])
    gyro = np.column_stack([np.interp(mid, rel, imu.gyro_rad_s[lo:hi, i]) for i in range(3)])
    dt = seconds_from_ns(np.diff(cuts))
    return accel, gyro, dt


def triangulate_dlt(cam_from_session: FloatArray, xy_normalised: FloatArray) -> FloatArray:
    """Point in S (3,) seen at normalised coordinates (N, 2) by cameras `T_C_S` (N, 4, 4).

    Linear triangulation (Hartley & Zisserman, 12.2) on the normalised
    projection matrices [R | t]; NaN when the system is degenerate.
    """
    P = cam_from_session[:, :3, :]
    rows = np.concatenate(
        [
            xy_normalised[:, 0:1] * P[:, 2, :] - P[:, 0, :],
            xy_normalised[:, 1:2] * P[:, 2, :] - P[:, 1, :],
        ]
    )
    _, _, vt = np.linalg.svd(rows)
    h = vt[-1]
    if abs(h[3]) < 1e-12:
        return np.full(3, np.nan)
    point: FloatArray = h[:3] / h[3]
    return point


def parallax_deg(session_from_cam: FloatArray, xy_normalised: FloatArray) -> float:
    """Largest angle (degrees) between the rays of one point seen from several cameras."""
    rays = np.column_stack([xy_normalised, np.ones(len(xy_normalised))])
    rays_s = np.einsum("nij,nj->ni", session_from_cam[:, :3, :3], rays)
    rays_s /= np.linalg.norm(rays_s, axis=1, keepdims=True)
    cos = np.clip(rays_s @ rays_s.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


# --------------------------------------------------------------------------------- backend


class VisualInertialBackend:
    """Incremental keyframe smoother. Call `start`, then `add_keyframe` in time order.

    focal_px: focal length of the frontend image (pixels), to express the
        normalised measurements in pixels.
    imu_from_cam: `T_B_C` (4, 4).
    imu_noise: Kalibr IMU noise (continuous-time densities).
    """

    def __init__(
        self,
        options: BackendOptions,
        *,
        focal_px: float,
        imu_from_cam: FloatArray,
        imu_noise: ImuNoise,
    ) -> None:
        import gtsam

        self.gtsam = gtsam
        self.options = options
        self.focal_px = float(focal_px)
        self.imu_from_cam = np.asarray(imu_from_cam, dtype=np.float64)
        self.cam_from_imu = invert_pose(self.imu_from_cam)
        self.stats = BackendStats()
        self._X = gtsam.symbol_shorthand.X
        self._V = gtsam.symbol_shorthand.V
        self._B = gtsam.symbol_shorthand.B
        self._L = gtsam.symbol_shorthand.L

        params = gtsam.PreintegrationCombinedParams.MakeSharedU(options.gravity_m_s2)
        inflate = options.imu_noise_inflation
        params.setAccelerometerCovariance(
            np.eye(3) * (inflate * imu_noise.accelerometer_noise_density) ** 2
        )
        params.setGyroscopeCovariance(
            np.eye(3) * (inflate * imu_noise.gyroscope_noise_density) ** 2
        )
        accel_walk = max(
            inflate * imu_noise.accelerometer_random_walk, options.min_accelerometer_random_walk
        )
        gyro_walk = max(
            inflate * imu_noise.gyroscope_random_walk, options.min_gyroscope_random_walk
        )
        params.setBiasAccCovariance(np.eye(3) * accel_walk**2)
        params.setBiasOmegaCovariance(np.eye(3) * gyro_walk**2)
        self.random_walks_used = (accel_walk, gyro_walk)
        # Integration of velocity into position: a small regulariser, as GTSAM's examples use.
        params.setIntegrationCovariance(np.eye(3) * 1e-8)
        self._preint_params = params

        self._calibration = gtsam.Cal3_S2(self.focal_px, self.focal_px, 0.0, 0.0, 0.0)
        self._body_P_cam = gtsam.Pose3(self.imu_from_cam)
        self._pixel_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(options.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, options.pixel_sigma_px),
        )
        self._factorization = options.factorization
        self._last_rebuild_error: RuntimeError | None = None
        self._isam = self._new_isam()
        self._first_active = 0  # keyframes before this are retired (frozen poses)
        self._frozen_points: dict[int, FloatArray] = {}  # retired landmarks, S (3,)
        # (old, new, T_Bold_Bnew, rotation sigma, translation sigma, Cauchy k)
        self._loops: list[tuple[int, int, FloatArray, float, float, float]] = []

        self._stamps_ns: list[int] = []
        self._poses: list[FloatArray] = []  # latest estimates T_S_B per keyframe
        self._velocities: list[FloatArray] = []
        self._biases: list[Any] = []
        # track id -> [(keyframe index, xy)], for tracks not yet landmarks
        self._pending: dict[int, list[tuple[int, FloatArray]]] = {}
        self._landmarks: set[int] = set()

    # ------------------------------------------------------------------ public interface

    @property
    def num_keyframes(self) -> int:
        return len(self._stamps_ns)

    def start(
        self,
        stamp_ns: int,
        session_from_body_rotation: FloatArray,
        track_ids: IntArray,
        xy_normalised: FloatArray,
        *,
        velocity_m_s: FloatArray | None = None,
        accel_bias_m_s2: FloatArray | None = None,
        gyro_bias_rad_s: FloatArray | None = None,
        velocity_sigma_m_s: float | None = None,
        gyro_bias_sigma_rad_s: float | None = None,
        position_m: FloatArray | None = None,
    ) -> None:
        """First keyframe at `stamp_ns` (IMU clock) with rotation `R_S_B` from gravity.

        `velocity_m_s` (in S) and `accel_bias_m_s2` come from the visual-inertial
        alignment when it succeeded (zero otherwise); `gyro_bias_rad_s` from a still
        start (zero otherwise); they centre the priors. `velocity_sigma_m_s` and
        `gyro_bias_sigma_rad_s` replace the options' prior sigmas (a start at rest knows
        both far better). `position_m` places the first keyframe (default: the origin
        of S; a new map segment starts where the last one left off).
        """
        gtsam = self.gtsam
        if self._stamps_ns:
            raise RuntimeError("start() called twice")
        o = self.options
        pose = np.eye(4)
        pose[:3, :3] = session_from_body_rotation
        if position_m is not None:
            pose[:3, 3] = np.asarray(position_m, dtype=np.float64)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        # Pose3's tangent is [rotation, translation] in the body frame. Roll and pitch
        # (from gravity) are uncertain; yaw about S's z and the position define S and are
        # pinned. Rotate the S-frame rotation covariance into the body frame.
        R_B_S = session_from_body_rotation.T
        rot_cov_s = np.diag([o.prior_tilt_sigma_rad**2, o.prior_tilt_sigma_rad**2, 1e-8])
        cov = np.zeros((6, 6))
        cov[:3, :3] = R_B_S @ rot_cov_s @ R_B_S.T
        cov[3:, 3:] = np.eye(3) * 1e-8
        pose_noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        graph.add(gtsam.PriorFactorPose3(self._X(0), gtsam.Pose3(pose), pose_noise))
        velocity = np.zeros(3) if velocity_m_s is None else np.asarray(velocity_m_s, float)
        bias = gtsam.imuBias.ConstantBias(
            np.zeros(3) if accel_bias_m_s2 is None else np.asarray(accel_bias_m_s2, float),
            np.zeros(3) if gyro_bias_rad_s is None else np.asarray(gyro_bias_rad_s, float),
        )
        graph.add(
            gtsam.PriorFactorVector(
                self._V(0),
                velocity,
                gtsam.noiseModel.Isotropic.Sigma(
                    3,
                    o.prior_velocity_sigma_m_s
                    if velocity_sigma_m_s is None
                    else velocity_sigma_m_s,
                ),
            )
        )
        gyro_sigma = o.prior_gyro_bias_sigma_rad_s
        if gyro_bias_sigma_rad_s is not None:
            gyro_sigma = gyro_bias_sigma_rad_s
        bias_noise = gtsam.noiseModel.Diagonal.Sigmas(
            np.concatenate(
                [
                    np.full(3, o.prior_accel_bias_sigma_m_s2),
                    np.full(3, gyro_sigma),
                ]
            )
        )
        graph.add(gtsam.PriorFactorConstantBias(self._B(0), bias, bias_noise))
        values.insert(self._X(0), gtsam.Pose3(pose))
        values.insert(self._V(0), velocity)
        values.insert(self._B(0), bias)
        self._isam.update(graph, values)
        self._stamps_ns.append(int(stamp_ns))
        self._poses.append(pose)
        self._velocities.append(velocity)
        self._biases.append(bias)
        for tid, xy in zip(track_ids.tolist(), xy_normalised, strict=True):
            self._pending[int(tid)] = [(0, xy.copy())]
        self.stats.keyframes = 1

    def _new_isam(self) -> Any:
        gtsam = self.gtsam
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(self.options.relinearize_threshold)
        isam_params.relinearizeSkip = 1
        isam_params.setFactorization(self._factorization)
        return gtsam.ISAM2(isam_params)

    @property
    def active_keyframes(self) -> int:
        """Keyframes currently in the smoother (the rest are retired and frozen)."""
        return self.num_keyframes - self._first_active

    def predicted_rotation(self, imu: ImuSamples, stamp_ns: int) -> FloatArray:
        """`R_Bprev_Bnow` from the gyro since the last keyframe, with its current bias."""
        pim = self.preintegrate(imu, self._stamps_ns[-1], stamp_ns, self._biases[-1])
        rotation: FloatArray = pim.deltaRij().matrix()
        return rotation

    def add_keyframe(
        self,
        stamp_ns: int,
        imu: ImuSamples,
        track_ids: IntArray,
        xy_normalised: FloatArray,
        *,
        still: bool = False,
    ) -> None:
        """Add a keyframe at `stamp_ns` (IMU clock) with its features; update the smoother.

        `imu` must cover the time since the previous keyframe. `still` adds a
        zero-velocity and zero-motion constraint (see initialization.is_still).
        """
        gtsam = self.gtsam
        if not self._stamps_ns:
            raise RuntimeError("add_keyframe() before start()")
        k = len(self._stamps_ns)
        prev_stamp = self._stamps_ns[-1]
        if stamp_ns <= prev_stamp:
            raise StageError(f"keyframe at {stamp_ns} ns is not after the previous {prev_stamp} ns")
        o = self.options
        X, V, B = self._X, self._V, self._B
        pim = gtsam.PreintegratedCombinedMeasurements(self._preint_params, self._biases[-1])
        accel, gyro, dt = imu_intervals(imu, prev_stamp, stamp_ns)
        for a, w, d in zip(accel, gyro, dt, strict=True):
            pim.integrateMeasurement(a, w, d)
        prev_state = gtsam.NavState(gtsam.Pose3(self._poses[-1]), self._velocities[-1])
        predicted = pim.predict(prev_state, self._biases[-1])
        pose_guess = predicted.pose().matrix()
        vel_guess = np.asarray(predicted.velocity())
        if still:
            pose_guess = make_pose(pose_guess[:3, :3], self._poses[-1][:3, 3])
            vel_guess = np.zeros(3)

        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
        values.insert(X(k), gtsam.Pose3(pose_guess))
        values.insert(V(k), vel_guess)
        values.insert(B(k), self._biases[-1])
        if o.weak_velocity_sigma_m_s > 0:
            graph.add(
                gtsam.PriorFactorVector(
                    V(k),
                    np.zeros(3),
                    gtsam.noiseModel.Isotropic.Sigma(3, o.weak_velocity_sigma_m_s),
                )
            )
        if still:
            self.stats.still_keyframes += 1
            graph.add(
                gtsam.PriorFactorVector(
                    V(k),
                    np.zeros(3),
                    gtsam.noiseModel.Isotropic.Sigma(3, o.zero_velocity_sigma_m_s),
                )
            )
            span_s = seconds_from_ns(stamp_ns - prev_stamp)
            graph.add(
                gtsam.BetweenFactorPose3(
                    X(k - 1),
                    X(k),
                    gtsam.Pose3(),
                    # Rotation stays free (a hovering diver may look around); the
                    # translation may move only as far as the velocity sigma allows.
                    gtsam.noiseModel.Diagonal.Sigmas(
                        np.concatenate(
                            [np.full(3, 1.0), np.full(3, o.zero_velocity_sigma_m_s * span_s)]
                        )
                    ),
                )
            )

        self._stamps_ns.append(int(stamp_ns))
        self._poses.append(pose_guess)
        self._velocities.append(vel_guess)
        self._biases.append(self._biases[-1])

        projections_before = self.stats.projection_factors
        new_landmarks = self._add_visual_factors(k, track_ids, xy_normalised, graph, values)
        if self.stats.projection_factors == projections_before:
            self.stats.blind_keyframes += 1  # only the IMU (and a still prior) ties it
        self._update_or_recover(graph, values, f"at keyframe {k} ({stamp_ns} ns")
        self._refresh_recent(k)
        self.stats.keyframes = k + 1
        o_w = self.options.window_keyframes
        if o_w > 0 and self.active_keyframes >= o_w + self.options.window_step_keyframes:
            self._retire(self.num_keyframes - o_w)
        LOG.debug("keyframe %d: %d new landmarks, %d total", k, new_landmarks, len(self._landmarks))

    def _update_or_recover(self, graph: Any, values: Any, where: str) -> None:
        """ISAM2 update with new factors; one recovery if GTSAM finds the system indeterminate.

        GTSAM raises IndeterminateLinearSystemException (a RuntimeError in Python)
        naming the variable whose elimination failed; ISAM2 has by then already
        taken the new factors and values, but its Bayes tree is stale. Recovery
        rebuilds ISAM2 from all its factors at the linearisation point, drops the
        projection factors of a named landmark, adds weak priors on the named
        variable (and the keyframe states it belongs to) and updates once. The
        trajectory is kept; `stats.recovered_updates` counts these.
        """
        o = self.options
        factors_before = self._isam.getFactorsUnsafe().size()
        try:
            self._isam.update(graph, values)
            for _ in range(o.extra_iterations):
                self._isam.update()
            return
        except RuntimeError as error:
            symbol = indeterminate_symbol(error)
            if symbol is None:
                # GTSAM reports other ill-posed systems (a diverged estimate) as
                # RuntimeError too; say where it happened.
                raise StageError(
                    f"visual-inertial backend failed {where}, {len(self._landmarks)} "
                    f"landmarks): {gtsam_reason(error)}"
                ) from error
            first_error = error
        LOG.warning("ISAM2 update %s): %s; rebuilding", where, gtsam_reason(first_error))
        if self._rebuild_dropping_landmarks(graph, values, factors_before, symbol):
            self.stats.recovered_updates += 1
            return
        # Cholesky gives up on systems that are only badly scaled; QR does not.
        if self._factorization != "QR":
            LOG.warning("ISAM2 rebuild %s): rebuilding with QR factorisation from now on", where)
            self._factorization = "QR"
            self.stats.qr_fallbacks += 1
            if self._rebuild_dropping_landmarks(graph, values, factors_before, symbol):
                self.stats.recovered_updates += 1
                return
        last_error = self._last_rebuild_error
        raise StageError(
            f"visual-inertial backend failed {where}, {len(self._landmarks)} landmarks) "
            f"even after recovery: {gtsam_reason(last_error)} (first: {gtsam_reason(first_error)})"
        ) from last_error

    def _rebuild_dropping_landmarks(
        self, graph: Any, values: Any, factors_before: int, symbol: tuple[str, int]
    ) -> bool:
        """`_rebuild_after_failure`, again for each further landmark GTSAM names (up to
        `max_landmark_drops`); False when it still fails (`_last_rebuild_error` says why)."""
        for _ in range(self.options.max_landmark_drops + 1):
            try:
                self._rebuild_after_failure(graph, values, factors_before, symbol)
                return True
            except RuntimeError as error:
                self._last_rebuild_error = error
                named = indeterminate_symbol(error)
                if named is None or named[0] != "l":
                    return False
                symbol = named
        return False

    def _rebuild_after_failure(
        self, graph: Any, values: Any, factors_before: int, symbol: tuple[str, int]
    ) -> None:
        gtsam = self.gtsam
        o = self.options
        old = self._isam
        factors = old.getFactorsUnsafe()
        theta = old.getLinearizationPoint()
        rebuilt = gtsam.NonlinearFactorGraph()
        chr_, index = symbol
        drop_landmark = self._L(index) if chr_ == "l" else None
        sources = [factors.at(n) for n in range(factors.size())]
        if factors.size() == factors_before:  # the failed update did not take them
            sources += [graph.at(n) for n in range(graph.size())]
        for factor in sources:
            if factor is None:
                continue
            if drop_landmark is not None and drop_landmark in list(factor.keys()):
                continue
            rebuilt.add(factor)
        start = gtsam.Values(theta)
        new_keys = values.keys()
        if any(not start.exists(key) for key in new_keys):  # not taken either
            start.insert(values)
        if drop_landmark is not None:
            self._landmarks.discard(index)
            if start.exists(drop_landmark):
                start.erase(drop_landmark)
        else:
            # Weak priors on the keyframe the named state belongs to (and the next one).
            for k in (index, index + 1):
                if not start.exists(self._X(k)):
                    continue
                rebuilt.add(
                    gtsam.PriorFactorPose3(
                        self._X(k),
                        start.atPose3(self._X(k)),
                        gtsam.noiseModel.Diagonal.Sigmas(
                            np.concatenate(
                                [
                                    np.full(3, o.recovery_rotation_sigma_rad),
                                    np.full(3, o.recovery_position_sigma_m),
                                ]
                            )
                        ),
                    )
                )
                rebuilt.add(
                    gtsam.PriorFactorVector(
                        self._V(k),
                        start.atVector(self._V(k)),
                        gtsam.noiseModel.Isotropic.Sigma(3, o.recovery_velocity_sigma_m_s),
                    )
                )
        self._isam = self._new_isam()
        del old, factors, theta
        release_freed_memory()
        self._isam.update(rebuilt, start)

    def landmark_position(self, track_id: int) -> FloatArray | None:
        """Current position in S (3,) of the landmark of `track_id`, None if it is none."""
        if track_id in self._frozen_points:
            return self._frozen_points[track_id]
        if track_id not in self._landmarks:
            return None
        point: FloatArray = np.asarray(self._isam.calculateEstimatePoint3(self._L(track_id)))
        return point

    def cached_poses(self) -> list[FloatArray]:
        """Latest pulled estimates `T_S_B` of all keyframes (older ones may lag slightly)."""
        return list(self._poses)

    def session_from_body(self, k: int) -> FloatArray:
        """Current estimate of keyframe k's pose `T_S_B`."""
        if k < self._first_active:
            return self._poses[k]
        pose: FloatArray = self._isam.calculateEstimatePose3(self._X(k)).matrix()
        return pose

    def add_loop(
        self,
        old: int,
        new: int,
        old_from_new: FloatArray,
        *,
        rotation_sigma_rad: float,
        translation_sigma_m: float,
        cauchy_k: float,
        iterations: int = 2,
    ) -> None:
        """Constrain keyframe `new` relative to keyframe `old` (`T_Bold_Bnew`), robustly.

        The loop always enters the global pose graph; it enters the smoother too
        when `old` is still in the window.
        """
        gtsam = self.gtsam
        self._loops.append(
            (
                old,
                new,
                np.asarray(old_from_new, float),
                rotation_sigma_rad,
                translation_sigma_m,
                cauchy_k,
            )
        )
        if old < self._first_active:
            self.stats.pose_graph_loops += 1
            self.stats.loop_closures += 1
            return
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k),
            gtsam.noiseModel.Diagonal.Sigmas(
                np.concatenate([np.full(3, rotation_sigma_rad), np.full(3, translation_sigma_m)])
            ),
        )
        graph = gtsam.NonlinearFactorGraph()
        graph.add(
            gtsam.BetweenFactorPose3(self._X(old), self._X(new), gtsam.Pose3(old_from_new), noise)
        )
        try:
            self._isam.update(graph, gtsam.Values())
            for _ in range(iterations):
                self._isam.update()
        except RuntimeError as error:
            raise StageError(
                f"visual-inertial backend failed closing the loop {old} -> {new}: "
                f"{gtsam_reason(error)}"
            ) from error
        self.stats.loop_closures += 1
        self._refresh_recent(self.num_keyframes - 1)

    def abandon(self) -> list[KeyframeState]:
        """States of every keyframe that was added successfully, for a smoother that failed.

        The keyframe of the failed update is dropped; the others get ISAM2's estimate
        where it can still give one, else their last pulled values. The backend takes no
        further keyframes after this (the estimator starts a new map segment).
        """
        while len(self._stamps_ns) > max(self.stats.keyframes, 1):
            self._stamps_ns.pop()
            self._poses.pop()
            self._velocities.pop()
            self._biases.pop()
        try:
            estimate = self._isam.calculateEstimate()
            for k in range(self._first_active, self.num_keyframes):
                self._poses[k] = estimate.atPose3(self._X(k)).matrix()
                self._velocities[k] = np.asarray(estimate.atVector(self._V(k)))
                self._biases[k] = estimate.atConstantBias(self._B(k))
            self._estimate = estimate
        except RuntimeError as error:  # the failed smoother cannot say: keep what was pulled
            LOG.warning("failed smoother: keeping the last pulled states (%s)", gtsam_reason(error))
            self._landmarks = set()
            self._estimate = self.gtsam.Values()
        return self.keyframe_states()

    def keyframe_states(self) -> list[KeyframeState]:
        """Current estimates of every keyframe (after `finish`, the final ones)."""
        return [
            KeyframeState(
                stamp_ns=s,
                session_from_body=p.copy(),
                velocity_m_s=v.copy(),
                accel_bias_m_s2=np.asarray(b.accelerometer()).copy(),
                gyro_bias_rad_s=np.asarray(b.gyroscope()).copy(),
            )
            for s, p, v, b in zip(
                self._stamps_ns, self._poses, self._velocities, self._biases, strict=True
            )
        ]

    def landmarks(self) -> tuple[IntArray, FloatArray]:
        """Track ids (L,) and positions in S (L, 3) of the landmarks in the graph."""
        ids = np.array(sorted(self._landmarks | set(self._frozen_points)), dtype=np.int64)
        if not len(ids):
            return ids, np.zeros((0, 3))
        estimate = self._estimate if hasattr(self, "_estimate") else self._isam.calculateEstimate()
        points = np.array(
            [
                self._frozen_points[i]
                if i in self._frozen_points
                else estimate.atPoint3(self._L(i))
                for i in ids.tolist()
            ],
            dtype=np.float64,
        )
        return ids, points.reshape(-1, 3)

    def finish(self) -> None:
        """Final estimate: ISAM2's, optionally refined by a batch Levenberg-Marquardt pass."""
        gtsam = self.gtsam
        estimate = self._isam.calculateEstimate()
        if self.options.final_batch and self.num_keyframes > 1:
            graph = self._isam.getFactorsUnsafe()
            cleaned = gtsam.NonlinearFactorGraph()
            for i in range(graph.size()):
                factor = graph.at(i)
                if factor is not None:
                    cleaned.add(factor)
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(self.options.final_batch_max_iterations)
            params.setRelativeErrorTol(self.options.final_batch_relative_tolerance)
            try:
                optimizer = gtsam.LevenbergMarquardtOptimizer(cleaned, estimate, params)
                estimate = optimizer.optimize()
                self.stats.final_batch_iterations += int(optimizer.iterations())
            except RuntimeError as error:  # an indeterminant system: keep ISAM2's answer
                LOG.warning("final batch refinement failed (%s); keeping the ISAM2 estimate", error)
        self._estimate = estimate
        for k in range(self._first_active, self.num_keyframes):
            self._poses[k] = estimate.atPose3(self._X(k)).matrix()
            self._velocities[k] = np.asarray(estimate.atVector(self._V(k)))
            self._biases[k] = estimate.atConstantBias(self._B(k))
        if self._first_active > 0 and self._loops:
            self._optimise_pose_graph()

    def preintegrate(self, imu: ImuSamples, start_ns: int, end_ns: int, bias: Any) -> Any:
        """A fresh preintegration of `imu` over [start_ns, end_ns] with `bias` (for frame poses)."""
        pim = self.gtsam.PreintegratedCombinedMeasurements(self._preint_params, bias)
        self.integrate(pim, imu, start_ns, end_ns)
        return pim

    @staticmethod
    def integrate(pim: Any, imu: ImuSamples, start_ns: int, end_ns: int) -> None:
        """Add the IMU readings of [start_ns, end_ns] to the preintegration `pim`."""
        if end_ns > start_ns:
            accel, gyro, dt = imu_intervals(imu, start_ns, end_ns)
            for a, w, d in zip(accel, gyro, dt, strict=True):
                pim.integrateMeasurement(a, w, d)

    def bias_of(self, k: int) -> Any:
        """The gtsam bias object of keyframe k."""
        return self._biases[k]

    # ------------------------------------------------------------------------- internals

    def _retire(self, first_kept: int) -> None:
        """Freeze keyframes before `first_kept`; rebuild ISAM2 on the rest (see module doc)."""
        gtsam = self.gtsam
        isam = self._isam
        X, V, B, L = self._X, self._V, self._B, self._L
        estimate = isam.calculateEstimate()
        for i in range(self._first_active, first_kept):
            self._poses[i] = estimate.atPose3(X(i)).matrix()
        # Anchor priors on the first kept state, in place of the retired part. (ISAM2's
        # marginal covariance there is exact but costs ~1 s for an old variable deep in
        # the Bayes tree; these sigmas are the window's gauge and bias memory.)
        o = self.options
        priors = [
            gtsam.PriorFactorPose3(
                X(first_kept),
                estimate.atPose3(X(first_kept)),
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.concatenate(
                        [
                            np.full(3, o.anchor_rotation_sigma_rad),
                            np.full(3, o.anchor_position_sigma_m),
                        ]
                    )
                ),
            ),
            gtsam.PriorFactorVector(
                V(first_kept),
                estimate.atVector(V(first_kept)),
                gtsam.noiseModel.Isotropic.Sigma(3, o.anchor_velocity_sigma_m_s),
            ),
            gtsam.PriorFactorConstantBias(
                B(first_kept),
                estimate.atConstantBias(B(first_kept)),
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.concatenate(
                        [
                            np.full(3, o.anchor_accel_bias_sigma_m_s2),
                            np.full(3, o.anchor_gyro_bias_sigma_rad_s),
                        ]
                    )
                ),
            ),
        ]
        landmark_chr = ord("l")
        kept: list[Any] = []
        observations: dict[int, int] = {}
        factors = isam.getFactorsUnsafe()
        for n in range(factors.size()):
            factor = factors.at(n)
            if factor is None:
                continue
            keep = True
            landmark = None
            keys = factor.keys()
            for key in keys:
                symbol = gtsam.Symbol(key)
                if symbol.chr() == landmark_chr:
                    landmark = int(symbol.index())
                elif symbol.index() < first_kept:
                    keep = False
            if keep:
                kept.append(factor)
                if landmark is not None:
                    observations[landmark] = observations.get(landmark, 0) + 1
        # A landmark seen fewer than twice in the window would be unconstrained in depth.
        live = {tid for tid, count in observations.items() if count >= 2}
        for tid in self._landmarks - live:
            self._frozen_points[tid] = np.asarray(estimate.atPoint3(L(tid)))
        self.stats.frozen_landmarks += len(self._landmarks - live)
        self._landmarks = live
        graph = gtsam.NonlinearFactorGraph()
        for factor in priors:
            graph.add(factor)
        for factor in kept:
            keys = factor.keys()
            if any(
                gtsam.Symbol(key).chr() == landmark_chr
                and int(gtsam.Symbol(key).index()) not in live
                for key in keys
            ):
                continue
            graph.add(factor)
        values = gtsam.Values()
        for i in range(first_kept, self.num_keyframes):
            values.insert(X(i), estimate.atPose3(X(i)))
            values.insert(V(i), estimate.atVector(V(i)))
            values.insert(B(i), estimate.atConstantBias(B(i)))
        for tid in live:
            values.insert(L(tid), estimate.atPoint3(L(tid)))
        # Pending tracks may no longer use retired keyframes (not in the new graph).
        self._pending = {
            tid: [(i, xy) for i, xy in obs if i >= first_kept] for tid, obs in self._pending.items()
        }
        self._isam = self._new_isam()
        del factors, kept, estimate
        release_freed_memory()
        try:
            self._isam.update(graph, values)
        except RuntimeError as error:
            raise StageError(
                f"visual-inertial backend failed retiring keyframes before {first_kept}: "
                f"{gtsam_reason(error)}"
            ) from error
        self.stats.retired_keyframes += first_kept - self._first_active
        self.stats.window_rebuilds += 1
        self._first_active = first_kept
        self._refresh_recent(self.num_keyframes - 1)

    def _optimise_pose_graph(self) -> None:
        """Globally consistent keyframe poses: relative-pose chain plus every loop."""
        gtsam = self.gtsam
        o = self.options
        X = self._X
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(
            gtsam.PriorFactorPose3(
                X(0), gtsam.Pose3(self._poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
            )
        )
        chain = gtsam.noiseModel.Diagonal.Sigmas(
            np.concatenate(
                [
                    np.full(3, o.pose_graph_rotation_sigma_rad),
                    np.full(3, o.pose_graph_translation_sigma_m),
                ]
            )
        )
        for k, pose in enumerate(self._poses):
            values.insert(X(k), gtsam.Pose3(pose))
            if k:
                relative = invert_pose(self._poses[k - 1]) @ pose
                graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(relative), chain))
        for old, new, old_from_new, rot_sigma, trans_sigma, cauchy_k in self._loops:
            noise = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k),
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.concatenate([np.full(3, rot_sigma), np.full(3, trans_sigma)])
                ),
            )
            graph.add(gtsam.BetweenFactorPose3(X(old), X(new), gtsam.Pose3(old_from_new), noise))
        try:
            result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        except RuntimeError as error:
            LOG.warning("pose graph optimisation failed (%s); keeping the window poses", error)
            return
        for k in range(self.num_keyframes):
            self._poses[k] = result.atPose3(X(k)).matrix()

    def _refresh_recent(self, k: int, window: int = 30) -> None:
        """Pull the estimates of the last `window` keyframes (the ones tracks still need)."""
        isam = self._isam
        for i in range(max(self._first_active, k - window + 1), k + 1):
            self._poses[i] = isam.calculateEstimatePose3(self._X(i)).matrix()
        self._velocities[k] = np.asarray(isam.calculateEstimateVector(self._V(k)))
        self._biases[k] = isam.calculateEstimateConstantBias(self._B(k))

    def _projection_factor(self, k: int, track_id: int, xy: FloatArray) -> Any:
        gtsam = self.gtsam
        self.stats.projection_factors += 1
        return gtsam.GenericProjectionFactorCal3_S2(
            self.focal_px * np.asarray(xy, dtype=np.float64),
            self._pixel_noise,
            self._X(k),
            self._L(track_id),
            self._calibration,
            self._body_P_cam,
        )

    def _add_visual_factors(
        self,
        k: int,
        track_ids: IntArray,
        xy_normalised: FloatArray,
        graph: Any,
        values: Any,
    ) -> int:
        o = self.options
        seen_now: dict[int, list[tuple[int, FloatArray]]] = {}
        ids = [int(t) for t in track_ids.tolist()]
        # Gate the observations of known landmarks against the current estimate, all at
        # once: a leftover outlier of the frontend must not drag a landmark (Huber bounds
        # its pull, not its presence).
        known = [
            i for i, t in enumerate(ids) if t not in self._frozen_points and t in self._landmarks
        ]
        passed = self._gate(k, [ids[i] for i in known], xy_normalised[known])
        passes = iter(passed.tolist())
        for tid, xy in zip(ids, xy_normalised, strict=True):
            if tid in self._frozen_points:
                continue  # retired with its keyframes; not re-added as a new landmark
            if tid in self._landmarks:
                if next(passes):
                    graph.add(self._projection_factor(k, tid, xy))
                else:
                    self.stats.gated_observations += 1
                continue
            observations = self._pending.get(tid, [])
            observations.append((k, xy.copy()))
            seen_now[tid] = observations
        # Tracks not seen in this keyframe have ended (the tracker is frame to frame).
        self._pending = seen_now
        added = 0
        min_parallax = o.min_parallax_deg
        # The landmark budget: what this keyframe observes already, then the longest-seen
        # tracks first (a stable sort keeps the tracker's order among equals).
        budget = o.max_landmarks_per_keyframe
        room = budget - int(passed.sum()) if budget > 0 else None
        ready = [item for item in seen_now.items() if len(item[1]) >= o.min_observations]
        ready.sort(key=lambda item: -len(item[1]))
        for count, (tid, observations) in enumerate(ready):
            if room is not None and added >= room:
                self.stats.landmark_deferrals += len(ready) - count
                break
            frames = [i for i, _ in observations]
            xy = np.array([p for _, p in observations])
            session_from_cam = np.array([self._poses[i] @ self.imu_from_cam for i in frames])
            if parallax_deg(session_from_cam, xy) < min_parallax:
                continue
            cam_from_session = invert_pose(session_from_cam)
            point = triangulate_dlt(cam_from_session, xy)
            if not self._triangulation_ok(point, cam_from_session, xy):
                self.stats.rejected_triangulations += 1
                # Keep only the latest observation: the older ones may hold the outlier.
                seen_now[tid] = observations[-1:]
                continue
            values.insert(self._L(tid), point)
            if o.landmark_prior_sigma_m > 0:
                graph.add(
                    self.gtsam.PriorFactorPoint3(
                        self._L(tid),
                        point,
                        self.gtsam.noiseModel.Isotropic.Sigma(3, o.landmark_prior_sigma_m),
                    )
                )
            for i, p in observations:
                graph.add(self._projection_factor(i, tid, p))
            self._landmarks.add(tid)
            del seen_now[tid]
            added += 1
        self.stats.landmarks = len(self._landmarks)
        return added

    def _gate(
        self, k: int, track_ids: list[int], xy_normalised: FloatArray
    ) -> npt.NDArray[np.bool_]:
        """Which observations (normalised (N, 2)) of landmarks `track_ids` by keyframe `k`
        lie in front of it and within `max_gate_px` of the landmark's estimate."""
        if not track_ids:
            return np.zeros(0, dtype=bool)
        o = self.options
        cam_from_session = invert_pose(self._poses[k] @ self.imu_from_cam)
        points = np.array([self._isam.calculateEstimatePoint3(self._L(t)) for t in track_ids])
        p_c = points @ cam_from_session[:3, :3].T + cam_from_session[:3, 3]
        in_front = p_c[:, 2] > o.min_depth_m
        with np.errstate(divide="ignore", invalid="ignore"):
            error_px = self.focal_px * np.linalg.norm(
                p_c[:, :2] / p_c[:, 2:3] - xy_normalised, axis=1
            )
        passed: npt.NDArray[np.bool_] = in_front & (error_px <= o.max_gate_px)
        return passed

    def _triangulation_ok(
        self, point: FloatArray, cam_from_session: FloatArray, xy: FloatArray
    ) -> bool:
        o = self.options
        if not np.all(np.isfinite(point)):
            return False
        p_c = (
            np.einsum("nij,j->ni", cam_from_session[:, :3, :3], point) + cam_from_session[:, :3, 3]
        )
        depth = p_c[:, 2]
        if np.any(depth < o.min_depth_m) or np.any(depth > o.max_depth_m):
            return False
        error_px = self.focal_px * np.linalg.norm(p_c[:, :2] / depth[:, None] - xy, axis=1)
        return bool(np.all(error_px <= o.max_reprojection_px))
