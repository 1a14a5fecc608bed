"""A simulated OAK-like rig: rendered, encoded camera frames, IMU and depth in real time.

The frames come from the survey simulator (`sim`: the wreck scene rendered through
the camera model along a diver trajectory) and the IMU from its IMU synthesis on the same
trajectory, so images and IMU agree. Rendering is far slower than real time, so a clip of
`clip_s` seconds is rendered and encoded once (H.264/H.265 with PyAV's libx264/libx265,
or JPEG with OpenCV), cached as an MCAP file, and replayed in a loop paced by the wall
clock. The trajectory jumps back at each loop, like a diver teleported to the start.

Time: the rig's device clock counts ns since its "boot" and runs `clock_drift_ppm` fast,
like an OAK's; `SourceSample.device_ns` is that reading, `message.stamp_ns` the same clock
moved to the epoch (`DeviceClockMapper`), `host_sync_ns` a DepthAI-like host-clock estimate
of the capture time, `receive_ns` the host clock when the sample is handed over.

Fault injection (for tests of the recorder): `camera_unplug_at_s` / `camera_unplug_for_s`
stop the camera streams for a while (IMU and depth go on); `device_lost_at_s` /
`device_lost_for_s` make the whole device disappear (`read` and `open` raise DeviceError).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from field.record.hostclock import host_now_ns
from field.record.sources.base import SourceSample, StreamInfo, register_source
from field.record.timing import DeviceClockMapper
from shared.archive import (
    ArchiveReader,
    ArchiveWriter,
    CompressedImage,
    CompressedVideo,
    DepthSample,
    Imu,
    depth_topic,
    image_topic,
    imu_topic,
    video_topic,
)
from shared.clock import NS_PER_S, ClockModel, ns_from_seconds, seconds_from_ns
from shared.errors import DeviceError, InputError

log = logging.getLogger(__name__)

CLIP_FORMAT_VERSION = 1
P_SURFACE_PA = 101_325.0
RHO_SALT = 1025.0
G = 9.80665
# Latency from capture to the host (encode + USB), like an OAK at these settings.
VIDEO_LATENCY_NS = 30_000_000
IMU_LATENCY_NS = 3_000_000
DEPTH_LATENCY_NS = 10_000_000
MAX_SAMPLES_PER_READ = 4000


@dataclass(kw_only=True)
class SimOptions:
    """The simulated rig.

    cameras: 1 (mono/colour) or 2 (stereo pair, `baseline_m` apart); width_px, height_px:
    output image size; render_scale: render at size / scale and upscale (integer; keeps the
    camera model exact), fps: frame rate (Hz); codec: "h264", "h265" or "mjpeg";
    bitrate_kbps: video bit rate; keyframe_interval: frames per group of pictures;
    jpeg_quality: 0-100 for mjpeg; noise_dn: sensor noise added after upscaling (grey levels);
    imu_rate_hz: IMU rate; depth_rate_hz: pressure-sensor rate (0: none); clip_s: rendered
    seconds replayed in a loop; seed: scene and trajectory; clock_drift_ppm: device clock rate
    error; boot_s_ago: device uptime at start (s); texel_mm: texture resolution on the wreck
    (mm; coarser builds the scene faster); cache_dir: where clips are cached
    (default $WRECKMAP_CACHE or ~/.cache/wreckmap); faults: see the module docstring (s
    since `open`).
    """

    cameras: int = 1
    width_px: int = 640
    height_px: int = 400
    render_scale: int = 2
    fps: float = 30.0
    codec: str = "h264"
    bitrate_kbps: int = 4000
    keyframe_interval: int = 15
    jpeg_quality: int = 85
    noise_dn: float = 2.0
    imu_rate_hz: float = 400.0
    depth_rate_hz: float = 4.0
    clip_s: float = 2.0
    seed: int = 1
    clock_drift_ppm: float = 25.0
    boot_s_ago: float = 120.0
    baseline_m: float = 0.075
    texel_mm: float = 10.0
    cache_dir: str | None = None
    camera_unplug_at_s: float | None = None
    camera_unplug_for_s: float = 1.0
    device_lost_at_s: float | None = None
    device_lost_for_s: float = 1.0

    def __post_init__(self) -> None:
        if self.cameras not in (1, 2):
            raise ValueError(f"cameras must be 1 or 2, got {self.cameras}")
        if self.codec not in ("h264", "h265", "mjpeg"):
            raise ValueError(f"codec must be h264, h265 or mjpeg, got {self.codec!r}")
        if (
            self.render_scale < 1
            or self.width_px % self.render_scale
            or (self.height_px % self.render_scale)
        ):
            raise ValueError(
                f"render_scale {self.render_scale} must divide {self.width_px}x{self.height_px}"
            )
        rw, rh = self.width_px // self.render_scale, self.height_px // self.render_scale
        if rw < 16 or rh < 16 or rw % 2 or rh % 2:
            raise ValueError(f"render size {rw}x{rh} must be even and at least 16x16")
        if not 0 < self.fps <= 120:
            raise ValueError(f"fps must be in (0, 120], got {self.fps}")
        if not 50 <= self.imu_rate_hz <= 1000:
            raise ValueError(f"imu_rate_hz must be in [50, 1000], got {self.imu_rate_hz}")
        if not 1.0 <= self.texel_mm <= 200.0:
            raise ValueError(f"texel_mm must be in [1, 200], got {self.texel_mm}")
        if self.clip_s <= 0 or self.keyframe_interval < 1:
            raise ValueError("clip_s and keyframe_interval must be positive")

    def clip_key(self) -> str:
        """Hash of everything that changes the rendered clip (names its cache file)."""
        keys = [
            "cameras",
            "width_px",
            "height_px",
            "render_scale",
            "fps",
            "codec",
            "bitrate_kbps",
            "keyframe_interval",
            "jpeg_quality",
            "noise_dn",
            "imu_rate_hz",
            "depth_rate_hz",
            "clip_s",
            "seed",
            "baseline_m",
            "texel_mm",
        ]
        values = {k: asdict(self)[k] for k in keys}
        values["version"] = CLIP_FORMAT_VERSION
        text = json.dumps(values, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


SMALL_RIG: dict[str, Any] = {
    "width_px": 320,
    "height_px": 200,
    "render_scale": 2,
    "fps": 15.0,
    "keyframe_interval": 5,
    "bitrate_kbps": 800,
    "clip_s": 2.0,
    "texel_mm": 40.0,  # coarse textures: the scene builds in well under a second
}
"""SimOptions of a small rig for tests and fault benchmarks: 320x200 frames rendered at
160x100, 15 fps, the default 400 Hz IMU and 4 Hz depth; renders in seconds."""


def default_cache_dir() -> Path:
    env = os.environ.get("WRECKMAP_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "wreckmap"


def clip_path(options: SimOptions) -> Path:
    """Where the clip for `options` is cached."""
    folder = Path(options.cache_dir) if options.cache_dir else default_cache_dir()
    return folder / f"sim-clip-{options.clip_key()}.mcap"


def _survey(options: SimOptions) -> Any:
    from sim.survey import SurveyOptions, SurveySimulator

    return SurveySimulator(
        SurveyOptions(
            sessions=1,
            duration_s=options.clip_s,
            seed=options.seed,
            width=options.width_px // options.render_scale,
            height=options.height_px // options.render_scale,
            fps=options.fps,
            video=False,
            imu_rate_hz=options.imu_rate_hz,
            texel_m=options.texel_mm * 1e-3,
            seafloor_texel_m=max(3 * options.texel_mm * 1e-3, 0.03),
        )
    )


def _cam0_from_cam1(baseline_m: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = baseline_m  # camera 1 sits to the right of camera 0
    return pose


class _VideoEncoder:
    """H.264/H.265 Annex B packets (libx264/libx265 through PyAV) or JPEG (OpenCV)."""

    def __init__(self, options: SimOptions) -> None:
        self.options = options
        self._ctx: Any = None
        if options.codec != "mjpeg":
            import av

            name = "libx264" if options.codec == "h264" else "libx265"
            ctx: Any = av.CodecContext.create(name, "w")
            ctx.width, ctx.height = options.width_px, options.height_px
            ctx.pix_fmt = "yuv420p"
            rate = Fraction(options.fps).limit_denominator(1001)
            ctx.time_base = 1 / rate
            ctx.framerate = rate
            ctx.bit_rate = options.bitrate_kbps * 1000
            gop = options.keyframe_interval
            # In-band parameter sets before every key frame, no B-frames: what a live
            # camera encoder emits, decodable from any key frame on.
            params = f"keyint={gop}:min-keyint={gop}:scenecut=0:bframes=0:repeat-headers=1"
            if options.codec == "h264":
                ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "x264-params": params}
            else:
                ctx.options = {
                    "preset": "ultrafast",
                    "tune": "zerolatency",
                    "x265-params": params + ":log-level=error",
                }
            self._ctx = ctx

    def encode(self, rgb: np.ndarray, index: int) -> list[tuple[bytes, bool]]:
        if self._ctx is None:
            import cv2

            ok, jpeg = cv2.imencode(
                ".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, self.options.jpeg_quality]
            )
            if not ok:
                raise DeviceError("simulated camera: JPEG encoding failed")
            return [(jpeg.tobytes(), True)]
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame = frame.reformat(format="yuv420p")
        frame.pts = index
        return [(bytes(p), bool(p.is_keyframe)) for p in self._ctx.encode(frame)]

    def flush(self) -> list[tuple[bytes, bool]]:
        if self._ctx is None:
            return []
        return [(bytes(p), bool(p.is_keyframe)) for p in self._ctx.encode(None)]


def prepare_clip(options: SimOptions) -> Path:
    """Render, encode and cache the clip for `options` (no-op when cached); its path.

    Takes seconds to minutes (the renderer runs on the CPU); the cache file is written
    atomically, so concurrent preparations only waste time.
    """
    path = clip_path(options)
    if path.is_file():
        return path
    import cv2

    from shared.progress import progress_bar

    path.parent.mkdir(parents=True, exist_ok=True)
    sim = _survey(options)
    truth = sim.sessions[0]
    stamps = truth.frame_stamps_cam_ns
    start_ns = int(truth.start_ns)
    encoders = [_VideoEncoder(options) for _ in range(options.cameras)]
    rng = np.random.default_rng([options.seed, 77])
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    cam0_from_cam1 = _cam0_from_cam1(options.baseline_m)
    log.info("simulated rig: rendering a %.1f s clip once (cached in %s)", options.clip_s, path)
    bar = progress_bar(total=len(stamps), desc="render sim clip", unit="frame")
    # Offsets from the clip start: the clip archive is time-relative (0 = clip start).
    with ArchiveWriter(tmp, overwrite=True, compression="none") as writer:
        pending: list[list[int]] = [[] for _ in range(options.cameras)]
        for i, t_cam in enumerate(stamps):
            world_from_cam0 = sim.world_from_cam(0, [int(t_cam)])[0]
            for cam in range(options.cameras):
                pose = world_from_cam0 if cam == 0 else world_from_cam0 @ cam0_from_cam1
                frame_rng = np.random.default_rng([options.seed, 78, cam, i])
                rgb = sim.renderer.render(pose, rng=frame_rng).image_rgb
                if options.render_scale > 1:
                    rgb = cv2.resize(
                        rgb, (options.width_px, options.height_px), interpolation=cv2.INTER_LINEAR
                    )
                if options.noise_dn > 0:
                    noise = rng.normal(0.0, options.noise_dn, rgb.shape)
                    rgb = np.clip(rgb + noise, 0, 255).astype(np.uint8)
                pending[cam].append(int(t_cam) - start_ns)
                for data, key in encoders[cam].encode(rgb, i):
                    _write_frame(writer, options, cam, pending[cam].pop(0), data, key)
            bar.update(1)
        for cam in range(options.cameras):
            for data, key in encoders[cam].flush():
                _write_frame(writer, options, cam, pending[cam].pop(0), data, key)
        bar.close()
        imu = sim.imu(0)
        n_imu = round(options.clip_s * options.imu_rate_hz)  # one loop, no duplicate end sample
        for k in range(min(n_imu, len(imu.stamps_ns))):
            writer.write(
                imu_topic(0),
                Imu(
                    stamp_ns=int(imu.stamps_ns[k]) - start_ns,
                    frame_id="imu0",
                    angular_velocity_rad_s=np.asarray(imu.gyro_rad_s[k], dtype=np.float64),
                    linear_acceleration_m_s2=np.asarray(imu.accel_m_s2[k], dtype=np.float64),
                ),
            )
        if options.depth_rate_hz > 0:
            n_depth = max(round(options.clip_s * options.depth_rate_hz), 1)
            offsets = np.round(np.arange(n_depth) * NS_PER_S / options.depth_rate_hz).astype(
                np.int64
            )
            z = sim.world_from_body(0, start_ns + offsets)[:, 2, 3]
            for off, z_m in zip(offsets, z, strict=True):
                depth = max(-float(z_m), 0.0)  # world z is 0 at the surface, up
                writer.write(
                    depth_topic(0),
                    DepthSample(
                        stamp_ns=int(off),
                        frame_id="depth0",
                        depth_m=depth,
                        pressure_pa=P_SURFACE_PA + RHO_SALT * G * depth,
                        temperature_c=14.0,
                    ),
                )
        writer.add_metadata("sim_clip", {"key": options.clip_key(), "start_ns": str(start_ns)})
    tmp.replace(path)
    return path


def _write_frame(
    writer: ArchiveWriter, options: SimOptions, cam: int, offset_ns: int, data: bytes, key: bool
) -> None:
    if options.codec == "mjpeg":
        writer.write(image_topic(cam), CompressedImage(offset_ns, f"cam{cam}", "jpeg", data))
    else:
        # The keyframe flag travels in frame_id's suffix only inside the cache file.
        frame_id = f"cam{cam}" + ("#key" if key else "")
        writer.write(video_topic(cam), CompressedVideo(offset_ns, frame_id, options.codec, data))


@dataclass
class _Track:
    """One stream of the clip: sample offsets (ns from clip start) and messages."""

    topic: str
    latency_ns: int
    offsets_ns: np.ndarray
    items: list[Any]
    keyframes: list[bool]
    camera: bool
    next_index: int = 0  # absolute index over loops


@register_source("sim")
class SimSource:
    """The simulated OAK-like rig (see the module docstring). Options: `SimOptions`."""

    name = "sim"
    options_type = SimOptions

    def __init__(self, options: SimOptions) -> None:
        self.options = options
        self._tracks: list[_Track] = []
        self._clip_ns = ns_from_seconds(options.clip_s)
        self._opened_at_ns: int | None = None
        self._start_true_ns = 0
        self._device_clock: ClockModel | None = None
        self._mapper = DeviceClockMapper()
        self._is_open = False
        self._camera_down_logged = False

    # -- CameraSource --------------------------------------------------------------

    def streams(self) -> list[StreamInfo]:
        o = self.options
        result = []
        for cam in range(o.cameras):
            topic = image_topic(cam) if o.codec == "mjpeg" else video_topic(cam)
            kind = "image" if o.codec == "mjpeg" else "video"
            codec = "jpeg" if o.codec == "mjpeg" else o.codec
            result.append(StreamInfo(topic, kind, o.fps, codec, o.width_px, o.height_px, "sim-rig"))
        result.append(StreamInfo(imu_topic(0), "imu", o.imu_rate_hz, device="sim-rig"))
        if o.depth_rate_hz > 0:
            result.append(StreamInfo(depth_topic(0), "depth", o.depth_rate_hz, device="sim-rig"))
        return result

    def open(self) -> None:
        if self._opened_at_ns is None:
            self._load_clip()  # seconds to minutes the first time (rendering)
            now = host_now_ns()
            self._opened_at_ns = now
            # Device clock: ns since boot, running drift_ppm fast (true time = host epoch here).
            boot_ns = now - ns_from_seconds(self.options.boot_s_ago)
            self._device_clock = ClockModel(
                offset_ns=-boot_ns, drift_ppm=self.options.clock_drift_ppm, reference_ns=boot_ns
            )
            self._start_true_ns = now + 20_000_000
        now = host_now_ns()
        if self._in_fault(now, "device_lost"):
            raise DeviceError("simulated rig: device not found (simulated unplug)")
        # A real device restarts its stream where the present is: skip what was missed.
        for track in self._tracks:
            track.next_index = max(track.next_index, self._index_at(track, now))
        self._mapper.reset()
        self._is_open = True

    def read(self, timeout_s: float) -> list[SourceSample]:
        if not self._is_open:
            raise DeviceError("simulated rig: read before open")
        deadline = host_now_ns() + ns_from_seconds(timeout_s)
        while True:
            now = host_now_ns()
            if self._in_fault(now, "device_lost"):
                self._is_open = False
                raise DeviceError("simulated rig: device lost (simulated unplug)")
            samples = self._due(now)
            if samples:
                return samples
            wake = min(self._due_time(t, t.next_index) for t in self._tracks)
            if now >= deadline:
                return []
            time.sleep(seconds_from_ns(max(min(wake, deadline) - now, 0)) + 0.0002)

    def close(self) -> None:
        self._is_open = False

    def describe(self) -> dict[str, Any]:
        o = self.options
        return {
            "kind": "sim",
            "model": "simulated OAK-like rig (sim renderer + IMU synthesis)",
            "serial": f"SIM-{o.seed:04d}",
            "settings": asdict(o),
            "clock": {
                "name": "sim_device",
                "description": "device clock (ns since boot) moved to the epoch by one "
                "offset fixed at the first sample; runs clock_drift_ppm fast",
                "true_drift_ppm": o.clock_drift_ppm,
            },
        }

    def calibration(self) -> tuple[list[Any], Any] | None:
        from shared.calibration.kalibr import CameraCalibration
        from sim.survey import default_cam_from_imu, default_camera, default_imu_noise

        o = self.options
        cam0_from_imu = default_cam_from_imu()
        cams = []
        for cam in range(o.cameras):
            cam_from_imu = (
                cam0_from_imu
                if cam == 0
                else np.linalg.inv(_cam0_from_cam1(o.baseline_m)) @ cam0_from_imu
            )
            topic = image_topic(cam) if o.codec == "mjpeg" else video_topic(cam)
            cams.append(
                CameraCalibration(
                    camera=default_camera(o.width_px, o.height_px),
                    cam_from_imu=cam_from_imu,
                    timeshift_cam_imu_s=0.0125,
                    topic=topic,
                    name=f"cam{cam}",
                    cam_overlaps=[1 - cam] if o.cameras == 2 else [],
                )
            )
        return cams, default_imu_noise(o.imu_rate_hz)

    # -- internals -----------------------------------------------------------------

    def _load_clip(self) -> None:
        path = prepare_clip(self.options)
        tracks: dict[str, _Track] = {}
        try:
            with ArchiveReader(path) as reader:
                for topic, _, msg in reader.messages():
                    track = tracks.get(topic)
                    if track is None:
                        is_cam = topic.startswith("/cam")
                        latency = (
                            VIDEO_LATENCY_NS
                            if is_cam
                            else IMU_LATENCY_NS
                            if topic.startswith("/imu")
                            else DEPTH_LATENCY_NS
                        )
                        track = tracks[topic] = _Track(topic, latency, np.zeros(0), [], [], is_cam)
                    track.items.append(msg)
                    frame_id = getattr(msg, "frame_id", "")
                    track.keyframes.append(
                        not isinstance(msg, CompressedVideo) or frame_id.endswith("#key")
                    )
                    if isinstance(msg, CompressedVideo):
                        msg.frame_id = frame_id.removesuffix("#key")
        except InputError as error:
            raise DeviceError(f"simulated rig: cached clip {path} unreadable ({error})") from None
        for track in tracks.values():
            track.offsets_ns = np.array([m.stamp_ns for m in track.items], dtype=np.int64)
        self._tracks = sorted(tracks.values(), key=lambda t: t.topic)

    def _due_time(self, track: _Track, index: int) -> int:
        """Host time at which sample `index` (over loops) of `track` is handed over."""
        loop, k = divmod(index, len(track.items))
        return (
            self._start_true_ns + loop * self._clip_ns + int(track.offsets_ns[k]) + track.latency_ns
        )

    def _index_at(self, track: _Track, now_ns: int) -> int:
        elapsed = now_ns - self._start_true_ns - track.latency_ns
        if elapsed < 0:
            return 0
        loop, rest = divmod(elapsed, self._clip_ns)
        k = int(np.searchsorted(track.offsets_ns, rest, side="right"))
        index = loop * len(track.items) + k
        if track.camera and self.options.codec != "mjpeg":
            # Resume at a key frame: the decoder needs one after a gap.
            while not track.keyframes[index % len(track.items)]:
                index += 1
        return int(index)

    def _in_fault(self, now_ns: int, kind: str) -> bool:
        o = self.options
        at = o.device_lost_at_s if kind == "device_lost" else o.camera_unplug_at_s
        length = o.device_lost_for_s if kind == "device_lost" else o.camera_unplug_for_s
        if at is None or self._opened_at_ns is None:
            return False
        t = seconds_from_ns(now_ns - self._opened_at_ns)
        return at <= t < at + length

    def _due(self, now_ns: int) -> list[SourceSample]:
        if self._device_clock is None:
            raise DeviceError("simulated rig: not opened")
        out: list[SourceSample] = []
        camera_down = self._in_fault(now_ns, "camera_unplug")
        if camera_down != self._camera_down_logged:
            self._camera_down_logged = camera_down
            if camera_down:
                log.warning("simulated rig: cameras unplugged (IMU and depth go on)")
            else:
                log.warning("simulated rig: cameras back")
                for track in self._tracks:
                    if track.camera:
                        track.next_index = max(track.next_index, self._index_at(track, now_ns))
        for track in self._tracks:
            n = len(track.items)
            while len(out) < MAX_SAMPLES_PER_READ:
                due = self._due_time(track, track.next_index)
                if due > now_ns:
                    break
                index = track.next_index
                track.next_index += 1
                if track.camera and camera_down:
                    continue
                k = index % n
                true_ns = due - track.latency_ns
                device_ns = self._device_clock.apply(true_ns)
                # Anchor the epoch offset on the capture-time estimate, as for the OAK.
                stamp_ns = self._mapper.to_epoch(device_ns, true_ns)
                template = track.items[k]
                message = _restamp(template, stamp_ns)
                out.append(
                    SourceSample(
                        topic=track.topic,
                        message=message,
                        receive_ns=now_ns,
                        device_ns=device_ns,
                        host_sync_ns=true_ns,
                        keyframe=track.keyframes[k],
                    )
                )
        out.sort(key=lambda s: s.message.stamp_ns)
        return out


def _restamp(template: Any, stamp_ns: int) -> Any:
    if isinstance(template, Imu):
        return Imu(
            stamp_ns=stamp_ns,
            frame_id=template.frame_id,
            angular_velocity_rad_s=template.angular_velocity_rad_s,
            linear_acceleration_m_s2=template.linear_acceleration_m_s2,
        )
    if isinstance(template, CompressedVideo):
        return CompressedVideo(stamp_ns, template.frame_id, template.format, template.data)
    if isinstance(template, CompressedImage):
        return CompressedImage(stamp_ns, template.frame_id, template.format, template.data)
    return DepthSample(
        stamp_ns=stamp_ns,
        frame_id=template.frame_id,
        depth_m=template.depth_m,
        pressure_pa=template.pressure_pa,
        temperature_c=template.temperature_c,
    )
