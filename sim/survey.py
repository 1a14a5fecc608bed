"""A simulated wreck survey with exact truth: the data every stage's accuracy is measured on.

`SurveySimulator` holds the scene, the camera, and each session's diver trajectory, IMU and
clocks, all drawn from one seed; it renders any frame on demand (`render_frame`, the call a
live source uses) and gives the truth. `run` writes a whole survey folder (see
`sim` for the layout). Time bases: every session's IMU clock *is* true time
(int64 ns since the epoch); camera stamps follow Kalibr, t_imu = t_cam + timeshift; the
GoPro file counts media time from its first frame; the dive computer has its own clock.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.calibration.cameras import PinholeRadtan
from shared.calibration.kalibr import CameraCalibration, ImuNoise
from shared.clock import NS_PER_S, ClockModel, ns_from_seconds
from shared.errors import OutputExistsError
from shared.folders import SessionFolder
from shared.forkpool import fork_pool
from shared.formats.diveprofile import DiveProfile
from sim.dive import DiveComputerOptions, simulate_dive_profile
from sim.imu import GRAVITY_W_M_S2, SimulatedImu, simulate_imu
from sim.mesh import scene_mesh, write_ply
from sim.motion import DiverRoute, builtin_route, diver_trajectory
from sim.render import RenderedFrame, Renderer, WaterModel
from sim.scene import WreckScene, build_wreck_scene
from sim.spline import SplineTrajectory

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

TRUTH_FORMAT = "wreckmap-sim-truth"
# Version 2: the unit suffixes of the tree (gravity_w_m_s2, gyro_bias0_rad_s, accel_bias0_m_s2;
# version 1 spelled them _mps2 and _radps).
TRUTH_VERSION = 2
# The survey's calib/ (camchain.yaml, imu.yaml) is laid out as a session's, so that the
# pipeline hands it on as it would a field session's; truth.json names it relative to DIR.
_SURVEY_CALIB = SessionFolder(".")
# The ORIN a HERO9 writes for ACCL/GYRO (value order of the IMU chip axes).
GOPRO_IMU_AXIS_ORDER = "ZXY"

# Random streams, one per purpose, so adding one never changes another.
_RNG_MOTION, _RNG_IMU, _RNG_CLOCKS, _RNG_DIVE, _RNG_FRAME, _RNG_BIAS = range(1, 7)


def default_imu_noise(rate_hz: float = 200.0) -> ImuNoise:
    """A consumer MEMS IMU like an action camera's (Kalibr densities, continuous time)."""
    return ImuNoise(
        accelerometer_noise_density=2.0e-3,
        accelerometer_random_walk=4.0e-4,
        gyroscope_noise_density=1.7e-4,
        gyroscope_random_walk=2.0e-5,
        update_rate_hz=rate_hz,
    )


def default_camera(
    width: int,
    height: int,
    *,
    focal_per_width: float = 0.53,
    fy_per_fx: float = 1.0,
    k1: float = -0.22,
    k2: float = 0.05,
) -> PinholeRadtan:
    """A GoPro-like wide camera (about 86 degrees across at the default focal length,
    fx = `focal_per_width` * width px) with barrel distortion and a principal point a
    little off the centre."""
    f = focal_per_width * width
    return PinholeRadtan(
        width=width,
        height=height,
        fx=f,
        fy=f * fy_per_fx,
        cx=(width - 1) / 2.0 + 0.011 * width,
        cy=(height - 1) / 2.0 - 0.008 * height,
        k1=k1,
        k2=k2,
        p1=3.0e-4,
        p2=-2.0e-4,
    )


def default_cam_from_imu() -> FloatArray:
    """`T_C_B`: IMU x forward, y left, z up, mounted a few centimetres from the lens, and
    1-2 degrees off the nominal axes (as a real calibration finds)."""
    from shared.geometry import so3_exp

    nominal = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    pose = np.eye(4)
    pose[:3, :3] = so3_exp(np.array([0.012, -0.02, 0.008])) @ nominal
    pose[:3, 3] = (0.021, -0.012, -0.034)
    return pose


