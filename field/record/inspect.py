"""What a recording holds: topics, counts, rates, time span, gaps and clock consistency.

For each topic: message count, rate from the header stamps (sensor clock), the log-time
span, gaps where consecutive header stamps are more than two nominal periods apart (the
nominal period is the median interval), and the relation of the two clocks in the file:
`log_time - header.stamp` (host receive minus sensor time: the latency plus the clock
offset), its mean and spread, and its drift in ppm (slope of a line fit over the
recording). A drift of tens of ppm is the device clock's; jumps show as a large spread.

The recorder's own events on /health are listed as they were recorded: sources lost and
back (with the gap), and wall-clock steps (the recorded times stay monotonic; the event
says how the wall clock moved against them).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from shared.archive import HEALTH_TOPIC, ArchiveReader, Imu, RecorderEvent
from shared.clock import NS_PER_S, seconds_from_ns
from shared.errors import InputError


@dataclass
class Gap:
    """A stretch with no sample: starts after the sample stamped `after_ns`, lasts `length_s`."""

    after_ns: int
    length_s: float


@dataclass
class TopicReport:
    """One topic (times: ns since epoch; rates in Hz; clock figures in ms and ppm)."""

    topic: str
    schema: str
    count: int
    first_log_ns: int
    last_log_ns: int
    rate_hz: float
    period_s: float
    gaps: list[Gap] = field(default_factory=list)
    latency_mean_ms: float | None = None
    latency_std_ms: float | None = None
    latency_min_ms: float | None = None
    latency_max_ms: float | None = None
    clock_drift_ppm: float | None = None
    stamps_backwards: int = 0


@dataclass
class HealthEvent:
    """One recorder event from /health: `kind` (see shared.archive.EVENT_KINDS), the
    source or topic concerned, host time (ns), and its details (times ns, lengths s)."""

    kind: str
    source: str
    stamp_ns: int
    details: dict[str, Any]


@dataclass
class InspectReport:
    """One file."""

    path: Path
    size_bytes: int
    indexed: bool
    complete: bool
    first_ns: int
    last_ns: int
    topics: list[TopicReport]
    metadata: dict[str, dict[str, str]]
    warnings: list[str] = field(default_factory=list)
    events: list[HealthEvent] = field(default_factory=list)

    @property
    def clock_steps(self) -> list[HealthEvent]:
        """The wall-clock steps the recorder saw."""
        return [e for e in self.events if e.kind == "clock_step"]

    @property
    def source_gaps(self) -> list[HealthEvent]:
        """Sources or streams that came back after a loss (`details['gap_s']`)."""
        return [e for e in self.events if e.kind == "source_back"]

    def as_dict(self) -> dict[str, Any]:
        doc = asdict(self)
        doc["path"] = str(self.path)
        doc["duration_s"] = round(seconds_from_ns(self.last_ns - self.first_ns), 6)
        return doc


def _topic_report(topic: str, schema: str, stamps: np.ndarray, logs: np.ndarray) -> TopicReport:
    count = int(stamps.size)
    report = TopicReport(
        topic=topic,
        schema=schema,
        count=count,
        first_log_ns=int(logs.min()) if count else 0,
        last_log_ns=int(logs.max()) if count else 0,
        rate_hz=0.0,
        period_s=0.0,
    )
    if count < 2:
        return report
    order = np.argsort(logs, kind="stable")
    stamps, logs = stamps[order], logs[order]
    intervals = np.diff(stamps)
    report.stamps_backwards = int(np.count_nonzero(intervals < 0))
    sorted_stamps = np.sort(stamps)
    span_s = seconds_from_ns(int(sorted_stamps[-1]) - int(sorted_stamps[0]))
    report.rate_hz = (count - 1) / span_s if span_s > 0 else 0.0
    positive = np.diff(sorted_stamps)
    period = float(np.median(positive)) if positive.size else 0.0
    report.period_s = period / NS_PER_S  # a median: half ns possible
    if period > 0:
        for i in np.nonzero(positive > 2 * period)[0]:
            report.gaps.append(
                Gap(after_ns=int(sorted_stamps[i]), length_s=seconds_from_ns(int(positive[i])))
            )
    # Clock consistency: receive (log) time minus sensor time.
    delta = (logs - stamps).astype(np.float64)
    report.latency_mean_ms = float(delta.mean()) * 1e-6
    report.latency_std_ms = float(delta.std()) * 1e-6
    report.latency_min_ms = float(delta.min()) * 1e-6
    report.latency_max_ms = float(delta.max()) * 1e-6
    x_s = seconds_from_ns(stamps - stamps[0])
    if x_s.max() - x_s.min() >= 2.0:  # shorter spans give noise, not drift
        slope_ns_per_s = np.polyfit(x_s, delta, 1)[0]
        report.clock_drift_ppm = float(slope_ns_per_s) * 1e-3
    return report


def inspect_file(path: Path | str) -> InspectReport:
    """Inspect one `.mcap` (a `.part` is read in salvage mode and marked incomplete)."""
    target = Path(path)
    partial = target.name.endswith(".part")
    with ArchiveReader(target, salvage=partial) as reader:
        topics = reader.topics()
        reports = []
        events = []
        for topic, info in topics.items():
            if topic == HEALTH_TOPIC and info.schema_name == RecorderEvent.ROS_TYPE_NAME:
                for _, _, message in reader.messages([topic]):
                    if not isinstance(message, RecorderEvent):
                        continue
                    try:
                        details = yaml.safe_load(message.yaml_text) or {}
                    except yaml.YAMLError:
                        details = {"text": message.yaml_text}
                    if not isinstance(details, dict):
                        details = {"text": message.yaml_text}
                    events.append(
                        HealthEvent(message.kind, message.frame_id, message.stamp_ns, details)
                    )
                continue
            if info.schema_name == Imu.ROS_TYPE_NAME:
                series = reader.read_imu(topic)
                stamps, logs = series.stamps_ns, series.log_times_ns
            else:
                pairs = [(m.stamp_ns, t) for _, t, m in reader.messages([topic])]
                stamps = np.array([p[0] for p in pairs], dtype=np.int64)
                logs = np.array([p[1] for p in pairs], dtype=np.int64)
            reports.append(_topic_report(topic, info.schema_name, stamps, logs))
        if not reports:
            raise InputError(f"{target}: no messages")
        return InspectReport(
            path=target,
            size_bytes=target.stat().st_size,
            indexed=reader.indexed,
            complete=not partial and reader.indexed,
            first_ns=min(r.first_log_ns for r in reports),
            last_ns=max(r.last_log_ns for r in reports),
            topics=reports,
            metadata=reader.metadata(),
            warnings=list(reader.warnings),
            events=events,
        )


def inspect_path(path: Path | str) -> list[InspectReport]:
    """Inspect a file, or every recording (`*.mcap`, `*.mcap.part`) of a session folder."""
    target = Path(path)
    if target.is_dir():
        files = sorted(target.glob("*.mcap")) + sorted(target.glob("*.mcap.part"))
        if not files:
            raise InputError(f"{target}: no .mcap recording in this folder")
        return [inspect_file(f) for f in files]
    if not target.is_file():
        raise InputError(f"{target}: no such file (expected a .mcap recording or a session folder)")
    return [inspect_file(target)]


def format_report(report: InspectReport) -> str:
    """A text table of one report."""
    duration = seconds_from_ns(report.last_ns - report.first_ns)
    state = "complete, indexed" if report.complete else "NOT CLOSED (run wreckmap-field recover)"
    lines = [
        f"{report.path}: {report.size_bytes / 2**20:.1f} MiB, {duration:.2f} s, {state}",
        f"{'topic':<14} {'count':>7} {'rate Hz':>8} {'gaps':>5} {'max gap s':>9} "
        f"{'lat ms':>8} {'±ms':>7} {'drift ppm':>9}",
    ]
    for t in report.topics:
        max_gap = max((g.length_s for g in t.gaps), default=0.0)
        lat = "" if t.latency_mean_ms is None else f"{t.latency_mean_ms:8.2f}"
        std = "" if t.latency_std_ms is None else f"{t.latency_std_ms:7.2f}"
        drift = "" if t.clock_drift_ppm is None else f"{t.clock_drift_ppm:9.2f}"
        lines.append(
            f"{t.topic:<14} {t.count:>7} {t.rate_hz:>8.2f} {len(t.gaps):>5} {max_gap:>9.3f} "
            f"{lat:>8} {std:>7} {drift:>9}"
        )
        if t.stamps_backwards:
            lines.append(f"  {t.topic}: {t.stamps_backwards} header stamps go backwards")
    for event in report.events:
        at = seconds_from_ns(event.stamp_ns - report.first_ns)
        if event.kind == "source_back":
            gap = event.details.get("gap_s", float("nan"))
            lines.append(f"gap: {event.source} back after {gap:.2f} s (at +{at:.2f} s)")
        elif event.kind == "source_lost":
            why = event.details.get("reason", "")
            lines.append(f"lost: {event.source} at +{at:.2f} s ({why})")
        elif event.kind == "clock_step":
            step = event.details.get("step_s", float("nan"))
            lines.append(
                f"clock step: host wall clock {step:+.3f} s at +{at:.2f} s "
                "(recorded times unaffected)"
            )
        else:
            lines.append(f"{event.kind}: {event.source} at +{at:.2f} s {event.details}")
    lines += [f"warning: {w}" for w in report.warnings[:10]]
    return "\n".join(lines)
