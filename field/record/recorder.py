"""The recorder: live sources -> bounded queue -> crash-safe, rotated MCAP files.

Threads: one pump thread per source (open, read, reconnect after a loss) puts samples
into one bounded queue (item and byte limits; a full queue drops the new sample and counts
it, and a dropped video packet also drops the rest of its group of pictures, which could
not be decoded anyway). The thread calling `run` writes: MCAP log time = host receive
time, `header.stamp` = sensor clock. Every `flush_interval_s` the chunk in progress is
written and fsynced, so a SIGKILL or a power cut loses at most about that much (the
`.part` file is rebuilt by `field.record.recover`). Files rotate by size or age
(`recording_NNN.mcap`); each one starts with the session description on `/session`.

The recorder stops cleanly (summary written, `.part` renamed) on `stop()` (SIGINT /
SIGTERM in the CLI), after `duration_s`, or when the disk is nearly full; if the disk
fills anyway (ENOSPC) it stops, keeps what is on disk and says how to recover it.

Session folder (conventions.md): session.yaml, recording_NNN.mcap, calib/.
"""

from __future__ import annotations

import collections
import errno
import logging
import shutil
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import yaml

from field.record.hostclock import CLOCK_STEP_NS, HOST_CLOCK
from field.record.sources.base import CameraSource, SourceSample
from field.record.timing import ClockFit
from shared.archive import (
    HEALTH_TOPIC,
    SESSION_TOPIC,
    ArchiveWriter,
    CompressedVideo,
    RecorderEvent,
    SessionInfo,
)
from shared.archive.writer import Compression
from shared.clock import seconds_from_ns
from shared.errors import DeviceError, InputError, OutputExistsError, WreckmapError
from shared.folders import SessionFolder
from shared.fsutil import write_text_atomic

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class RecorderOptions:
    """How to record.

    duration_s: stop after this many seconds (None: until stopped); rotate_size_mb: start a
    new file past this size (MiB; 0: never); rotate_interval_s: start a new file after this
    many seconds (0: never); flush_interval_s: write and fsync the chunk in progress at
    least this often (s; bounds what a crash loses); fsync: fsync at each flush;
    chunk_size_kb: uncompressed chunk size that forces a write (KiB); compression: "zstd",
    "lz4" or "none"; queue_max_items, queue_max_mb: the bounded queue between sources and
    writer (items, MiB); min_free_mb: stop cleanly when the disk has less free space (MiB);
    reconnect_interval_s: wait between attempts to reopen a lost device (s);
    health_interval_s: how often health is computed and published (s); session_id: session
    name (default: the folder name); rig: rig name (preview keys); site: where (free text).
    """

    duration_s: float | None = None
    rotate_size_mb: float = 1024.0
    rotate_interval_s: float = 0.0
    flush_interval_s: float = 0.5
    fsync: bool = True
    chunk_size_kb: int = 1024
    compression: Compression = "zstd"
    queue_max_items: int = 4000
    queue_max_mb: float = 64.0
    min_free_mb: float = 200.0
    reconnect_interval_s: float = 1.0
    health_interval_s: float = 1.0
    session_id: str = ""
    rig: str = "rig0"
    site: str = ""

    def __post_init__(self) -> None:
        if self.duration_s is not None and self.duration_s <= 0:
            raise ValueError(f"duration_s must be positive, got {self.duration_s}")
        if not 0.05 <= self.flush_interval_s <= 10:
            raise ValueError(f"flush_interval_s must be in [0.05, 10], got {self.flush_interval_s}")
        if self.queue_max_items < 10 or self.queue_max_mb <= 0:
            raise ValueError("queue_max_items must be >= 10 and queue_max_mb positive")
        if self.rotate_size_mb < 0 or self.rotate_interval_s < 0:
            raise ValueError("rotate_size_mb and rotate_interval_s must be >= 0")
        if self.compression not in ("zstd", "lz4", "none"):
            raise ValueError(f"compression must be zstd, lz4 or none, got {self.compression!r}")


class PreviewSink(Protocol):
    """Where the recorder offers samples and health for the live preview (never blocks)."""

    def offer(self, sample: SourceSample) -> None: ...

    def publish_health(self, health: dict[str, Any]) -> None: ...


