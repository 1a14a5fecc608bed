"""The recorder in-process with fake sources: rotation, bounded queue, losses, full disk."""

from __future__ import annotations

import errno
import itertools
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import field.record.recorder as recorder_module
from field.record.hostclock import host_now_ns
from field.record.recorder import Recorder, RecorderOptions, SampleQueue
from field.record.recover import recover
from field.record.sources.base import SourceSample, StreamInfo
from shared.archive import ArchiveReader, ArchiveWriter, CompressedVideo, Imu
from shared.archive.messages import ArchiveMessage
from shared.errors import DeviceError, InputError, OutputExistsError

IDR = b"\x00\x00\x00\x01\x65"
P = b"\x00\x00\x00\x01\x41"


class FakeSource:
    """IMU at `imu_hz` and fake video packets at `fps`, paced by the wall clock.

    lost: (start_s, end_s) after the first open during which the device is gone;
    burst: samples returned at once by every read (ignores pacing; for queue tests).
    """

    def __init__(
        self,
        name: str = "fake",
        index: int = 0,
        *,
        imu_hz: float = 200.0,
        fps: float = 0.0,
        packet_bytes: int = 1000,
        lost: tuple[float, float] | None = None,
        burst: int = 0,
        absent: bool = False,
    ) -> None:
        self.name = name
        self.index = index
        self.imu_hz = imu_hz
        self.fps = fps
        self.packet_bytes = packet_bytes
        self.lost = lost
        self.burst = burst
        self.absent = absent
        self.t0: int | None = None
        self.next_imu = 0
        self.next_frame = 0
        self.produced = 0

    def streams(self) -> list[StreamInfo]:
        out = [StreamInfo(f"/imu{self.index}", "imu", self.imu_hz)]
        if self.fps:
            out.append(StreamInfo(f"/cam{self.index}/video", "video", self.fps, "h264", 64, 48))
        return out

    def _gone(self) -> bool:
        if self.lost is None or self.t0 is None:
            return False
        t = (host_now_ns() - self.t0) * 1e-9
        return self.lost[0] <= t < self.lost[1]

    def open(self) -> None:
        if self.absent:
            raise DeviceError(f"{self.name}: no device (found: none)")
        if self.t0 is None:
            self.t0 = host_now_ns()
        if self._gone():
            raise DeviceError(f"{self.name}: not found")
        elapsed = host_now_ns() - self.t0
        self.next_imu = max(self.next_imu, int(elapsed * self.imu_hz / 1e9))
        if self.fps:
            self.next_frame = max(self.next_frame, -(-int(elapsed * self.fps / 1e9) // 5) * 5)

    def _imu(self, k: int, now: int) -> SourceSample:
        assert self.t0 is not None
        stamp = self.t0 + round(k * 1e9 / self.imu_hz)
        msg = Imu(stamp, f"imu{self.index}", np.array([k, 0.0, 0.0]), np.array([0.0, 0.0, 9.81]))
        return SourceSample(f"/imu{self.index}", msg, now, device_ns=k, host_sync_ns=stamp)

    def _frame(self, k: int, now: int) -> SourceSample:
        assert self.t0 is not None
        stamp = self.t0 + round(k * 1e9 / self.fps)
        head = IDR if k % 5 == 0 else P
        data = head + k.to_bytes(4, "little") + bytes(self.packet_bytes)
        msg = CompressedVideo(stamp, f"cam{self.index}", "h264", data)
        return SourceSample(f"/cam{self.index}/video", msg, now, keyframe=k % 5 == 0)

    def read(self, timeout_s: float) -> list[SourceSample]:
        if self._gone():
            raise DeviceError(f"{self.name}: unplugged")
        now = host_now_ns()
        assert self.t0 is not None
        out = []
        if self.burst:
            for _ in range(self.burst):
                out.append(self._imu(self.next_imu, now))
                self.next_imu += 1
                if self.fps:
                    out.append(self._frame(self.next_frame, now))
                    self.next_frame += 1
            self.produced += len(out)
            time.sleep(0.001)
            return out
        # Integer stamps: t0 (~1.8e18 ns) as a float is only good to 256 ns, which let a
        # sample out up to that much before its own stamp (log time < stamp_ns).
        while self.t0 + round(self.next_imu * 1e9 / self.imu_hz) <= now:
            out.append(self._imu(self.next_imu, now))
            self.next_imu += 1
        while self.fps and self.t0 + round(self.next_frame * 1e9 / self.fps) <= now:
            out.append(self._frame(self.next_frame, now))
            self.next_frame += 1
        if not out:
            time.sleep(min(timeout_s, 0.005))
        self.produced += len(out)
        return out

    def close(self) -> None:
        pass

    def describe(self) -> dict[str, Any]:
        return {"kind": "fake", "name": self.name}

    def calibration(self) -> None:
        return None


def _video(message: ArchiveMessage) -> CompressedVideo:
    assert isinstance(message, CompressedVideo)
    return message


def _options(**kw: Any) -> RecorderOptions:
    base: dict[str, Any] = {"health_interval_s": 0.2, "min_free_mb": 1.0, "flush_interval_s": 0.2}
    base.update(kw)
    return RecorderOptions(**base)


def test_records_rotated_files_and_session(tmp_path: Path) -> None:
    source = FakeSource(imu_hz=400, fps=30, packet_bytes=20_000)
    session = tmp_path / "dive1"
    options = _options(duration_s=1.6, rotate_size_mb=0.25, compression="none")
    report = Recorder(options, [source], session).run()
    assert report.clean and report.stop_reason == "duration reached"
    assert len(report.files) >= 3
    assert [p.name for p in report.files][:2] == ["recording_000.mcap", "recording_001.mcap"]
    assert not list(session.glob("*.part"))
    doc = yaml.safe_load((session / "session.yaml").read_text())
    assert doc["id"] == "dive1"
    assert doc["recordings"] == [p.name for p in report.files]
    assert doc["stop_reason"] == "duration reached" and doc["clean"] is True
    assert doc["devices"] == [{"kind": "fake", "name": "fake"}]
    assert doc["clocks"]["imu0"]["to_host_sync"]["drift_ppm"] == pytest.approx(0.0, abs=1e-6)
    counts: dict[str, int] = {}
    imu_stamps: list[int] = []
    for path in report.files:
        with ArchiveReader(path) as reader:  # complete and indexed, no salvage needed
            assert reader.indexed
            messages = list(reader.messages())
            assert sum(topic == "/session" for topic, _, _ in messages) == 1
            for topic, log_time, msg in messages:
                counts[topic] = counts.get(topic, 0) + 1
                if topic == "/imu0":
                    imu_stamps.append(msg.stamp_ns)
                    assert log_time >= msg.stamp_ns  # log time = host receive time
    assert counts["/session"] == len(report.files)
    assert counts["/imu0"] == report.messages["/imu0"] == source.next_imu
    # Nothing lost across rotations: IMU sample k has stamp t0 + k * 2.5 ms.
    assert np.all(np.diff(imu_stamps) == 2_500_000)
    assert 1.4 * 400 <= len(imu_stamps) <= 1.8 * 400


def test_full_queue_drops_counts_and_skips_to_key_frame(tmp_path: Path) -> None:
    source = FakeSource(imu_hz=400, fps=30, packet_bytes=100_000, burst=50)
    options = _options(duration_s=0.8, queue_max_items=40, queue_max_mb=1.0, flush_interval_s=0.05)
    report = Recorder(options, [source], tmp_path / "s").run()
    written = sum(c for t, c in report.messages.items() if t != "/session")
    assert sum(report.dropped.values()) > 0
    assert written + sum(report.dropped.values()) == source.produced
    with ArchiveReader(report.files[0]) as reader:
        frames = [
            int.from_bytes(_video(m).data[5:9], "little")
            for _, _, m in reader.messages(["/cam0/video"])
        ]
    # After a dropped packet the next one written starts a group of pictures (k % 5 == 0).
    for previous, current in itertools.pairwise(frames):
        if current != previous + 1:
            assert current % 5 == 0


def test_sample_queue_limits_items_and_bytes() -> None:
    queue = SampleQueue(max_items=3, max_bytes=10_000)
    small = SourceSample("/imu0", Imu(1, "imu0", np.zeros(3), np.zeros(3)), 1)
    big = SourceSample("/cam0/video", CompressedVideo(1, "cam0", "h264", bytes(9_000)), 1)
    assert queue.put(big) and not queue.put(big)  # bytes limit
    assert queue.put(small) and queue.put(small) and not queue.put(small)  # item limit
    assert len(queue.get_batch(0.0, max_items=2)) == 2 and len(queue) == 1
    assert queue.get_batch(0.01)[0] is small and queue.bytes == 0
    assert queue.get_batch(0.01) == []


def test_lost_source_reconnects_while_others_go_on(tmp_path: Path) -> None:
    flaky = FakeSource("flaky", 0, imu_hz=200, lost=(0.3, 0.8))
    steady = FakeSource("steady", 1, imu_hz=200)
    options = _options(duration_s=1.4, reconnect_interval_s=0.05)
    report = Recorder(options, [flaky, steady], tmp_path / "s").run()
    assert any("flaky: lost" in e for e in report.events)
    assert any("flaky: reconnected" in e for e in report.events)
    with ArchiveReader(report.files[0]) as reader:
        t_flaky = reader.read_imu("/imu0").stamps_ns
        t_steady = reader.read_imu("/imu1").stamps_ns
    assert np.max(np.diff(t_steady)) == 5_000_000  # no gap
    gaps = np.diff(t_flaky)
    assert 0.4e9 < np.max(gaps) < 0.7e9  # the outage, then recording resumed
    assert t_flaky[-1] > flaky.t0 + 1.0e9  # type: ignore[operator]


def test_refuses_existing_session_duplicate_topics_and_absent_device(tmp_path: Path) -> None:
    session = tmp_path / "s"
    Recorder(_options(duration_s=0.3), [FakeSource()], session).run()
    with pytest.raises(OutputExistsError, match="already holds a recording"):
        Recorder(_options(duration_s=0.3), [FakeSource()], session).run()
    with pytest.raises(InputError, match="several sources write /imu0"):
        Recorder(_options(), [FakeSource("a"), FakeSource("b")], tmp_path / "x")
    with pytest.raises(InputError, match="no source"):
        Recorder(_options(), [], tmp_path / "x")
    with pytest.raises(DeviceError, match="no device"):
        Recorder(_options(), [FakeSource(absent=True)], tmp_path / "absent").run()
    assert not (tmp_path / "absent").exists()  # nothing written when the device is absent
    with pytest.raises(ValueError, match="flush_interval_s"):
        RecorderOptions(flush_interval_s=60)


def test_disk_nearly_full_stops_cleanly(tmp_path: Path) -> None:
    options = _options(duration_s=5.0, min_free_mb=1e12)
    report = Recorder(options, [FakeSource()], tmp_path / "s").run()
    assert report.stop_reason == "disk nearly full" and report.clean
    assert report.duration_s < 2.0
    with ArchiveReader(report.files[0]) as reader:
        assert reader.indexed


class HealthSink:
    """A preview sink that keeps every health message."""

    def __init__(self) -> None:
        self.health: list[dict[str, Any]] = []

    def offer(self, sample: SourceSample) -> None:
        pass

    def publish_health(self, health: dict[str, Any]) -> None:
        self.health.append(dict(health))


def test_preview_is_told_why_the_recording_stopped(tmp_path: Path) -> None:
    sink = HealthSink()
    options = _options(duration_s=5.0, min_free_mb=1e12)
    report = Recorder(options, [FakeSource()], tmp_path / "s", preview=sink).run()
    assert report.stop_reason == "disk nearly full"
    assert sink.health[0]["state"] == "recording"
    last = sink.health[-1]
    assert last["state"] == "stopped" and last["stop_reason"] == "disk nearly full"
    assert last["clean"] is True
    assert any("disk nearly full" in e for e in last["events"])


class FailingWriter(ArchiveWriter):
    """An ArchiveWriter whose disk fills up after a few flushes (fault injection)."""

    flushes_left = 3

    def flush(self, *, fsync: bool = False) -> None:
        FailingWriter.flushes_left -= 1
        if FailingWriter.flushes_left < 0:
            super().flush(fsync=fsync)  # what fitted is on disk, then the disk is full
            raise OSError(errno.ENOSPC, "No space left on device")
        super().flush(fsync=fsync)

    def close(self) -> Path:
        if FailingWriter.flushes_left < 0:
            self._file.close()  # the summary cannot be written any more
            self._closed = True
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().close()


def test_enospc_stops_keeps_data_and_says_how_to_recover(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(recorder_module, "ArchiveWriter", FailingWriter)
    FailingWriter.flushes_left = 3
    report = Recorder(_options(duration_s=5.0), [FakeSource()], tmp_path / "s").run()
    assert report.stop_reason == "disk full" and not report.clean
    assert any("recover" in e and ".part" in e for e in report.events)
    part = tmp_path / "s" / "recording_000.mcap.part"
    assert part.is_file()
    result = recover(part)
    assert result.messages["/imu0"] > 0.5 * 200  # at least the flushed ~0.6 s are kept
    doc = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    assert doc["stop_reason"] == "disk full" and doc["clean"] is False


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tiny tmpfs needs root")
def test_real_full_disk_on_tiny_tmpfs(tmp_path: Path) -> None:
    mount = tmp_path / "tiny"
    mount.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], check=True)
    try:
        source = FakeSource(imu_hz=200, fps=30, packet_bytes=30_000)  # ~1 MB/s: full in ~1 s
        options = _options(duration_s=10.0, min_free_mb=0.0, compression="none")
        report = Recorder(options, [source], mount / "s").run()
        assert report.stop_reason == "disk full"
        assert report.duration_s < 5.0
        files = list((mount / "s").glob("recording_000.mcap*"))
        assert files, "what was written is kept"
        with ArchiveReader(files[0], salvage=True) as reader:
            kept = sum(1 for _ in reader.raw_messages())
        assert kept > 100
    finally:
        subprocess.run(["umount", str(mount)], check=True)


def test_rotates_by_time(tmp_path: Path) -> None:
    options = _options(duration_s=1.3, rotate_interval_s=0.5, rotate_size_mb=0.0)
    report = Recorder(options, [FakeSource(imu_hz=200)], tmp_path / "s").run()
    assert len(report.files) in (2, 3)
    total = 0
    for path in report.files:
        with ArchiveReader(path) as reader:
            series = reader.read_imu("/imu0")
            total += len(series.stamps_ns)
            span_s = (series.log_times_ns[-1] - series.log_times_ns[0]) * 1e-9
            assert span_s < 0.5 + 0.2 + 0.1  # interval + health check period + slack
    assert total == report.messages["/imu0"]
