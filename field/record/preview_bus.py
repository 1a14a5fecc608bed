"""Live preview over zenoh: thumbnails, IMU summary, depth and recorder health.

Keys (all under `wreckmap/<rig>/<session>/`):

| key             | payload                                                        |
|-----------------|----------------------------------------------------------------|
| `camN/thumb`    | JPEG thumbnail (attachment: JSON `{"stamp_ns", "width", ...}`) |
| `imuN/summary`  | JSON: decimated gyro (rad/s) and accel (m/s^2) since the last  |
| `depthN`        | JSON: depth_m, pressure_pa, temperature_c, stamp_ns            |
| `health`        | JSON: disk free, rates, drops, queue, sources, events          |

Read-only by construction: the recorder's zenoh session declares publishers only (no
subscriber, queryable or query), so nothing put on the bus can reach the recorder.
Thumbnails are decoded from key frames only (an H.264 IDR decodes on its own), so the
preview never decodes the whole stream; their rate is at most the key-frame rate.

Network: loopback by default (listen on tcp/127.0.0.1:7447, multicast scouting off); a
LAN endpoint is opt-in; TLS and access control come from a zenoh config file
(deploy/zenoh/).
"""

from __future__ import annotations

import collections
import json
import logging
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from field.record.sources.base import SourceSample
from shared.archive import CompressedImage, CompressedVideo, DepthSample, Imu
from shared.clock import NS_PER_S, seconds_from_ns
from shared.errors import DeviceError, InputError

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(kw_only=True)
class PreviewOptions:
    """The preview publisher.

    listen: zenoh endpoints to listen on (default loopback only); connect: endpoints to
    connect to (a router); config_file: a zenoh JSON5 config (TLS, access control) loaded
    first, the endpoints above then override its listen/connect; thumbnail_hz: thumbnails
    per second per camera (at most the key-frame rate); thumbnail_width_px: thumbnail
    width; jpeg_quality: 0-100; imu_summary_hz: IMU summaries per second; imu_plot_hz:
    IMU samples per second kept in the summaries (decimation).
    """

    listen: list[str] = field(default_factory=lambda: [DEFAULT_ENDPOINT])
    connect: list[str] = field(default_factory=list)
    config_file: str | None = None
    thumbnail_hz: float = 2.0
    thumbnail_width_px: int = 320
    jpeg_quality: int = 70
    imu_summary_hz: float = 10.0
    imu_plot_hz: float = 50.0


def key_part(name: str) -> str:
    """`name` made safe as one zenoh key chunk (no '/', '*', '$', '#', '?', spaces)."""
    cleaned = re.sub(r"[^A-Za-z0-9_.\-]", "_", name).strip("_")
    return cleaned or "unnamed"


def key_prefix(rig: str, session: str) -> str:
    """`wreckmap/<rig>/<session>`."""
    return f"wreckmap/{key_part(rig)}/{key_part(session)}"