@dataclass(kw_only=True)
class SurveyOptions:
    """What to simulate.

    sessions: number of dives (routes from `sim.motion.builtin_route`);
    duration_s: filmed seconds per session; seed: everything random derives from it;
    width, height (px), fps (Hz): the camera; video: also write the GoPro-like MP4;
    video_crf: its x264 quality (constant rate factor, preset ultrafast; lower is better).
    18 gives about 1.2 bit per pixel and frame on the wreck at 960x540, what a GoPro
    records at 1080p (about 60 Mbit/s, 1 bit per pixel); a GoPro's 4K file scaled down
    to this size is cleaner still. 28 (0.12 bit per pixel) blurs the texture that
    matching and the depth maps need;
    imu_rate_hz: IMU sample rate; timeshift_cam_imu_s: Kalibr's t_imu = t_cam + shift;
    texel_m, seafloor_texel_m: texture resolution (m per texel); workers: render processes;
    start_utc: true start of session 0 (ISO 8601, UTC); session_gap_s: between session
    starts (s); speed_m_s: mean swimming speed; save_depth: also write each frame's depth
    map (camera z) as a 16-bit PNG in millimetres; cam_from_imu: the extrinsic `T_C_B`
    (4x4, default `default_cam_from_imu()`); water: the image model; imu_noise: Kalibr
    noise (default `default_imu_noise`); dive_computer: the dive computer's settings.
    """

    sessions: int = 2
    duration_s: float = 60.0
    seed: int = 1
    width: int = 640
    height: int = 360
    fps: float = 15.0
    video: bool = True
    video_crf: int = 18
    imu_rate_hz: float = 200.0
    timeshift_cam_imu_s: float = 0.0125
    texel_m: float = 0.005
    seafloor_texel_m: float = 0.015
    workers: int = 2
    start_utc: str = "2024-06-15T09:30:00"
    session_gap_s: float = 10800.0
    speed_m_s: float = 0.35
    save_depth: bool = False
    cam_from_imu: FloatArray | None = None
    water: WaterModel = field(default_factory=WaterModel)
    imu_noise: ImuNoise | None = None
    dive_computer: DiveComputerOptions = field(default_factory=DiveComputerOptions)

    def __post_init__(self) -> None:
        if self.sessions < 1:
            raise ValueError(f"sessions must be at least 1, got {self.sessions}")
        if not self.duration_s > 0:
            raise ValueError(f"duration_s must be positive, got {self.duration_s}")
        if self.width < 16 or self.height < 16 or self.width % 2 or self.height % 2:
            raise ValueError(
                "image size must be even and at least 16x16 (H.264), "
                f"got {self.width}x{self.height}"
            )
        if not 0 < self.fps <= 240:
            raise ValueError(f"fps must be in (0, 240], got {self.fps}")
        if not 0 <= self.video_crf <= 51:
            raise ValueError(f"video_crf must be in [0, 51] (x264), got {self.video_crf}")
        if abs(self.timeshift_cam_imu_s) >= 1.0:
            raise ValueError(
                f"timeshift_cam_imu_s must be below 1 s, got {self.timeshift_cam_imu_s}"
            )
        if self.imu_noise is None:
            self.imu_noise = default_imu_noise(self.imu_rate_hz)
        _utc_ns(self.start_utc)
        if self.cam_from_imu is not None:
            pose = np.asarray(self.cam_from_imu, dtype=np.float64)
            rotation = pose[:3, :3] if pose.shape == (4, 4) else np.zeros((3, 3))
            if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) or not np.allclose(
                pose[3], (0.0, 0.0, 0.0, 1.0)
            ):
                raise ValueError("cam_from_imu must be a 4x4 rigid transform")

    @property
    def imu(self) -> ImuNoise:
        """The IMU noise model in use (the default one when none was given)."""
        return self.imu_noise if self.imu_noise is not None else default_imu_noise(self.imu_rate_hz)


@dataclass
class SessionTruth:
    """Everything true about one session (times in int64 ns, true time = IMU clock)."""

    index: int
    name: str
    route: DiverRoute
    trajectory: SplineTrajectory
    start_ns: int
    end_ns: int
    frame_stamps_cam_ns: IntArray
    imu_stamps_ns: IntArray
    gyro_bias0_rad_s: FloatArray
    accel_bias0_m_s2: FloatArray
    dive_clock: ClockModel
    gopro_clock: ClockModel


