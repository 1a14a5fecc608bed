"""A Luxonis OAK camera through the DepthAI 3.x API: encoded video and IMU.

Pipeline (depthai 3): `dai.Pipeline(device)`; a `Camera` node per sensor socket built with
`.build(socket)`, its `requestOutput((w, h), NV12, fps=...)` linked into a `VideoEncoder`
(H.264/H.265/MJPEG encoded on the device, so the host only moves bytes); an `IMU` node with
raw accelerometer + gyroscope at 200-400 Hz; host queues from `output.createOutputQueue()`
polled with `tryGetAll()`; `pipeline.start()` / `pipeline.stop()`.

Time: each DepthAI message has `getTimestampDevice()` (device clock, since boot) and
`getTimestamp()` (the same instant on the host's steady clock, from DepthAI's own time
sync). Both are kept: the device reading goes to `header.stamp` (moved to the epoch by one
fixed offset, `DeviceClockMapper`), the host-synced one to `host_sync_ns` (moved from the
steady clock to the epoch), from which the recorder fits the device-to-host relation.

The conversions (`encoded_frame_samples`, `imu_samples`, `timedelta_ns`) are plain
functions of DepthAI-like objects so they are tested with fakes; the pipeline needs a
device (tests marked `hardware`).
"""

from __future__ import annotations

import datetime
import logging
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from field.record.hostclock import host_now_ns
from field.record.sources.base import SourceSample, StreamInfo, register_source
from field.record.timing import DeviceClockMapper
from shared.archive import (
    CompressedImage,
    CompressedVideo,
    Imu,
    image_topic,
    imu_topic,
    video_topic,
)
from shared.clock import NS_PER_S
from shared.errors import DeviceError

log = logging.getLogger(__name__)

_CAMERA_LAYOUTS = {
    # layout -> sockets (DepthAI CameraBoardSocket names), in topic order
    "color": ("CAM_A",),
    "mono": ("CAM_B",),
    "stereo": ("CAM_B", "CAM_C"),
}
_PROFILES = {"h264": "H264_MAIN", "h265": "H265_MAIN", "mjpeg": "MJPEG"}


@dataclass(kw_only=True)
class OakOptions:
    """OAK settings.

    device_id: DepthAI device id (MX id / serial) or "" for the first one found;
    cameras: "color" (CAM_A), "mono" (CAM_B) or "stereo" (CAM_B + CAM_C);
    width_px, height_px: encoded image size; fps: frame rate (Hz);
    codec: "h264", "h265" or "mjpeg" (encoded on the device); bitrate_kbps: H.26x bit rate
    (0: the encoder's default); keyframe_interval: frames per group of pictures;
    jpeg_quality: 0-100 for mjpeg; imu_rate_hz: accelerometer and gyroscope rate (200-400);
    queue_size: host-side DepthAI queue length per stream (non-blocking: oldest dropped).
    """

    device_id: str = ""
    cameras: str = "stereo"
    width_px: int = 1280
    height_px: int = 800
    fps: float = 30.0
    codec: str = "h264"
    bitrate_kbps: int = 8000
    keyframe_interval: int = 30
    jpeg_quality: int = 90
    imu_rate_hz: float = 400.0
    queue_size: int = 30

    def __post_init__(self) -> None:
        if self.cameras not in _CAMERA_LAYOUTS:
            raise ValueError(
                f"cameras must be one of {sorted(_CAMERA_LAYOUTS)}, got {self.cameras!r}"
            )
        if self.codec not in _PROFILES:
            raise ValueError(f"codec must be one of {sorted(_PROFILES)}, got {self.codec!r}")
        if not 100 <= self.imu_rate_hz <= 500:
            raise ValueError(f"imu_rate_hz must be in [100, 500], got {self.imu_rate_hz}")
        if not 0 < self.fps <= 120:
            raise ValueError(f"fps must be in (0, 120], got {self.fps}")


def timedelta_ns(value: datetime.timedelta) -> int:
    """A DepthAI timestamp (datetime.timedelta) as integer nanoseconds, exactly."""
    return (value.days * 86_400 + value.seconds) * NS_PER_S + value.microseconds * 1000


def steady_to_epoch_offset_ns() -> int:
    """Epoch minus steady clock now (DepthAI's host timestamps use std::chrono::steady_clock,
    which is CLOCK_MONOTONIC on Linux, like `time.monotonic_ns`)."""
    a = host_now_ns()
    m = time.monotonic_ns()
    b = host_now_ns()
    return (a + b) // 2 - m