def zenoh_config(
    *, listen: list[str], connect: list[str], config_file: str | None = None, mode: str = "peer"
) -> Any:
    """A zenoh Config: explicit endpoints, multicast scouting off (nothing is found by
    accident on the boat's network), optional file for TLS / access control."""
    import zenoh

    if config_file:
        path = Path(config_file)
        if not path.is_file():
            raise InputError(f"{path}: zenoh config file not found")
        try:
            config = zenoh.Config.from_file(str(path))
        except zenoh.ZError as error:
            raise InputError(f"{path}: not a valid zenoh config ({error})") from None
    else:
        config = zenoh.Config()
    for endpoint in [*listen, *connect]:
        if not re.fullmatch(r"(tcp|udp|tls|quic|ws|unixsock-stream)/\S+", endpoint):
            raise InputError(
                f"zenoh endpoint {endpoint!r}: expected PROTOCOL/ADDRESS, e.g. {DEFAULT_ENDPOINT}"
            )
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("listen/endpoints", json.dumps(listen))
    config.insert_json5("connect/endpoints", json.dumps(connect))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def thumbnail_jpeg(
    data: bytes, codec: str, *, width_px: int, quality: int
) -> tuple[bytes, int, int] | None:
    """A JPEG thumbnail (bytes, width, height) of one key frame (H.264/H.265 access unit
    with in-band parameter sets, or a JPEG); None when it does not decode."""
    import cv2

    image: np.ndarray | None
    if codec in ("jpeg", "jpg", "mjpeg"):
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_COLOR_2)
    else:
        import av

        try:
            ctx = av.CodecContext.create("hevc" if codec in ("h265", "hevc") else "h264", "r")
            frames = list(ctx.decode(av.Packet(data))) + list(ctx.decode(None))
        except av.FFmpegError:
            return None
        if not frames:
            return None
        image = frames[0].to_ndarray(format="bgr24")
    if image is None or image.size == 0:
        return None
    h, w = image.shape[:2]
    out_w = min(width_px, w)
    out_h = max(1, round(h * out_w / w))
    small = cv2.resize(image, (out_w, out_h), interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return (jpeg.tobytes(), out_w, out_h) if ok else None


class PreviewPublisher:
    """Publishes the preview of a recording (see the module docstring).

    `offer` and `publish_health` are called by the recorder and never block: they keep
    the latest key frame per camera, a bounded window of IMU samples and the latest
    depth and health; a background thread encodes and publishes them.
    """

    def __init__(self, options: PreviewOptions, *, rig: str, session: str) -> None:
        self.options = options
        self.prefix = key_prefix(rig, session)
        self._lock = threading.Lock()
        self._frames: dict[str, SourceSample] = {}
        self._last_frame_ns: dict[str, int] = {}
        self._imu: dict[str, collections.deque[tuple[int, np.ndarray, np.ndarray]]] = {}
        self._depth: dict[str, DepthSample] = {}
        self._health: dict[str, Any] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._session: Any = None
        self._publishers: dict[str, Any] = {}
        self._thread: threading.Thread | None = None
        self.published: collections.Counter[str] = collections.Counter()

    def start(self) -> None:
        """Open the zenoh session (DeviceError when the endpoint cannot be used)."""
        import zenoh

        o = self.options
        config = zenoh_config(listen=o.listen, connect=o.connect, config_file=o.config_file)
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as error:
            raise DeviceError(
                f"preview: cannot open zenoh on {', '.join(o.listen + o.connect)} ({error})"
            ) from None
        self._thread = threading.Thread(target=self._loop, name="preview", daemon=True)
        self._thread.start()
        log.info("preview on %s under %s/**", ", ".join(o.listen + o.connect), self.prefix)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._session is not None:
            self._session.close()
            self._session = None

    # -- called by the recorder (non-blocking) -------------------------------------

    def offer(self, sample: SourceSample) -> None:
        message = sample.message
        topic = sample.topic
        if isinstance(message, CompressedVideo | CompressedImage):
            if not sample.keyframe and isinstance(message, CompressedVideo):
                return
            period_ns = NS_PER_S / self.options.thumbnail_hz
            if sample.receive_ns - self._last_frame_ns.get(topic, 0) < period_ns:
                return
            self._last_frame_ns[topic] = sample.receive_ns
            with self._lock:
                self._frames[topic] = sample
            self._wake.set()
        elif isinstance(message, Imu):
            window = self._imu.get(topic)
            if window is None:
                with self._lock:
                    window = self._imu.setdefault(topic, collections.deque(maxlen=4000))
            window.append(
                (message.stamp_ns, message.angular_velocity_rad_s, message.linear_acceleration_m_s2)
            )
        elif isinstance(message, DepthSample):
            with self._lock:
                self._depth[topic] = message

    def publish_health(self, health: dict[str, Any]) -> None:
        with self._lock:
            self._health = health
        self._wake.set()

    # -- background ------------------------------------------------------------------

    def _put(
        self, key: str, payload: bytes, *, encoding: str, attachment: bytes | None = None
    ) -> None:
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self._session.declare_publisher(
                f"{self.prefix}/{key}"
            )
        if attachment is None:
            publisher.put(payload, encoding=encoding)
        else:
            publisher.put(payload, encoding=encoding, attachment=attachment)
        self.published[key] += 1

    def _loop(self) -> None:
        o = self.options
        next_imu = time.monotonic()
        while not self._stop.is_set():
            self._wake.wait(0.02)
            self._wake.clear()
            try:
                self._publish_frames()
                if time.monotonic() >= next_imu:
                    next_imu = time.monotonic() + 1.0 / o.imu_summary_hz
                    self._publish_imu()
                    self._publish_depth()
                with self._lock:
                    health, self._health = self._health, None
                if health is not None:
                    self._put("health", json.dumps(health).encode(), encoding="application/json")
            except Exception:  # the preview must never take the recording down
                log.exception("preview: publishing failed")
                time.sleep(0.5)

    def _publish_frames(self) -> None:
        with self._lock:
            frames, self._frames = self._frames, {}
        for topic, sample in frames.items():
            message = sample.message
            codec = message.format  # type: ignore[union-attr]
            thumb = thumbnail_jpeg(
                message.data,  # type: ignore[union-attr]
                codec,
                width_px=self.options.thumbnail_width_px,
                quality=self.options.jpeg_quality,
            )
            if thumb is None:
                continue
            jpeg, w, h = thumb
            info = {
                "stamp_ns": message.stamp_ns,
                "receive_ns": sample.receive_ns,
                "width": w,
                "height": h,
            }
            camera = topic.split("/")[1]
            self._put(
                f"{camera}/thumb", jpeg, encoding="image/jpeg", attachment=json.dumps(info).encode()
            )

    def _publish_imu(self) -> None:
        step_ns = NS_PER_S / self.options.imu_plot_hz
        for topic, window in list(self._imu.items()):
            items = []
            while window:
                items.append(window.popleft())
            if not items:
                continue
            stamps = np.array([t for t, _, _ in items], dtype=np.int64)
            gyro = np.array([g for _, g, _ in items])
            accel = np.array([a for _, _, a in items])
            # Keep about imu_plot_hz samples a second (the plot needs no more).
            keep = [0]
            for i in range(1, len(stamps)):
                if stamps[i] - stamps[keep[-1]] >= step_ns:
                    keep.append(i)
            span_s = seconds_from_ns(stamps[-1] - stamps[0])
            summary = {
                "stamp_ns": int(stamps[-1]),
                "count": len(items),
                "rate_hz": round((len(items) - 1) / span_s, 1) if span_s > 0 else 0.0,
                "t_ns": [int(stamps[i]) for i in keep],
                "gyro_rad_s": np.round(gyro[keep], 5).tolist(),
                "accel_m_s2": np.round(accel[keep], 4).tolist(),
                "gyro_mean_rad_s": np.round(gyro.mean(axis=0), 5).tolist(),
                "accel_norm_mean_m_s2": round(float(np.linalg.norm(accel, axis=1).mean()), 4),
            }
            name = topic.strip("/")
            self._put(f"{name}/summary", json.dumps(summary).encode(), encoding="application/json")

    def _publish_depth(self) -> None:
        with self._lock:
            depths, self._depth = self._depth, {}
        for topic, sample in depths.items():
            payload = {
                "stamp_ns": sample.stamp_ns,
                "depth_m": _finite(sample.depth_m),
                "pressure_pa": _finite(sample.pressure_pa),
                "temperature_c": _finite(sample.temperature_c),
            }
            self._put(topic.strip("/"), json.dumps(payload).encode(), encoding="application/json")


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
