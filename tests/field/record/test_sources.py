"""Sources: the registry, the simulated rig in real time, the OAK conversions with fakes."""

from __future__ import annotations

import datetime
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from field.record.hostclock import host_now_ns
from field.record.sources import SOURCES, make_source
from field.record.sources.base import CameraSource
from field.record.sources.oak import (
    OakOptions,
    OakSource,
    describe_devices,
    encoded_frame_samples,
    imu_samples,
    timedelta_ns,
)
from field.record.sources.sim import SimOptions, clip_path
from field.record.timing import ClockFit, DeviceClockMapper, is_keyframe
from shared.archive import CompressedImage, CompressedVideo, Imu
from shared.errors import DeviceError, InputError


def test_registry_names_and_errors() -> None:
    assert {"oak", "sim"} <= set(SOURCES)
    with pytest.raises(InputError, match=r"unknown .*expected one of: .*oak.*sim"):
        make_source("gopro-live")
    with pytest.raises(InputError, match=r"unknown key\(s\) colour"):
        make_source("sim", {"colour": True})
    with pytest.raises(InputError, match="cameras must be 1 or 2"):
        make_source("sim", {"cameras": 3})
    with pytest.raises(InputError, match="codec must be"):
        make_source("oak", {"codec": "vp9"})


def test_sim_options_are_checked() -> None:
    with pytest.raises(ValueError, match="render_scale"):
        SimOptions(width_px=320, height_px=200, render_scale=3)
    with pytest.raises(ValueError, match="even"):
        SimOptions(width_px=34, height_px=14, render_scale=1)


def _collect(source: CameraSource, seconds: float) -> list[Any]:
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out += source.read(0.05)
    return out


def test_sim_streams_in_real_time_on_its_own_clock(sim_options: dict[str, Any]) -> None:
    source = make_source("sim", sim_options)
    assert clip_path(source.options).is_file()  # type: ignore[attr-defined]
    topics = [s.topic for s in source.streams()]
    assert topics == ["/cam0/video", "/imu0", "/depth0"]
    source.open()
    t0 = host_now_ns()  # the clock sources stamp with (the wall clock may step)
    samples = _collect(source, 1.5)
    t1 = host_now_ns()
    source.close()
    by_topic: dict[str, list[Any]] = {}
    for s in samples:
        by_topic.setdefault(s.topic, []).append(s)
    # Paced by the wall clock: counts match the rates over 1.5 s (minus start latency).
    assert 15 * 1.5 - 3 <= len(by_topic["/cam0/video"]) <= 15 * 1.5 + 1
    assert 400 * 1.5 - 30 <= len(by_topic["/imu0"]) <= 400 * 1.5 + 2
    for s in samples:
        assert t0 <= s.receive_ns <= t1
        assert s.message.stamp_ns <= s.receive_ns + 1_000_000  # captured before received
    video = by_topic["/cam0/video"]
    assert video[0].keyframe and is_keyframe(video[0].message.data, "h264")
    assert sum(s.keyframe for s in video) == pytest.approx(len(video) / 5, abs=1)
    imu = [s.message for s in by_topic["/imu0"]]
    assert all(isinstance(m, Imu) for m in imu)
    stamps = np.array([m.stamp_ns for m in imu])
    assert np.all(np.diff(stamps) > 0)
    # The device clock runs 25 ppm fast: its 2.5 ms steps are 2.5 ms * (1 + 25e-6).
    assert np.median(np.diff(stamps)) == pytest.approx(2_500_062, abs=2)
    fit = ClockFit()
    for s in by_topic["/imu0"]:
        fit.add(s.message.stamp_ns, s.host_sync_ns)
    est = fit.estimate()
    assert est is not None and est.model.drift_ppm == pytest.approx(-25.0, abs=0.5)
    # Gravity is in the accelerometer (|a| ~ 9.8 m/s^2 for a slow diver).
    accel = np.array([m.linear_acceleration_m_s2 for m in imu])
    assert np.linalg.norm(accel, axis=1).mean() == pytest.approx(9.81, abs=0.6)