def _utc_ns(iso: str) -> int:
    """ISO 8601 time (UTC when no zone is given) -> int64 ns since the epoch, exactly."""
    try:
        when = datetime.fromisoformat(iso)
    except ValueError as error:
        raise ValueError(f"start_utc: expected an ISO 8601 time, got {iso!r}") from error
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return (when - datetime(1970, 1, 1, tzinfo=UTC)) // timedelta(microseconds=1) * 1000


class SurveySimulator:
    """The simulated survey, built lazily from `options` (deterministic in `options.seed`)."""

    def __init__(self, options: SurveyOptions) -> None:
        self.options = options
        self.camera = default_camera(options.width, options.height)
        self.calibration = CameraCalibration(
            camera=self.camera,
            cam_from_imu=(
                default_cam_from_imu()
                if options.cam_from_imu is None
                else np.asarray(options.cam_from_imu, dtype=np.float64)
            ),
            timeshift_cam_imu_s=options.timeshift_cam_imu_s,
        )
        self.sessions = [self._make_session(k) for k in range(options.sessions)]
        self._scene: WreckScene | None = None
        self._renderer: Renderer | None = None

    # ------------------------------------------------------------- construction

    def _rng(self, purpose: int, *more: int) -> np.random.Generator:
        return np.random.default_rng([self.options.seed, purpose, *more])

    def _make_session(self, k: int) -> SessionTruth:
        opt = self.options
        start_ns = _utc_ns(opt.start_utc) + ns_from_seconds(k * opt.session_gap_s)
        duration_ns = ns_from_seconds(opt.duration_s)
        route = builtin_route(k)
        trajectory = diver_trajectory(
            route,
            start_ns=start_ns,
            duration_s=opt.duration_s,
            cam_from_imu=self.calibration.cam_from_imu,
            rng=self._rng(_RNG_MOTION, k),
            speed_m_s=opt.speed_m_s,
        )
        n_frames = max(int(np.floor(opt.duration_s * opt.fps + 1e-9)), 1)
        fps = Fraction(opt.fps).limit_denominator(1001)
        frame_offsets = np.array(
            [round(i * NS_PER_S / fps) for i in range(n_frames)], dtype=np.int64
        )
        n_imu = int(np.floor(opt.duration_s * opt.imu_rate_hz + 1e-9)) + 1
        imu_offsets = np.array(
            [round(j * NS_PER_S / opt.imu_rate_hz) for j in range(n_imu)], dtype=np.int64
        )
        bias_rng = self._rng(_RNG_BIAS, k)
        clock_rng = self._rng(_RNG_CLOCKS, k)
        # Dive computers keep local time (hours off UTC) and drift (tens of ppm).
        dive_clock = ClockModel(
            offset_ns=ns_from_seconds(
                3600.0 * int(clock_rng.integers(-3, 4)) + clock_rng.uniform(-120, 120)
            ),
            drift_ppm=float(clock_rng.uniform(-50.0, 50.0)),
            reference_ns=start_ns,
        )
        gopro_clock = ClockModel(
            offset_ns=ns_from_seconds(
                3600.0 * int(clock_rng.integers(0, 3)) + clock_rng.uniform(-30, 30)
            ),
            drift_ppm=float(clock_rng.uniform(-20.0, 20.0)),
            reference_ns=start_ns,
        )
        return SessionTruth(
            index=k,
            name=f"session_{k:02d}",
            route=route,
            trajectory=trajectory,
            start_ns=start_ns,
            end_ns=start_ns + duration_ns,
            frame_stamps_cam_ns=start_ns + frame_offsets,
            imu_stamps_ns=start_ns + imu_offsets,
            gyro_bias0_rad_s=bias_rng.normal(0.0, 0.003, size=3),
            accel_bias0_m_s2=bias_rng.normal(0.0, 0.04, size=3),
            dive_clock=dive_clock,
            gopro_clock=gopro_clock,
        )

    @property
    def scene(self) -> WreckScene:
        """The wreck with its textures (generated on first use: seconds at 5 mm texels)."""
        if self._scene is None:
            self._scene = build_wreck_scene(
                seed=self.options.seed,
                texel_m=self.options.texel_m,
                seafloor_texel_m=self.options.seafloor_texel_m,
                workers=self.options.workers,
            )
        return self._scene

    @property
    def renderer(self) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(self.scene, self.camera, self.options.water)
        return self._renderer

    # ------------------------------------------------------------- truth on demand

    @property
    def timeshift_ns(self) -> int:
        return ns_from_seconds(self.options.timeshift_cam_imu_s)

    def world_from_body(self, session: int, t_ns: npt.ArrayLike) -> FloatArray:
        """(N,4,4) true body poses `T_W_B` at true (IMU-clock) times."""
        return self.sessions[session].trajectory.world_from_body(t_ns)

    def world_from_cam(self, session: int, t_cam_ns: npt.ArrayLike) -> FloatArray:
        """(N,4,4) true camera poses `T_W_C` of images stamped `t_cam_ns` on the camera clock
        (taken at true time t_cam + timeshift)."""
        t = np.atleast_1d(np.asarray(t_cam_ns, dtype=np.int64)) + self.timeshift_ns
        imu_from_cam = self.calibration.imu_from_cam
        return self.world_from_body(session, t) @ imu_from_cam

    def render_frame(
        self, session: int, t_cam_ns: int, *, noise: bool = True, frame_index: int | None = None
    ) -> RenderedFrame:
        """Render the image stamped `t_cam_ns` (camera clock) of `session`.

        The sensor noise is drawn from (seed, session, frame_index or t_cam_ns), so the same
        call gives the same bytes in any process and any order.
        """
        pose = self.world_from_cam(session, [t_cam_ns])[0]
        key = int(t_cam_ns) if frame_index is None else int(frame_index)
        rng = self._rng(_RNG_FRAME, session, key) if noise else None
        return self.renderer.render(pose, rng=rng)

    def imu(self, session: int) -> SimulatedImu:
        """The session's IMU samples (noise and bias walks included)."""
        truth = self.sessions[session]
        return simulate_imu(
            truth.trajectory,
            truth.imu_stamps_ns,
            noise=self.options.imu,
            rng=self._rng(_RNG_IMU, session),
            gyro_bias0_rad_s=truth.gyro_bias0_rad_s,
            accel_bias0_m_s2=truth.accel_bias0_m_s2,
        )

    def dive_profile(self, session: int) -> DiveProfile:
        """The dive computer's log of the session's dive (its own clock)."""
        truth = self.sessions[session]
        return simulate_dive_profile(
            truth.trajectory,
            film_start_ns=truth.start_ns,
            film_end_ns=truth.end_ns,
            clock=truth.dive_clock,
            options=self.options.dive_computer,
            rng=self._rng(_RNG_DIVE, session),
        )

    def truth_document(self) -> dict[str, Any]:
        """The content of truth.json (see `sim`)."""
        opt = self.options
        cam = self.camera
        noise = opt.imu
        sessions = []
        for truth in self.sessions:
            first_cam = int(truth.frame_stamps_cam_ns[0])
            sessions.append(
                {
                    "name": truth.name,
                    "route": truth.route.name,
                    "start_ns": truth.start_ns,
                    "end_ns": truth.end_ns,
                    "frames": len(truth.frame_stamps_cam_ns),
                    "first_frame_cam_ns": first_cam,
                    "world_from_first_body": _matrix(
                        self.world_from_body(truth.index, [first_cam + self.timeshift_ns])[0]
                    ),
                    "world_from_first_cam": _matrix(
                        self.world_from_cam(truth.index, [first_cam])[0]
                    ),
                    "gyro_bias0_rad_s": truth.gyro_bias0_rad_s.tolist(),
                    "accel_bias0_m_s2": truth.accel_bias0_m_s2.tolist(),
                    "clocks": {
                        "imu": "true time (int64 ns since the epoch, UTC)",
                        "cam0": {
                            "relation": "t_true = t_cam + timeshift_cam_imu_s",
                            "timeshift_cam_imu_s": opt.timeshift_cam_imu_s,
                        },
                        "dive_computer": _clock(
                            truth.dive_clock,
                            "t_dc = t_true + offset_ns + drift_ppm*1e-6*(t_true - reference_ns)",
                        ),
                        "gopro": {
                            **_clock(
                                truth.gopro_clock,
                                "creation_time (whole seconds) = t_true + offset_ns + "
                                "drift_ppm*1e-6*(t_true - reference_ns) at frame 0's exposure",
                            ),
                            "media_time_zero_cam_ns": first_cam,
                            "imu_media_time": "t_imu_true - timeshift_ns - media_time_zero_cam_ns",
                            "imu_axes": (
                                f"GoPro IMU axes, ORIN {GOPRO_IMU_AXIS_ORDER!r}; after "
                                "`gopro import`: body frame B of calib/camchain.yaml (as imu0)"
                            ),
                        },
                    },
                    "files": {
                        "euroc": f"{truth.name}/euroc",
                        "dive": f"{truth.name}/dive",
                        "gopro": f"{truth.name}/gopro/GX010001.MP4" if opt.video else None,
                        "trajectory": f"{truth.name}/world_from_body.tum",
                        "depth": f"{truth.name}/depth" if opt.save_depth else None,
                    },
                }
            )
        return {
            "format": TRUTH_FORMAT,
            "version": TRUTH_VERSION,
            "seed": opt.seed,
            "world": {
                "frame": "W: z up, z = 0 at the sea surface, metres",
                "gravity_w_m_s2": GRAVITY_W_M_S2.tolist(),
                "depth_relation": "depth_m = -z_W of the body (IMU) origin",
                "seafloor_z_m": self.scene_seafloor_z_m,
                "mesh": "truth_mesh.ply",
            },
            "targets": [
                {
                    "name": placement.name,
                    "tag_id_offset": placement.target.tag_id_offset,
                    "tag_rows": placement.target.tag_rows,
                    "tag_cols": placement.target.tag_cols,
                    "tag_size_m": placement.target.tag_size_m,
                    "tag_spacing_ratio": placement.target.tag_spacing_ratio,
                    "world_from_target": _matrix(placement.world_from_target),
                    "yaml": f"targets/{placement.name}.yaml",
                }
                for placement in self.scene_targets
            ],
            "camera": {
                "model": list(cam.kalibr_model),
                "width": cam.width,
                "height": cam.height,
                "intrinsics_fx_fy_cx_cy": [cam.fx, cam.fy, cam.cx, cam.cy],
                "distortion_k1_k2_p1_p2": [cam.k1, cam.k2, cam.p1, cam.p2],
                "fps": opt.fps,
                "cam_from_imu": _matrix(self.calibration.cam_from_imu),
                "timeshift_cam_imu_s": opt.timeshift_cam_imu_s,
                "camchain": _SURVEY_CALIB.relative(_SURVEY_CALIB.camchain),
            },
            "imu": {
                "rate_hz": opt.imu_rate_hz,
                "accelerometer_noise_density": noise.accelerometer_noise_density,
                "accelerometer_random_walk": noise.accelerometer_random_walk,
                "gyroscope_noise_density": noise.gyroscope_noise_density,
                "gyroscope_random_walk": noise.gyroscope_random_walk,
                "yaml": _SURVEY_CALIB.relative(_SURVEY_CALIB.imu_yaml),
            },
            "sessions": sessions,
        }

    @property
    def scene_targets(self) -> list[Any]:
        from sim.scene import wreck_targets

        return wreck_targets() if self._scene is None else self._scene.targets

    @property
    def scene_seafloor_z_m(self) -> float:
        from sim.scene import SEAFLOOR_Z_M

        return SEAFLOOR_Z_M if self._scene is None else self._scene.seafloor_z_m


