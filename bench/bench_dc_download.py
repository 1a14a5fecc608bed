"""Dive-computer download over a pty from the simulated Shearwater: speed under line faults.

Run: .venv/bin/python bench/bench_dc_download.py
Prints, per case, the wall time, the reply packets the unit sent and the compression ratio.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from field.divecomputer import protocol
from field.divecomputer.download import DownloadOptions, download_dives
from field.divecomputer.simulator import (
    FaultOptions,
    LineFaults,
    SimulatedShearwater,
    serving_pty,
    synthetic_dives,
)

os.environ.setdefault("WRECKMAP_PROGRESS", "0")
DIVES = synthetic_dives(10, seed=1, duration_s=3600.0)


def run_case(name: str, faults: FaultOptions, options: DownloadOptions) -> None:
    device = SimulatedShearwater("perdix-ai", DIVES)
    line = LineFaults(faults)
    with serving_pty(device, line) as port, tempfile.TemporaryDirectory() as folder:
        begin = time.perf_counter()
        result = download_dives(port, Path(folder), options)
        elapsed = time.perf_counter() - begin
    print(
        f"{name:<28} {elapsed:6.2f} s  {len(result.written)} dives  {line.packets:5d} replies  "
        f"dropped {line.dropped:5d}  corrupted {line.corrupted:5d}"
    )


def main() -> None:
    plain = sum(len(log) for log in SimulatedShearwater("perdix-ai", DIVES).logs)
    packed = sum(
        sum(len(b) for b in protocol.compress_dive(log))
        for log in SimulatedShearwater("perdix-ai", DIVES).logs
    )
    print(
        f"10 one-hour dives at 10 s: {plain} log bytes, {packed} compressed ({plain / packed:.1f}x)"
    )
    fast = DownloadOptions(settle_s=0.0, read_timeout_s=0.3, backoff_s=0.0, backoff_max_s=0.0)
    run_case("clean", FaultOptions(), fast)
    run_case("clean, verify", FaultOptions(), replace(fast, verify=True))
    run_case("0.1% dropped", FaultOptions(drop_rate=0.001), replace(fast, block_retries=20))
    run_case("1% dropped", FaultOptions(drop_rate=0.01), replace(fast, block_retries=80))
    run_case(
        "1% corrupted, verify",
        FaultOptions(corrupt_rate=0.01),
        replace(fast, block_retries=80, verify=True),
    )


if __name__ == "__main__":
    main()