def test_sim_camera_unplug_keeps_imu(sim_options: dict[str, Any]) -> None:
    source = make_source(
        "sim", {**sim_options, "camera_unplug_at_s": 0.3, "camera_unplug_for_s": 0.8}
    )
    source.open()
    opened = host_now_ns()
    samples = _collect(source, 1.6)
    source.close()
    cam = [(s.receive_ns - opened) * 1e-9 for s in samples if s.topic == "/cam0/video"]
    imu = [(s.receive_ns - opened) * 1e-9 for s in samples if s.topic == "/imu0"]
    assert not [t for t in cam if 0.35 < t < 1.05]
    assert [t for t in cam if t > 1.15], "the camera resumes"
    assert len([t for t in imu if 0.35 < t < 1.05]) > 200, "the IMU goes on"
    resumed = [s for s in samples if s.topic == "/cam0/video" and (s.receive_ns - opened) > 1.1e9]
    assert resumed[0].keyframe, "a camera resumes on a key frame"


def test_sim_device_loss_raises_and_reopens(sim_options: dict[str, Any]) -> None:
    source = make_source("sim", {**sim_options, "device_lost_at_s": 0.2, "device_lost_for_s": 0.5})
    source.open()
    with pytest.raises(DeviceError, match="device lost"):
        _collect(source, 0.5)
    with pytest.raises(DeviceError, match="not found"):
        source.open()
    time.sleep(0.6)
    source.open()
    assert _collect(source, 0.3)
    source.close()
    with pytest.raises(DeviceError, match="read before open"):
        source.read(0.01)


def test_sim_mjpeg_and_stereo(tmp_path: Path) -> None:
    options = {
        "cameras": 2,
        "codec": "mjpeg",
        "width_px": 64,
        "height_px": 48,
        "render_scale": 2,
        "fps": 10.0,
        "clip_s": 0.5,
        "texel_mm": 40.0,
        "depth_rate_hz": 0,
        "cache_dir": str(tmp_path),
    }
    source = make_source("sim", options)
    assert [s.topic for s in source.streams()] == ["/cam0/image", "/cam1/image", "/imu0"]
    calib = source.calibration()
    assert calib is not None
    cams, noise = calib
    assert [c.name for c in cams] == ["cam0", "cam1"]
    # cam1 sits baseline_m to the right of cam0: its extrinsic differs by that translation.
    np.testing.assert_allclose(
        (cams[0].cam_from_imu - cams[1].cam_from_imu)[:3, 3], [0.075, 0.0, 0.0], atol=1e-12
    )
    assert noise is not None and noise.update_rate_hz == 400.0
    source.open()
    samples = _collect(source, 0.45)
    source.close()
    images = [s.message for s in samples if s.topic == "/cam1/image"]
    assert images and all(
        isinstance(m, CompressedImage) and m.data[:2] == b"\xff\xd8" for m in images
    )


# ---------------------------------------------------------------- OAK pieces with fakes


class FakeEncodedFrame:
    def __init__(self, device_s: float, host_s: float, data: bytes, frame_type: str) -> None:
        self._device = datetime.timedelta(seconds=device_s)
        self._host = datetime.timedelta(seconds=host_s)
        self._data = np.frombuffer(data, np.uint8)
        self._type = frame_type

    def getTimestampDevice(self) -> datetime.timedelta:  # noqa: N802 (DepthAI's name)
        return self._device

    def getTimestamp(self) -> datetime.timedelta:  # noqa: N802
        return self._host

    def getData(self) -> np.ndarray:  # noqa: N802
        return self._data

    def getFrameType(self) -> str:  # noqa: N802
        return f"FrameType.{self._type}"


class FakeReport(SimpleNamespace):
    device: datetime.timedelta
    host: datetime.timedelta

    def getTimestampDevice(self) -> datetime.timedelta:  # noqa: N802
        return self.device

    def getTimestamp(self) -> datetime.timedelta:  # noqa: N802
        return self.host


def test_timedelta_ns_is_exact() -> None:
    assert timedelta_ns(datetime.timedelta(days=1, seconds=2, microseconds=345_678)) == (
        86_402_345_678_000
    )
    assert timedelta_ns(datetime.timedelta(microseconds=-1)) == -1000