def encoded_frame_samples(
    frame: Any,
    *,
    topic: str,
    frame_id: str,
    codec: str,
    mapper: DeviceClockMapper,
    steady_to_epoch_ns: int,
    receive_ns: int,
) -> SourceSample:
    """One DepthAI `EncodedFrame` (or 2.x-style ImgFrame bitstream) as a SourceSample.

    H.26x frames become CompressedVideo (Annex B as the encoder emits it), MJPEG frames
    CompressedImage "jpeg".
    """
    device_ns = timedelta_ns(frame.getTimestampDevice())
    host_sync_ns = timedelta_ns(frame.getTimestamp()) + steady_to_epoch_ns
    stamp_ns = mapper.to_epoch(device_ns, host_sync_ns)
    data = bytes(np.asarray(frame.getData(), dtype=np.uint8).tobytes())
    message: CompressedVideo | CompressedImage
    if codec == "mjpeg":
        message = CompressedImage(stamp_ns, frame_id, "jpeg", data)
        keyframe = True
    else:
        message = CompressedVideo(stamp_ns, frame_id, codec, data)
        keyframe = _is_i_frame(frame)
    return SourceSample(topic, message, receive_ns, device_ns, host_sync_ns, keyframe)


def _is_i_frame(frame: Any) -> bool:
    getter = getattr(frame, "getFrameType", None)
    if getter is None:
        return False
    return str(getter()).rsplit(".", 1)[-1] == "I"


def imu_samples(
    imu_data: Any,
    *,
    topic: str,
    frame_id: str,
    mapper: DeviceClockMapper,
    steady_to_epoch_ns: int,
    receive_ns: int,
) -> list[SourceSample]:
    """The packets of one DepthAI `IMUData` as Imu samples.

    Each packet pairs one accelerometer and one gyroscope report; the gyroscope's time
    is the sample time (the accelerometer is sampled within a millisecond of it, and
    the archive's Imu message holds one stamp).
    """
    out = []
    for packet in imu_data.packets:
        gyro = packet.gyroscope
        accel = packet.acceleroMeter
        device_ns = timedelta_ns(gyro.getTimestampDevice())
        host_sync_ns = timedelta_ns(gyro.getTimestamp()) + steady_to_epoch_ns
        stamp_ns = mapper.to_epoch(device_ns, host_sync_ns)
        message = Imu(
            stamp_ns=stamp_ns,
            frame_id=frame_id,
            angular_velocity_rad_s=np.array([gyro.x, gyro.y, gyro.z], dtype=np.float64),
            linear_acceleration_m_s2=np.array([accel.x, accel.y, accel.z], dtype=np.float64),
        )
        out.append(SourceSample(topic, message, receive_ns, device_ns, host_sync_ns))
    return out


def describe_devices(devices: list[Any]) -> str:
    """One line per found DepthAI device (id, name, state), or "none"."""
    if not devices:
        return "none"
    parts = []
    for info in devices:
        device_id = getattr(info, "deviceId", None) or getattr(info, "getDeviceId", lambda: "?")()
        parts.append(f"{device_id} ({getattr(info, 'name', '?')}, {getattr(info, 'state', '?')})")
    return ", ".join(parts)


