"""Benchmark: every field fault, many trials each, and what survives it.

Faults (each `--trials` times, default 20, seeded):
- sigkill: `wreckmap-field record --source sim` killed at a random moment, then `recover`;
  lost = seconds of IMU between the last recovered sample and the kill.
- disk watermark: recording onto a size-limited tmpfs with `--min-free-mb`; lost =
  messages the recorder counted that are not in its closed files.
- disk ENOSPC: the same card with the watermark off, then `recover` of the `.part`;
  lost = seconds of IMU counted by the recorder but not recovered.
- camera unplug: the simulated rig's cameras vanish for 0.5-2 s while its IMU flows;
  lost = IMU samples missing (the IMU must not notice), and the camera's extra gap
  beyond the outage (time to recover).
- clock step: the wall clock jumps by a random +-1 s..+-3 h mid-recording; lost = log
  times that go backwards or IMU holes; the step must be on /health.
- download cut: the dive computer's cable pulled after a random byte, then a re-run;
  lost / duplicated / corrupt dives after the re-run.
- power loss: a closed archive cut at a random offset inside a chunk, a message index,
  the summary or the footer, then `recover`; lost = messages of whole chunks before the
  cut that were not recovered, corrupt = outputs the mcap library cannot read.

Needs root for the tmpfs cases (skipped with a note otherwise).

    .venv/bin/python bench/bench_faults.py
    .venv/bin/python bench/bench_faults.py --trials 5 --only sigkill,power
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

IMU_HZ = 400.0


@dataclass
class Row:
    fault: str
    trials: int = 0
    kept: list[float] = field(default_factory=list)
    lost: list[float] = field(default_factory=list)
    recover_s: list[float] = field(default_factory=list)
    corrupt: int = 0
    duplicates: int = 0
    unit: str = ""
    note: str = ""


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "field.cli", *args]


def env() -> dict[str, str]:
    out = dict(os.environ)
    out["WRECKMAP_PROGRESS"] = "0"
    out["PYTHONPATH"] = str(REPO) + os.pathsep + out.get("PYTHONPATH", "")
    return out


def sim_args(options: dict[str, Any]) -> list[str]:
    out = []
    for key, value in options.items():
        out += ["--source-option", f"sim.{key}={value}"]
    return out


@contextmanager
def tmpfs(folder: Path, size_kib: int) -> Any:
    folder.mkdir(parents=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(folder)],
                   check=True)  # fmt: skip
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def reported(stdout: str, topic: str) -> int:
    for line in stdout.splitlines():
        if line.strip().startswith(f"{topic}:"):
            return int(line.split(":")[1].split(",")[0])
    raise RuntimeError(f"no count for {topic} in: {stdout}")


def imu_of(path: Path) -> np.ndarray:
    from shared.archive import ArchiveReader

    with ArchiveReader(path) as reader:
        return reader.read_imu("/imu0").log_times_ns


# -- the faults ----------------------------------------------------------------


def sigkill(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from field.record.recover import recover
    from shared.archive.writer import part_path
    from shared.clock import seconds_from_ns
    from shared.folders import SessionFolder

    out = work / f"kill{row.trials}"
    proc = subprocess.Popen(
        cli("record", "--source", "sim", "--out", str(out), "--duration", "30", *sim_args(sim)),
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env(),
    )  # fmt: skip
    part = part_path(SessionFolder(out).recording_part(0))
    deadline = time.monotonic() + 120
    while not (part.exists() and part.stat().st_size > 0) and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(rng.uniform(0.7, 4.0))
    killed_ns = time.time_ns()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    t0 = time.monotonic()
    report = recover(part)
    row.recover_s.append(time.monotonic() - t0)
    logs = imu_of(report.output)
    row.kept.append(len(logs) / IMU_HZ)
    row.lost.append(max(seconds_from_ns(killed_ns - int(logs[-1])), 0.0))


def disk_watermark(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from shared.archive import ArchiveReader
    from shared.folders import SessionFolder

    size = rng.choice([1024, 1536, 2048])
    with tmpfs(work / f"card{row.trials}", size) as card:
        t0 = time.monotonic()
        run = subprocess.run(
            cli("record", "--source", "sim", "--out", str(card / "s"), "--duration", "120",
                "--min-free-mb", "1", *sim_args(sim)),
            capture_output=True, text=True, env=env(), timeout=300,
        )  # fmt: skip
        stopped_s = time.monotonic() - t0
        counted = sum(reported(run.stdout, t) for t in ("/imu0", "/cam0/video", "/depth0"))
        in_files = 0
        for path in SessionFolder(card / "s").recording_parts():
            with ArchiveReader(path) as reader:
                in_files += sum(
                    t.message_count for name, t in reader.topics().items() if name != "/session"
                )
        if run.returncode != 3 or list((card / "s").glob("*.part")):
            row.corrupt += 1
        row.kept.append(in_files)
        row.lost.append(counted - in_files)
        row.recover_s.append(0.0)
        row.note = f"stopped after {stopped_s:.1f} s on a {size} KiB card (last trial)"


def disk_enospc(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from field.record.recover import recover
    from shared.folders import SessionFolder

    size = rng.choice([512, 768, 1024])
    with tmpfs(work / f"full{row.trials}", size) as card:
        run = subprocess.run(
            cli("record", "--source", "sim", "--out", str(card / "s"), "--duration", "120",
                "--min-free-mb", "0", *sim_args(sim)),
            capture_output=True, text=True, env=env(), timeout=300,
        )  # fmt: skip
        counted = reported(run.stdout, "/imu0")
        parts = list((card / "s").glob("*.part"))
        t0 = time.monotonic()
        if parts:
            path = recover(parts[0], work / f"recovered{row.trials}.mcap").output
        else:
            path = SessionFolder(card / "s").recording_parts()[-1]
        row.recover_s.append(time.monotonic() - t0)
        logs = imu_of(path)
        if np.any(np.diff(logs) < 0):
            row.corrupt += 1
        row.kept.append(len(logs) / IMU_HZ)
        row.lost.append((counted - len(logs)) / IMU_HZ)


def _in_process_recording(
    sim: dict[str, Any], out: Path, extra: dict[str, Any], duration_s: float
) -> Any:
    from field.record.recorder import Recorder, RecorderOptions
    from field.record.sources.base import make_source

    source = make_source("sim", {**sim, **extra})
    options = RecorderOptions(duration_s=duration_s, health_interval_s=0.2, min_free_mb=0.0)
    return Recorder(options, [source], out).run()


def camera_unplug(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from field.record.inspect import inspect_file
    from shared.archive import ArchiveReader
    from shared.clock import seconds_from_ns

    outage_s = rng.uniform(0.5, 2.0)
    extra = {"camera_unplug_at_s": rng.uniform(0.5, 1.5), "camera_unplug_for_s": outage_s}
    report = _in_process_recording(sim, work / f"unplug{row.trials}", extra, 3.5)
    (path,) = report.files
    with ArchiveReader(path) as reader:
        imu = reader.read_imu("/imu0").stamps_ns
        video = np.array([m.stamp_ns for _, _, m in reader.messages(["/cam0/video"])])
    holes = seconds_from_ns(np.diff(imu))
    missing_imu = int(np.sum(np.round(holes * IMU_HZ) - 1))
    camera_gap_s = seconds_from_ns(int(np.diff(video).max()))
    gaps = [e for e in inspect_file(path).source_gaps if e.source == "/cam0/video"]
    if outage_s > 1.0 and not gaps:
        row.corrupt += 1  # an outage longer than the silence limit must be on /health
    row.kept.append(len(imu) / IMU_HZ)
    row.lost.append(missing_imu)
    row.recover_s.append(max(camera_gap_s - outage_s, 0.0))


def clock_step(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from field.record.inspect import inspect_file
    from shared.archive import iter_records_salvage
    from shared.clock import ns_from_seconds, seconds_from_ns

    step_s = rng.choice([-1, 1]) * 10 ** rng.uniform(0, np.log10(3 * 3600))
    at_s = rng.uniform(0.5, 2.0)
    step_ns, at_ns = ns_from_seconds(step_s), ns_from_seconds(at_s)
    real = time.time_ns
    start = real()

    def wall_ns() -> int:
        now = real()
        return now + (step_ns if now - start > at_ns else 0)

    time.time_ns = wall_ns
    try:
        report = _in_process_recording(sim, work / f"step{row.trials}", {}, 3.0)
    finally:
        time.time_ns = real
    (path,) = report.files
    logs = np.array([r.log_time_ns for r in iter_records_salvage(path)], dtype=np.int64)
    backwards = int(np.count_nonzero(np.diff(logs) < 0))
    from shared.archive import ArchiveReader

    with ArchiveReader(path) as reader:
        imu = reader.read_imu("/imu0").stamps_ns  # sensor stamps: receive times jitter
    holes = int(np.count_nonzero(seconds_from_ns(np.diff(imu)) > 3 / IMU_HZ))
    steps = [e.details["step_s"] for e in inspect_file(path).clock_steps]
    if len(steps) != 1 or abs(steps[0] - step_s) > 0.1:
        row.corrupt += 1  # the step must be recorded, once, with its size
    row.kept.append(len(imu) / IMU_HZ)
    row.lost.append(backwards + holes)
    row.recover_s.append(0.0)


def download_cut(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from field.divecomputer.download import DownloadOptions, download_dives
    from field.divecomputer.simulator import (
        FaultOptions,
        LineFaults,
        SimulatedShearwater,
        serving_pty,
        synthetic_dives,
    )
    from shared.errors import DeviceError
    from shared.formats.diveprofile import read_dive_index, write_dive

    quick = DownloadOptions(
        settle_s=0.02, read_timeout_s=0.2, backoff_s=0.0, backoff_max_s=0.0, session_retries=1
    )

    def unit() -> Any:
        return SimulatedShearwater("perdix-ai", synthetic_dives(6, seed=31, duration_s=300))

    if not hasattr(download_cut, "total"):
        line = LineFaults(FaultOptions())
        with serving_pty(unit(), line) as port:
            download_dives(port, work / "dc-full", quick)
        download_cut.total = line.bytes_sent  # type: ignore[attr-defined]
        truth = work / "dc-truth"
        for profile, raw in unit().held_dives():
            write_dive(truth, profile, raw=raw)
        download_cut.truth = truth  # type: ignore[attr-defined]
    total: int = download_cut.total  # type: ignore[attr-defined]
    truth = download_cut.truth  # type: ignore[attr-defined]
    folder = work / f"dc{row.trials}"
    cut = rng.randrange(1, total)
    cable = LineFaults(FaultOptions(disconnect_after_bytes=cut))
    with serving_pty(unit(), cable) as port, suppress(DeviceError):
        download_dives(port, folder, quick)
    kept = len(read_dive_index(folder)) if (folder / "dives.json").exists() else 0
    t0 = time.monotonic()
    with serving_pty(unit()) as port:
        download_dives(port, folder, quick)
    row.recover_s.append(time.monotonic() - t0)
    index = read_dive_index(folder)
    fingerprints = [e["fingerprint"] for e in index]
    row.duplicates += len(fingerprints) - len(set(fingerprints))
    want = {e["fingerprint"]: e for e in read_dive_index(truth)}
    for entry in index:
        ref = want.get(entry["fingerprint"])
        if ref is None or any(
            (folder / entry[k]).read_bytes() != (truth / ref[k]).read_bytes()
            for k in ("csv", "raw")
        ):
            row.corrupt += 1
    row.kept.append(kept)
    row.lost.append(len(want) - len(set(fingerprints) & set(want)))
    row.unit = "dives"


def power_loss(row: Row, rng: random.Random, work: Path, sim: dict[str, Any]) -> None:
    from mcap.reader import make_reader

    from field.record.recover import recover
    from shared.archive import ArchiveWriter, Imu
    from shared.errors import InputError

    source = work / "closed.mcap"
    if not source.exists():
        with ArchiveWriter(source, chunk_size=1 << 30) as writer:
            for k in range(1200):
                stamp = 1_700_000_000_000_000_000 + k * 5_000_000
                imu = Imu(stamp, "imu0", np.array([k, 0.0, 0.0]), np.array([0.0, 0.0, 9.81]))
                writer.write("/imu0", imu, log_time_ns=stamp)
                if (k + 1) % 100 == 0:
                    writer.flush(fsync=True)
    data = source.read_bytes()
    spans = []
    position = 8
    while position < len(data) - 8:
        opcode = data[position]
        end = position + 9 + struct.unpack_from("<Q", data, position + 1)[0]
        spans.append((opcode, position, end))
        position = end
    kind = ["chunk", "index", "summary", "footer"][row.trials % 4]
    if kind == "chunk":
        candidates = [(s + 1, e) for op, s, e in spans if op == 0x06]
    elif kind == "index":
        candidates = [(s + 1, e) for op, s, e in spans if op == 0x07]
    elif kind == "summary":
        data_end = next(s for op, s, _ in spans if op == 0x0F)
        candidates = [(data_end, next(s for op, s, _ in spans if op == 0x02))]
    else:
        candidates = [(next(s for op, s, _ in spans if op == 0x02), len(data))]
    start, end = rng.choice(candidates)
    cut = rng.randrange(start, end)
    whole = 100 * sum(1 for op, _, e in spans if op == 0x06 and e <= cut)
    part = work / f"cut{row.trials}.mcap.part"
    part.write_bytes(data[:cut])
    t0 = time.monotonic()
    try:
        report = recover(part, work / f"cut{row.trials}.mcap")
    except InputError:
        row.recover_s.append(time.monotonic() - t0)
        row.kept.append(0)
        row.lost.append(whole)  # 0 unless whole chunks were there
        return
    row.recover_s.append(time.monotonic() - t0)
    try:
        with report.output.open("rb") as f:
            count = sum(1 for _ in make_reader(f).iter_messages())
    except Exception:
        row.corrupt += 1
        count = 0
    row.kept.append(count)
    row.lost.append(max(whole - count, 0))
    row.unit = "messages"


FAULTS: dict[str, tuple[Callable[..., None], str, bool]] = {
    "sigkill": (sigkill, "s of IMU", False),
    "disk-watermark": (disk_watermark, "messages", True),
    "disk-enospc": (disk_enospc, "s of IMU", True),
    "camera-unplug": (camera_unplug, "IMU samples", False),
    "clock-step": (clock_step, "bad stamps", False),
    "download-cut": (download_cut, "dives", False),
    "power-loss": (power_loss, "messages", False),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=20, help="trials per fault")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--only", help="comma-separated faults (default: all): " + ",".join(FAULTS))
    args = parser.parse_args()
    os.environ["WRECKMAP_PROGRESS"] = "0"
    import logging

    logging.disable(logging.WARNING)
    from field.record.sources.sim import SMALL_RIG, SimOptions, prepare_clip

    chosen = list(FAULTS) if not args.only else [f.strip() for f in args.only.split(",")]
    unknown = set(chosen) - set(FAULTS)
    if unknown:
        parser.error(f"unknown fault(s): {', '.join(sorted(unknown))}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-faults-") as tmp:
        work = Path(tmp)
        cache = work / "cache"
        prepare_clip(SimOptions(**SMALL_RIG, cache_dir=str(cache)))
        sim = {**SMALL_RIG, "cache_dir": str(cache)}
        for name in chosen:
            function, unit, needs_root = FAULTS[name]
            row = Row(name, unit=unit)
            if needs_root and os.geteuid() != 0:
                row.note = "skipped: needs root for a tmpfs"
                rows.append(row)
                continue
            rng = random.Random(f"{args.seed}-{name}")
            folder = work / name
            folder.mkdir()
            started = time.monotonic()
            for _ in range(args.trials):
                function(row, rng, folder, sim)
                row.trials += 1
            print(f"{name}: {row.trials} trials in {time.monotonic() - started:.1f} s",
                  file=sys.stderr)  # fmt: skip
            rows.append(row)
    print(
        f"\n{'fault':<15} {'trials':>6} {'kept (median)':>14} {'lost (max)':>11} "
        f"{'unit':<12} {'corrupt':>7} {'dup':>4} {'recover s (max)':>15}"
    )
    for row in rows:
        if not row.trials:
            print(f"{row.fault:<15} {0:>6}  {row.note}")
            continue
        print(
            f"{row.fault:<15} {row.trials:>6} {np.median(row.kept):>14.2f} "
            f"{max(row.lost):>11.3f} {row.unit:<12} {row.corrupt:>7} {row.duplicates:>4} "
            f"{max(row.recover_s):>15.3f}"
        )
    for row in rows:
        if row.note and row.trials:
            print(f"  {row.fault}: {row.note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