def test_encoded_frames_keep_both_clocks() -> None:
    mapper = DeviceClockMapper()
    steady_to_epoch = 1_700_000_000_000_000_000
    idr = b"\x00\x00\x00\x01\x67\x00\x00\x00\x01\x65\x88"
    first = encoded_frame_samples(
        FakeEncodedFrame(10.0, 500.000_1, idr, "I"),
        topic="/cam0/video",
        frame_id="cam0",
        codec="h264",
        mapper=mapper,
        steady_to_epoch_ns=steady_to_epoch,
        receive_ns=7,
    )
    second = encoded_frame_samples(
        FakeEncodedFrame(10.033_333, 500.033_5, b"\x00\x00\x01\x41", "P"),
        topic="/cam0/video",
        frame_id="cam0",
        codec="h264",
        mapper=mapper,
        steady_to_epoch_ns=steady_to_epoch,
        receive_ns=8,
    )
    assert isinstance(first.message, CompressedVideo) and first.message.data == idr
    assert first.keyframe and not second.keyframe
    assert first.device_ns == 10_000_000_000 and second.device_ns == 10_033_333_000
    assert first.host_sync_ns == steady_to_epoch + 500_000_100_000
    # header.stamp: device clock moved by the offset fixed at the first frame.
    assert first.message.stamp_ns == first.host_sync_ns
    assert second.message.stamp_ns - first.message.stamp_ns == 33_333_000
    assert (first.receive_ns, second.receive_ns) == (7, 8)
    jpeg = encoded_frame_samples(
        FakeEncodedFrame(1.0, 2.0, b"\xff\xd8\xff", "I"),
        topic="/cam0/image",
        frame_id="cam0",
        codec="mjpeg",
        mapper=DeviceClockMapper(),
        steady_to_epoch_ns=0,
        receive_ns=0,
    )
    assert isinstance(jpeg.message, CompressedImage) and jpeg.message.format == "jpeg"


def test_imu_packets_become_imu_messages() -> None:
    def report(t: float, x: float, y: float, z: float) -> FakeReport:
        return FakeReport(
            device=datetime.timedelta(seconds=t),
            host=datetime.timedelta(seconds=t + 100.0),
            x=x,
            y=y,
            z=z,
        )

    packets = [
        SimpleNamespace(
            gyroscope=report(1.0, 0.1, 0.2, 0.3), acceleroMeter=report(0.9995, 0.0, 0.0, 9.8)
        ),
        SimpleNamespace(
            gyroscope=report(1.0025, 0.4, 0.5, 0.6), acceleroMeter=report(1.002, 1.0, 0.0, 9.8)
        ),
    ]
    samples = imu_samples(
        SimpleNamespace(packets=packets),
        topic="/imu0",
        frame_id="imu0",
        mapper=DeviceClockMapper(),
        steady_to_epoch_ns=0,
        receive_ns=123,
    )
    assert [s.device_ns for s in samples] == [1_000_000_000, 1_002_500_000]
    assert [s.host_sync_ns for s in samples] == [101_000_000_000, 101_002_500_000]
    assert samples[1].message.stamp_ns - samples[0].message.stamp_ns == 2_500_000
    imu = samples[1].message
    assert isinstance(imu, Imu)
    np.testing.assert_allclose(imu.angular_velocity_rad_s, [0.4, 0.5, 0.6])
    np.testing.assert_allclose(imu.linear_acceleration_m_s2, [1.0, 0.0, 9.8])


def test_oak_without_device_lists_what_was_found() -> None:
    assert describe_devices([]) == "none"
    assert "14442C10 (oak-d, X_LINK_UNBOOTED)" in describe_devices(
        [SimpleNamespace(deviceId="14442C10", name="oak-d", state="X_LINK_UNBOOTED")]
    )
    source = OakSource(OakOptions(device_id="NOPE"))
    with pytest.raises(
        DeviceError, match=r"no device available \(looked for device 'NOPE'; found: "
    ):
        source.open()
    with pytest.raises(DeviceError, match="read before open"):
        source.read(0.01)
    source.close()  # nothing to release: no error


@pytest.mark.hardware
def test_oak_streams_video_and_imu() -> None:
    source = make_source("oak", {"cameras": "color", "width_px": 1280, "height_px": 720})
    source.open()
    try:
        samples = []
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            samples += source.read(0.1)
    finally:
        source.close()
    topics = {s.topic for s in samples}
    assert {"/cam0/video", "/imu0"} <= topics
    imu = [s for s in samples if s.topic == "/imu0"]
    assert len(imu) > 3 * 150