@register_source("oak")
class OakSource:
    """A DepthAI 3.x OAK camera (see the module docstring). Options: `OakOptions`."""

    name = "oak"
    options_type = OakOptions

    def __init__(self, options: OakOptions) -> None:
        self.options = options
        self._pipeline: Any = None
        self._device: Any = None
        self._queues: list[tuple[str, str, Any]] = []  # (kind, topic, queue)
        self._mapper = DeviceClockMapper()
        self._steady_to_epoch_ns = 0
        self._facts: dict[str, Any] = {}

    def streams(self) -> list[StreamInfo]:
        o = self.options
        result = []
        for i, _socket in enumerate(_CAMERA_LAYOUTS[o.cameras]):
            if o.codec == "mjpeg":
                result.append(
                    StreamInfo(
                        image_topic(i), "image", o.fps, "jpeg", o.width_px, o.height_px, "oak"
                    )
                )
            else:
                result.append(
                    StreamInfo(
                        video_topic(i), "video", o.fps, o.codec, o.width_px, o.height_px, "oak"
                    )
                )
        result.append(StreamInfo(imu_topic(0), "imu", o.imu_rate_hz, device="oak"))
        return result

    def open(self) -> None:
        try:
            import depthai as dai
        except ImportError as error:
            raise DeviceError(f"OAK: depthai is not installed ({error})") from None
        o = self.options
        found = list(dai.Device.getAllAvailableDevices())
        wanted = [d for d in found if not o.device_id or getattr(d, "deviceId", "") == o.device_id]
        if not wanted:
            looked = f"device {o.device_id!r}" if o.device_id else "any OAK device"
            raise DeviceError(
                f"OAK: no device available (looked for {looked}; found: "
                f"{describe_devices(found)}); check the USB cable and the udev rule for vendor 03e7"
            )
        try:
            self._device = dai.Device(wanted[0])
            self._build_pipeline(dai, self._device)
        except RuntimeError as error:
            self.close()
            raise DeviceError(
                f"OAK: cannot start {describe_devices(wanted[:1])}: {error}"
            ) from None
        self._mapper.reset()
        self._steady_to_epoch_ns = steady_to_epoch_offset_ns()

    def _build_pipeline(self, dai: Any, device: Any) -> None:
        o = self.options
        pipeline = dai.Pipeline(device)
        profile = getattr(dai.VideoEncoderProperties.Profile, _PROFILES[o.codec])
        self._queues = []
        for i, socket_name in enumerate(_CAMERA_LAYOUTS[o.cameras]):
            socket = getattr(dai.CameraBoardSocket, socket_name)
            camera = pipeline.create(dai.node.Camera).build(socket)
            output = camera.requestOutput(
                (o.width_px, o.height_px), dai.ImgFrame.Type.NV12, fps=o.fps
            )
            encoder = pipeline.create(dai.node.VideoEncoder)
            encoder.setDefaultProfilePreset(o.fps, profile)
            if o.codec == "mjpeg":
                encoder.setQuality(o.jpeg_quality)
            else:
                if o.bitrate_kbps:
                    encoder.setBitrateKbps(o.bitrate_kbps)
                encoder.setKeyframeFrequency(o.keyframe_interval)
                encoder.setNumBFrames(0)
            output.link(encoder.input)
            topic = image_topic(i) if o.codec == "mjpeg" else video_topic(i)
            queue = encoder.out.createOutputQueue(maxSize=o.queue_size, blocking=False)
            self._queues.append(("camera", topic, queue))
        imu = pipeline.create(dai.node.IMU)
        rate = round(o.imu_rate_hz)
        imu.enableIMUSensor([dai.IMUSensor.ACCELEROMETER_RAW, dai.IMUSensor.GYROSCOPE_RAW], rate)
        # Small batches: low latency, and a crash loses few samples.
        imu.setBatchReportThreshold(5)
        imu.setMaxBatchReports(20)
        queue = imu.out.createOutputQueue(maxSize=o.queue_size * 4, blocking=False)
        self._queues.append(("imu", imu_topic(0), queue))
        pipeline.start()
        self._pipeline = pipeline
        self._facts = {
            "device_id": str(device.getDeviceId()),
            "product": str(device.getProductName()) if hasattr(device, "getProductName") else "",
            "imu": str(device.getConnectedIMU()) if hasattr(device, "getConnectedIMU") else "",
            "usb_speed": str(device.getUsbSpeed()) if hasattr(device, "getUsbSpeed") else "",
        }

    def read(self, timeout_s: float) -> list[SourceSample]:
        if self._pipeline is None:
            raise DeviceError("OAK: read before open")
        deadline = time.monotonic() + timeout_s
        while True:
            out: list[SourceSample] = []
            try:
                if not self._pipeline.isRunning():
                    raise DeviceError("OAK: pipeline stopped (device unplugged or crashed)")
                for kind, topic, queue in self._queues:
                    messages = queue.tryGetAll()
                    receive_ns = host_now_ns()
                    for m in messages:
                        if kind == "camera":
                            out.append(self._frame(m, topic, receive_ns))
                        else:
                            out.extend(self._imu(m, topic, receive_ns))
            except RuntimeError as error:
                # XLink errors surface as RuntimeError subclasses (queue closed, link down).
                raise DeviceError(f"OAK: device lost ({error})") from None
            if out or time.monotonic() >= deadline:
                return out
            time.sleep(0.002)

    def _frame(self, frame: Any, topic: str, receive_ns: int) -> SourceSample:
        index = topic.split("/")[1]
        return encoded_frame_samples(
            frame,
            topic=topic,
            frame_id=index,
            codec=self.options.codec,
            mapper=self._mapper,
            steady_to_epoch_ns=self._steady_to_epoch_ns,
            receive_ns=receive_ns,
        )

    def _imu(self, data: Any, topic: str, receive_ns: int) -> list[SourceSample]:
        return imu_samples(
            data,
            topic=topic,
            frame_id="imu0",
            mapper=self._mapper,
            steady_to_epoch_ns=self._steady_to_epoch_ns,
            receive_ns=receive_ns,
        )

    def close(self) -> None:
        pipeline, device = self._pipeline, self._device
        self._pipeline = self._device = None
        for thing in (pipeline, device):
            if thing is None:
                continue
            try:
                (thing.stop if thing is pipeline else thing.close)()
            except RuntimeError as error:  # already gone: nothing left to release
                log.debug("OAK: close: %s", error)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "oak",
            "model": self._facts.get("product", "Luxonis OAK"),
            "serial": self._facts.get("device_id", self.options.device_id),
            "settings": asdict(self.options),
            "device": dict(self._facts),
            "clock": {
                "name": "oak_device",
                "description": "OAK device clock (getTimestampDevice) moved to the epoch by one "
                "offset fixed at the first sample; host_sync from getTimestamp()",
            },
        }

    def calibration(self) -> None:
        # The EEPROM calibration could be exported here (readCalibration); not done yet.
        return None