@dataclass
class RecordReport:
    """What a recording produced (also summarised in session.yaml)."""

    session_dir: Path
    files: list[Path]
    messages: dict[str, int]
    dropped: dict[str, int]
    stop_reason: str
    duration_s: float
    events: list[str] = field(default_factory=list)
    clean: bool = True
    """False when the last file could not be closed (disk full): recover its `.part`."""


class SampleQueue:
    """A bounded FIFO of samples limited in items and bytes; `put` never blocks."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self._items: collections.deque[SourceSample] = collections.deque()
        self._bytes = 0
        self._max_items = max_items
        self._max_bytes = max_bytes
        self._cond = threading.Condition()
        self.peak_items = 0
        self.peak_bytes = 0

    def put(self, sample: SourceSample, *, force: bool = False) -> bool:
        """Append `sample`; False (and nothing stored) when the queue is full, unless
        `force` (the recorder's own few events are never dropped)."""
        size = sample.size_bytes
        with self._cond:
            full = len(self._items) >= self._max_items or self._bytes + size > self._max_bytes
            if full and not force:
                return False
            self._items.append(sample)
            self._bytes += size
            self.peak_items = max(self.peak_items, len(self._items))
            self.peak_bytes = max(self.peak_bytes, self._bytes)
            self._cond.notify()
            return True

    def get_batch(self, timeout_s: float, max_items: int = 512) -> list[SourceSample]:
        """Up to `max_items` samples, waiting up to `timeout_s` for the first."""
        with self._cond:
            if not self._items:
                self._cond.wait(timeout_s)
            batch: list[SourceSample] = []
            while self._items and len(batch) < max_items:
                sample = self._items.popleft()
                self._bytes -= sample.size_bytes
                batch.append(sample)
            return batch

    def __len__(self) -> int:
        return len(self._items)

    @property
    def bytes(self) -> int:
        return self._bytes


class _TopicStats:
    __slots__ = (
        "count",
        "dropped",
        "last_receive_ns",
        "rate_hz",
        "silent_since_ns",
        "skip_until_key",
        "window_count",
    )

    def __init__(self) -> None:
        self.count = 0
        self.dropped = 0
        self.rate_hz = 0.0
        self.window_count = 0
        self.skip_until_key = False
        self.last_receive_ns = 0
        self.silent_since_ns = 0  # > 0 while the stream is reported silent


class Recorder:
    """Record `sources` into `session_dir` (see the module docstring).

    Raises OutputExistsError when `session_dir` already holds a recording (unless
    `overwrite`), DeviceError when a source cannot be opened at the start.
    """

    def __init__(
        self,
        options: RecorderOptions,
        sources: Sequence[CameraSource],
        session_dir: Path | str,
        *,
        preview: PreviewSink | None = None,
        overwrite: bool = False,
    ) -> None:
        if not sources:
            raise InputError("record: no source given (expected at least one, e.g. 'sim')")
        self.options = options
        self.sources = list(sources)
        self.session_dir = Path(session_dir)
        self.folder = SessionFolder(self.session_dir)
        self.session_id = options.session_id or self.session_dir.resolve().name
        self.preview = preview
        self.overwrite = overwrite
        self._stop = threading.Event()
        self._stop_reason = ""
        self._queue = SampleQueue(options.queue_max_items, int(options.queue_max_mb * 2**20))
        self._stats: dict[str, _TopicStats] = {}
        self._stats_lock = threading.Lock()
        self._events: list[str] = []
        self._source_up: dict[str, bool] = {}
        self._fits: dict[str, dict[str, ClockFit]] = {}
        self._files: list[Path] = []
        self._writer: ArchiveWriter | None = None
        self._file_started = 0.0
        self._started_ns = 0
        self._health: dict[str, Any] = {}
        self._clock = HOST_CLOCK
        self._wall_minus_host_ns = 0
        self._clock_steps: list[dict[str, Any]] = []
        self._lost_at_ns: dict[str, int] = {}
        self._stream_rates = {s.topic: s.rate_hz for src in self.sources for s in src.streams()}
        topics = [s.topic for src in self.sources for s in src.streams()]
        duplicates = sorted({t for t in topics if topics.count(t) > 1})
        if duplicates:
            raise InputError(f"record: several sources write {', '.join(duplicates)}")

    # -- control -------------------------------------------------------------------

    def stop(self, reason: str = "stopped") -> None:
        """Ask the recorder to stop (thread- and signal-safe); `run` then closes the files."""
        if not self._stop_reason:
            self._stop_reason = reason
        self._stop.set()

    def health(self) -> dict[str, Any]:
        """The last health snapshot (rates, drops, disk, sources), as published."""
        return dict(self._health)

    def _record_event(self, kind: str, source: str, details: dict[str, Any]) -> None:
        """Write a `RecorderEvent` on /health (through the queue, never dropped)."""
        now = self._clock.now_ns()
        event = RecorderEvent(
            stamp_ns=now, frame_id=source, kind=kind, yaml_text=yaml.safe_dump(details)
        )
        with self._stats_lock:
            self._stats.setdefault(HEALTH_TOPIC, _TopicStats())
        self._queue.put(SourceSample(HEALTH_TOPIC, event, now), force=True)

    def _event(self, text: str, level: int = logging.WARNING) -> None:
        log.log(level, "%s", text)
        stamp = datetime.now(UTC).strftime("%H:%M:%S")
        with self._stats_lock:
            self._events.append(f"{stamp} {text}")
            del self._events[:-200]  # bounded

    # -- run -----------------------------------------------------------------------

    def run(self) -> RecordReport:
        """Record until stopped, `duration_s` elapsed or the disk is full; the report."""
        self._check_session_dir()
        for source in self.sources:
            source.open()  # DeviceError here: nothing is written
            self._source_up[source.name] = True
        self.session_dir.mkdir(parents=True, exist_ok=True)
        self._started_ns = self._clock.now_ns()
        self._wall_minus_host_ns = self._clock.wall_minus_host_ns()
        self._write_calibration()
        self._write_session_yaml(final=False)
        pumps = [
            threading.Thread(target=self._pump, args=(s,), name=f"pump-{s.name}", daemon=True)
            for s in self.sources
        ]
        clean = True
        try:
            self._open_file()
            for pump in pumps:
                pump.start()
            self._write_loop()
        except OSError as error:
            clean = self._disk_error(error)
        finally:
            self._stop.set()
            for pump in pumps:
                if pump.is_alive():
                    pump.join(timeout=5)
            for source in self.sources:
                try:
                    source.close()
                except WreckmapError as error:
                    log.warning("closing %s: %s", source.name, error)
            if clean:
                try:
                    self._drain_and_close()
                except OSError as error:
                    clean = self._disk_error(error)
        duration_s = seconds_from_ns(self._clock.now_ns() - self._started_ns)
        report = RecordReport(
            session_dir=self.session_dir,
            files=list(self._files),
            messages={t: s.count for t, s in sorted(self._stats.items())},
            dropped={t: s.dropped for t, s in sorted(self._stats.items()) if s.dropped},
            stop_reason=self._stop_reason or "stopped",
            duration_s=duration_s,
            events=list(self._events),
            clean=clean,
        )
        try:
            self._write_session_yaml(final=True, report=report)
        except OSError as error:
            log.error("%s not updated: %s", self.folder.session_yaml, error)
        self._publish_final_health(report)
        return report

    def _publish_final_health(self, report: RecordReport) -> None:
        """One last health message saying the recording stopped, why, and if cleanly
        (the preview page shows it: a full disk must not look like a live recorder)."""
        with self._stats_lock:
            events = self._events[-5:]
        self._health = {
            **self._health,
            "t_ns": self._clock.now_ns(),
            "session": self.session_id,
            "rig": self.options.rig,
            "state": "stopped",
            "stop_reason": report.stop_reason,
            "clean": report.clean,
            "files": len(report.files),
            "events": events,
        }
        if self.preview is not None:
            try:
                self.preview.publish_health(self._health)
            except Exception as error:  # the preview is best effort; the files are done
                log.warning("preview: last health not published (%s)", error)

    def _check_session_dir(self) -> None:
        if not self.session_dir.exists() or self.overwrite:
            return
        existing = sorted(
            p.name
            for p in self.session_dir.iterdir()
            if p.name == self.folder.session_yaml.name or SessionFolder.is_recording_part(p.name)
        )
        if existing:
            raise OutputExistsError(
                f"{self.session_dir}: already holds a recording ({', '.join(existing[:3])}); "
                "choose a new session folder"
            )

    def _pump(self, source: CameraSource) -> None:
        """Read one source into the queue; survive losses (reconnect) and bad iterations."""
        opened = True
        failures = 0
        while not self._stop.is_set():
            if not opened:
                try:
                    source.open()
                except DeviceError as error:
                    log.debug("%s: still absent: %s", source.name, error)
                    self._stop.wait(self.options.reconnect_interval_s)
                    continue
                opened = True
                self._source_up[source.name] = True
                back_ns = self._clock.now_ns()
                lost_ns = self._lost_at_ns.pop(source.name, back_ns)
                gap_s = round(seconds_from_ns(back_ns - lost_ns), 3)
                self._record_event(
                    "source_back",
                    source.name,
                    {"lost_ns": lost_ns, "back_ns": back_ns, "gap_s": gap_s},
                )
                self._event(f"{source.name}: reconnected after {gap_s:.1f} s, recording resumed")
            try:
                samples = source.read(0.1)
                failures = 0
            except DeviceError as error:
                self._source_up[source.name] = False
                lost_ns = self._clock.now_ns()
                self._lost_at_ns[source.name] = lost_ns
                self._record_event(
                    "source_lost", source.name, {"lost_ns": lost_ns, "reason": str(error)}
                )
                self._event(f"{source.name}: lost ({error}); other streams go on, retrying")
                source.close()
                opened = False
                continue
            except Exception:  # a bug or glitch in one read must not end the recording
                failures += 1
                log.exception("%s: read failed (%d in a row)", source.name, failures)
                if failures >= 10:
                    self._source_up[source.name] = False
                    self._event(f"{source.name}: giving up after {failures} failed reads")
                    return
                time.sleep(0.1)
                continue
            for sample in samples:
                self._enqueue(sample)

    def _enqueue(self, sample: SourceSample) -> None:
        stats = self._stats.get(sample.topic)
        if stats is None:
            with self._stats_lock:
                stats = self._stats.setdefault(sample.topic, _TopicStats())
        previous_ns, stats.last_receive_ns = stats.last_receive_ns, sample.receive_ns
        if stats.silent_since_ns:
            stats.silent_since_ns = 0
            gap_s = round(seconds_from_ns(sample.receive_ns - previous_ns), 3)
            self._record_event(
                "source_back",
                sample.topic,
                {"lost_ns": previous_ns, "back_ns": sample.receive_ns, "gap_s": gap_s},
            )
            self._event(f"{sample.topic}: samples again after a {gap_s:.1f} s gap", logging.INFO)
        if stats.skip_until_key and not sample.keyframe:
            stats.dropped += 1
            return
        stats.skip_until_key = False
        if not self._queue.put(sample):
            stats.dropped += 1
            if isinstance(sample.message, CompressedVideo):
                stats.skip_until_key = True
            return
        if self.preview is not None:
            self.preview.offer(sample)

    def _write_loop(self) -> None:
        o = self.options
        last_flush = last_health = time.monotonic()
        deadline = None if o.duration_s is None else last_flush + o.duration_s
        while True:
            batch = self._queue.get_batch(0.05)
            writer = self._writer
            if writer is None:
                raise WreckmapError("recorder: no open file")
            for sample in batch:
                self._write(writer, sample)
            now = time.monotonic()
            if now - last_flush >= o.flush_interval_s:
                writer.flush(fsync=o.fsync)
                last_flush = now
            if now - last_health >= o.health_interval_s:
                self._update_health(now - last_health)
                last_health = now
                if self._rotate_due(writer, now):
                    self._open_file()
            if deadline is not None and now >= deadline:
                self.stop("duration reached")
            if self._stop.is_set():
                return

    def _write(self, writer: ArchiveWriter, sample: SourceSample) -> None:
        writer.write(sample.topic, sample.message, log_time_ns=sample.receive_ns)
        stats = self._stats[sample.topic]
        stats.count += 1
        stats.window_count += 1
        if sample.device_ns is not None:
            device = sample.topic.split("/")[1]
            fits = self._fits.get(device)
            if fits is None:
                fits = self._fits[device] = {"host_sync": ClockFit(), "receive": ClockFit()}
            stamp = sample.message.stamp_ns
            # Fit the recorded stamp (device clock, epoch) against the host's views of it.
            if sample.host_sync_ns is not None:
                fits["host_sync"].add(stamp, sample.host_sync_ns)
            fits["receive"].add(stamp, sample.receive_ns)

    def _rotate_due(self, writer: ArchiveWriter, now: float) -> bool:
        o = self.options
        if o.rotate_size_mb > 0 and writer.bytes_written >= o.rotate_size_mb * 2**20:
            return True
        return o.rotate_interval_s > 0 and now - self._file_started >= o.rotate_interval_s

    def _open_file(self) -> None:
        if self._writer is not None:
            self._writer.close()
        path = self.folder.recording_part(len(self._files))
        self._writer = ArchiveWriter(
            path,
            overwrite=self.overwrite,
            chunk_size=self.options.chunk_size_kb * 1024,
            compression=self.options.compression,
            metadata={
                "session_id": self.session_id,
                "rig": self.options.rig,
                "file_index": str(len(self._files)),
                "recorder": "wreckmap-field record",
            },
        )
        self._files.append(path)
        self._file_started = time.monotonic()
        self._writer.write(
            SESSION_TOPIC,
            SessionInfo(self._clock.now_ns(), self._session_yaml_text(final=False)),
        )
        self._writer.flush(fsync=self.options.fsync)
        log.info("recording to %s", path)

    def _drain_and_close(self) -> None:
        writer = self._writer
        if writer is None:
            return
        for sample in self._queue.get_batch(0.0, max_items=10**9):
            self._write(writer, sample)
        writer.close()
        self._writer = None

    def _disk_error(self, error: OSError) -> bool:
        """Handle a write error; True when the file could still be closed cleanly."""
        full = error.errno in (errno.ENOSPC, errno.EDQUOT)
        what = "disk full" if full else f"write error ({error.strerror or error})"
        self._stop_reason = what
        self._stop.set()
        writer, self._writer = self._writer, None
        if writer is None:
            return False
        try:
            writer.close()
        except OSError:
            part = writer.part_path
            self._event(
                f"{what}: recording stopped; what was written is kept in {part.name} "
                f"(run: wreckmap-field recover {part})",
                logging.ERROR,
            )
            return False
        self._event(f"{what}: recording stopped; {writer.path.name} closed", logging.ERROR)
        return True

    # -- health --------------------------------------------------------------------

    def _check_streams_and_clock(self) -> None:
        """Report streams gone silent (a camera unplugged while the IMU flows, a stalled
        device) and wall-clock steps, on /health and in the log."""
        now = self._clock.now_ns()
        for topic, rate_hz in self._stream_rates.items():
            stats = self._stats.get(topic)
            if stats is None or not stats.count or rate_hz <= 0 or stats.silent_since_ns:
                continue
            silent_s = seconds_from_ns(now - stats.last_receive_ns)
            if silent_s > max(1.0, 5.0 / rate_hz):
                stats.silent_since_ns = stats.last_receive_ns
                self._record_event(
                    "source_lost",
                    topic,
                    {"lost_ns": stats.last_receive_ns, "reason": f"no sample for {silent_s:.1f} s"},
                )
                self._event(f"{topic}: no sample for {silent_s:.1f} s; the other streams go on")
        offset_ns = self._clock.wall_minus_host_ns()
        step_ns = offset_ns - self._wall_minus_host_ns
        if abs(step_ns) > CLOCK_STEP_NS:
            self._wall_minus_host_ns = offset_ns
            entry = {
                "host_ns": now,
                "wall_ns": now + offset_ns,
                "step_s": round(seconds_from_ns(step_ns), 6),
                "wall_minus_host_s": round(seconds_from_ns(offset_ns), 6),
            }
            self._clock_steps.append(entry)
            self._record_event("clock_step", "", entry)
            self._event(
                f"host wall clock stepped {seconds_from_ns(step_ns):+.3f} s; recorded times stay "
                "monotonic (wall = host + {:.3f} s)".format(seconds_from_ns(offset_ns))
            )

    def _update_health(self, window_s: float) -> None:
        self._check_streams_and_clock()
        try:
            free = shutil.disk_usage(self.session_dir).free
        except OSError:
            free = -1
        with self._stats_lock:
            topics = {}
            for topic, stats in sorted(self._stats.items()):
                stats.rate_hz = stats.window_count / window_s if window_s > 0 else 0.0
                stats.window_count = 0
                topics[topic] = {
                    "rate_hz": round(stats.rate_hz, 2),
                    "count": stats.count,
                    "dropped": stats.dropped,
                }
            events = self._events[-5:]
        writer = self._writer
        self._health = {
            "t_ns": self._clock.now_ns(),
            "session": self.session_id,
            "rig": self.options.rig,
            "uptime_s": round(seconds_from_ns(self._clock.now_ns() - self._started_ns), 1),
            "file": writer.path.name if writer is not None else "",
            "file_bytes": writer.bytes_written if writer is not None else 0,
            "files": len(self._files),
            "disk_free_bytes": free,
            "queue_items": len(self._queue),
            "queue_bytes": self._queue.bytes,
            "topics": topics,
            "sources": {name: ("up" if up else "down") for name, up in self._source_up.items()},
            "events": events,
            "state": "recording",
        }
        if self.preview is not None:
            self.preview.publish_health(self._health)
        if 0 <= free < self.options.min_free_mb * 2**20:
            self._event(
                f"disk nearly full ({free / 2**20:.0f} MiB free < {self.options.min_free_mb} MiB): "
                "stopping the recording",
                logging.ERROR,
            )
            self.stop("disk nearly full")

    # -- session folder ------------------------------------------------------------

    def _write_calibration(self) -> None:
        for source in self.sources:
            calib = source.calibration()
            if calib is None:
                continue
            cameras, imu = calib
            if cameras:
                self.folder.write_camchain(cameras, overwrite=self.overwrite)
            if imu is not None:
                self.folder.write_imu_noise(imu, overwrite=self.overwrite)
            return  # one calibration per session (the first source that has one)

    def _session_yaml_text(self, *, final: bool, report: RecordReport | None = None) -> str:
        folder = self.folder
        doc: dict[str, Any] = {
            "id": self.session_id,
            "site": self.options.site,
            "rig": self.options.rig,
            "host": socket.gethostname(),
            "start_utc": _iso(self._started_ns),
            "devices": [source.describe() for source in self.sources],
            "streams": [
                {
                    "topic": s.topic,
                    "kind": s.kind,
                    "rate_hz": s.rate_hz,
                    "codec": s.codec,
                    "width_px": s.width_px,
                    "height_px": s.height_px,
                    "device": s.device,
                }
                for source in self.sources
                for s in source.streams()
            ],
            "clocks": self._clock_doc(),
            "calibration": {
                "camchain": folder.relative(folder.camchain) if folder.camchain.exists() else None,
                "imu": folder.relative(folder.imu_yaml) if folder.imu_yaml.exists() else None,
            },
            "recorder": {
                k: v
                for k, v in vars(self.options).items()
                if k not in ("session_id", "rig", "site")
            },
            "recordings": [p.name for p in self._files],
        }
        if final and report is not None:
            doc["end_utc"] = _iso(self._clock.now_ns())
            doc["stop_reason"] = report.stop_reason
            doc["clean"] = report.clean
            doc["messages"] = report.messages
            doc["dropped"] = report.dropped
            doc["events"] = report.events[-50:]
            doc["clock_steps"] = list(self._clock_steps)
        return "# wreckmap session (written by wreckmap-field record)\n" + yaml.safe_dump(
            doc, sort_keys=False, default_flow_style=False
        )

    def _clock_doc(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "host": {
                "description": "MCAP log time: host time when a sample was received, ns "
                "since the epoch: the wall clock read at start carried by the monotonic clock "
                "(never steps); wall-clock steps are on /health and under clock_steps",
            }
        }
        for device, fits in sorted(self._fits.items()):
            entry: dict[str, Any] = {
                "description": "header.stamp of this topic: the device clock moved "
                "to the epoch by one offset; fits map it to the host clock "
                "(t_host = t + offset + drift*(t - reference))",
            }
            for name, fit in fits.items():
                estimate = fit.estimate()
                if estimate is not None:
                    entry[f"to_{name}"] = estimate.as_dict()
            doc[device] = entry
        return doc

    def _write_session_yaml(self, *, final: bool, report: RecordReport | None = None) -> None:
        write_text_atomic(
            self.folder.session_yaml,
            self._session_yaml_text(final=final, report=report),
            overwrite=final or self.overwrite,
        )


def _iso(t_ns: int) -> str:
    return datetime.fromtimestamp(seconds_from_ns(t_ns), UTC).isoformat(timespec="milliseconds")