def _matrix(m: FloatArray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(m)]


def _clock(clock: ClockModel, relation: str) -> dict[str, Any]:
    return {
        "relation": relation,
        "offset_ns": clock.offset_ns,
        "drift_ppm": clock.drift_ppm,
        "reference_ns": clock.reference_ns,
    }


# --------------------------------------------------------------------------- writing

_WORKER_SIM: SurveySimulator | None = None


RenderedImages = tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8], npt.NDArray[np.uint16] | None]


def depth_png_mm(depth_m: npt.NDArray[np.float32]) -> npt.NDArray[np.uint16]:
    """Depth (camera z, m) as uint16 millimetres, 0 where nothing is hit or beyond 65.5 m."""
    mm = np.rint(np.where(np.isfinite(depth_m), depth_m, 0.0) * 1000.0)
    mm[(mm < 0) | (mm > 65535)] = 0
    return mm.astype(np.uint16)


def _render_task(task: tuple[int, int, int]) -> RenderedImages:
    session, index, stamp = task
    if _WORKER_SIM is None:
        raise RuntimeError("render worker started without a simulator")
    frame = _WORKER_SIM.render_frame(session, stamp, frame_index=index)
    import cv2

    gray = np.asarray(cv2.cvtColor(frame.image_rgb, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
    depth = depth_png_mm(frame.depth_m) if _WORKER_SIM.options.save_depth else None
    return gray, frame.image_rgb, depth


def _rendered_frames(sim: SurveySimulator, session: int, workers: int, bar: Any) -> Any:
    """Yield (stamp_cam_ns, gray, rgb, depth_mm) of a session in order, rendered by
    `workers` processes."""
    truth = sim.sessions[session]
    tasks = [(session, i, int(s)) for i, s in enumerate(truth.frame_stamps_cam_ns)]
    global _WORKER_SIM
    _WORKER_SIM = sim
    if workers <= 1:
        for task in tasks:
            images = _render_task(task)
            bar.update(1)
            yield (task[2], *images)
        return
    # fork shares the scene's textures and the renderer's tables with the workers without
    # copying them, so build everything before the pool starts.
    sim.renderer.prepare()
    with fork_pool(workers) as pool:
        for task, images in zip(tasks, pool.imap(_render_task, tasks, chunksize=4), strict=True):
            bar.update(1)
            yield (task[2], *images)


def _gopro_payloads(sim: SurveySimulator, session: int, imu: SimulatedImu) -> list[bytes]:
    """One GPMF payload per second of media time (IMU samples on the camera clock)."""
    from field.gopro.cameras import body_from_file_axes
    from field.gopro.writer import encode_gpmf_imu_payload

    # A real camera stores ACCL/GYRO in its IMU chip's axes and says which in ORIN; the
    # importer maps them to its camera-aligned body frame with `body_from_file_axes`.
    # Write the values so that this mapping gives back the simulator's body frame B:
    # the imported session then matches calib/camchain.yaml like the EuRoC copy does.
    body_from_file = body_from_file_axes(GOPRO_IMU_AXIS_ORDER)
    truth = sim.sessions[session]
    fps = Fraction(sim.options.fps).limit_denominator(1001)
    per_s = Fraction(round(fps)) / fps
    media_ns = imu.stamps_ns - sim.timeshift_ns - int(truth.frame_stamps_cam_ns[0])
    n_frames = len(truth.frame_stamps_cam_ns)
    n_payloads = int(np.ceil(n_frames / round(fps)))
    payloads = []
    total = 0
    for p in range(n_payloads):
        # Payload p covers media time [p, p + 1) * per_s; ceil keeps the bounds exact in ns.
        lo = math.ceil(p * per_s * NS_PER_S)
        hi = math.ceil((p + 1) * per_s * NS_PER_S)
        # Samples before the first frame (media time < 0) are not in the file, as on a camera.
        pick = np.flatnonzero((media_ns >= lo) & (media_ns < hi))
        first_us = int(media_ns[pick[0]] // 1000) if len(pick) else int(lo // 1000)
        payloads.append(
            encode_gpmf_imu_payload(
                accl_mps2=imu.accel_m_s2[pick] @ body_from_file,
                gyro_rads=imu.gyro_rad_s[pick] @ body_from_file,
                accl_first_us=first_us,
                gyro_first_us=first_us,
                accl_total_before=total,
                gyro_total_before=total,
                orientation_in=GOPRO_IMU_AXIS_ORDER,
                orientation_out=GOPRO_IMU_AXIS_ORDER,
            )
        )
        total += len(pick)
    return payloads


def write_session(sim: SurveySimulator, session: int, folder: Path, bar: Any) -> None:
    """Write one session's EuRoC folder, dive folder, TUM truth and (optionally) GoPro MP4
    and depth maps."""
    import cv2

    from shared.formats.diveprofile import write_dive
    from shared.formats.euroc import EurocWriter
    from shared.formats.tum import write_tum
    from shared.trajectory import Trajectory

    opt = sim.options
    truth = sim.sessions[session]
    imu = sim.imu(session)
    folder.mkdir(parents=True, exist_ok=True)
    depth_dir = folder / "depth"
    fps = Fraction(opt.fps).limit_denominator(1001)
    stream = None
    with EurocWriter(folder / "euroc", camera=sim.calibration, imu_noise=opt.imu) as euroc:

        def colour_frames() -> Iterator[npt.NDArray[np.uint8]]:
            # Each frame goes to disk (EuRoC) and to the encoder as it is rendered:
            # holding a long dive's frames would take 1.5 MB each at 960x540.
            for stamp, gray, rgb, depth_mm in _rendered_frames(sim, session, opt.workers, bar):
                euroc.add_image(stamp, gray)
                if depth_mm is not None:
                    depth_dir.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(depth_dir / f"{stamp}.png"), depth_mm)
                yield rgb

        if opt.video:
            from field.gopro.writer import encode_h264

            stream = encode_h264(
                colour_frames(), fps=fps, gop_frames=max(round(fps), 1), crf=opt.video_crf
            )
        else:
            for _ in colour_frames():
                pass
        euroc.add_imu(imu.stamps_ns, imu.gyro_rad_s, imu.accel_m_s2)
        poses = truth.trajectory.world_from_body(imu.stamps_ns)
        euroc.set_groundtruth(
            Trajectory(stamps_ns=imu.stamps_ns, poses=poses),
            truth.trajectory.velocity_m_s(imu.stamps_ns),
            imu.gyro_bias_rad_s,
            imu.accel_bias_m_s2,
        )
    write_tum(folder / "world_from_body.tum", Trajectory(stamps_ns=imu.stamps_ns, poses=poses))
    write_dive(folder / "dive", sim.dive_profile(session))
    if stream is not None:
        from field.gopro.writer import write_gopro_mp4

        first_true = int(truth.frame_stamps_cam_ns[0]) + sim.timeshift_ns
        created_ns = truth.gopro_clock.apply(first_true)
        write_gopro_mp4(
            folder / "gopro" / "GX010001.MP4",
            video_packets=stream.packets,
            sps=stream.sps,
            pps=stream.pps,
            width=stream.width,
            height=stream.height,
            fps=fps,
            keyframe_flags=stream.keyframes,
            gpmf_payloads=_gopro_payloads(sim, session, imu),
            creation_time=datetime.fromtimestamp(created_ns // NS_PER_S, tz=UTC),
        )


def run(options: SurveyOptions, out_dir: Path | str, *, overwrite: bool = False) -> Path:
    """Simulate a survey into `out_dir` (layout in `sim`); returns `out_dir`.

    Refuses an existing non-empty `out_dir` unless `overwrite`; everything is written
    under a temporary name and renamed into place when complete.
    """
    from shared.calibration.kalibr import write_target_yaml
    from shared.fsutil import atomic_path, write_text_atomic
    from shared.progress import progress_bar

    out = Path(out_dir)
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()  # an empty folder holds nothing to protect
    elif out.exists() and not overwrite:
        raise OutputExistsError(f"{out}: already exists (refusing to overwrite a survey)")
    sim = SurveySimulator(options)
    total = sum(len(s.frame_stamps_cam_ns) for s in sim.sessions)
    with atomic_path(out, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        scene = sim.scene
        write_ply(tmp / "truth_mesh.ply", scene_mesh(scene))
        for placement in scene.targets:
            write_target_yaml(tmp / "targets" / f"{placement.name}.yaml", placement.target)
        calib = SessionFolder(tmp)  # a session's calib/ layout (_SURVEY_CALIB)
        calib.write_camchain([sim.calibration])
        calib.write_imu_noise(options.imu)
        bar = progress_bar(total=total, desc="sim survey", unit="frame")
        try:
            for k in range(len(sim.sessions)):
                write_session(sim, k, tmp / sim.sessions[k].name, bar)
        finally:
            bar.close()
        write_text_atomic(tmp / "truth.json", json.dumps(sim.truth_document(), indent=2) + "\n")
    return out
