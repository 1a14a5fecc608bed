"""GoPro telemetry parse time: the two real files, one synthetic hour, one sparse 4+ GB file.

Run: .venv/bin/python bench/bench_gpmf.py [--hours 1.0] [--gigabytes 4.5]
Prints, for each file: MP4 size, telemetry payloads and IMU samples, and the
wall time of `read_telemetry` (moov index + every GPMF payload + per-sample
times + scaling), best of 3. The synthetic files hold 200 Hz ACCL and GYRO
in 1.001 s payloads at 29.97 fps, written by `write_gopro_mp4`; the large one
has its video bytes left as a hole in a sparse file (only the layout matters
to the reader, which never reads video), so it costs no disk space.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path
from typing import BinaryIO

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from field.gopro import writer
from field.gopro.telemetry import read_telemetry

FPS = Fraction(30000, 1001)
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "gopro"


class Hole(bytes):
    """A video packet whose bytes are never written (a hole in a sparse file)."""

    size: int

    def __new__(cls, size: int) -> Hole:
        packet = super().__new__(cls, b"")
        packet.size = size
        return packet

    def __len__(self) -> int:
        return self.size


class Holes(Sequence[bytes]):
    def __init__(self, count: int, size: int) -> None:
        self.length, self.packet = count, Hole(size)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index):  # type: ignore[no-untyped-def]
        if isinstance(index, slice):
            return [self.packet] * len(range(*index.indices(self.length)))
        if not -self.length <= index < self.length:
            raise IndexError(index)
        return self.packet


def _sparse_write_all(
    out: BinaryIO,
    ftyp: bytes,
    mdat_header: bytes,
    order: list[tuple[str, int]],
    video_packets: Sequence[bytes],
    gpmf_payloads: Sequence[bytes],
    moov: bytes,
) -> None:
    out.write(ftyp + mdat_header)
    for kind, index in order:
        if kind == "v":
            out.seek(len(video_packets[index]), 1)
        else:
            out.write(gpmf_payloads[index])
    out.write(moov)


def synthetic_payloads(hours: float) -> list[bytes]:
    rng = np.random.default_rng(0)
    n_payloads = int(hours * 3600 / 1.001)
    payloads = []
    total = 0
    for p in range(n_payloads):
        first = round(p * 1.001 * 200)
        n = round((p + 1) * 1.001 * 200) - first
        payloads.append(
            writer.encode_gpmf_imu_payload(
                accl_mps2=rng.normal(0, 1, (n, 3)) + np.array([9.81, 0, 0]),
                gyro_rads=rng.normal(0, 0.2, (n, 3)),
                accl_first_us=round(first / 200 * 1e6),
                gyro_first_us=round(first / 200 * 1e6),
                accl_total_before=total,
                gyro_total_before=total,
            )
        )
        total += n
    return payloads


def write_synthetic(path: Path, payloads: list[bytes], video_bytes: int) -> Path:
    frames = round(len(payloads) * 30)
    packet = max(16, video_bytes // frames)
    keyframes = [i % 30 == 0 for i in range(frames)]
    sparse = video_bytes > 100_000_000
    packets: Sequence[bytes] = Holes(frames, packet) if sparse else [b"\0" * packet] * frames
    original: Callable[..., None] = writer._write_all
    if sparse:
        writer._write_all = _sparse_write_all
    try:
        writer.write_gopro_mp4(
            path,
            video_packets=packets,
            sps=b"\x67\x42\xc0\x0d",
            pps=b"\x68\xce",
            width=1920,
            height=1080,
            fps=FPS,
            keyframe_flags=keyframes,
            gpmf_payloads=payloads,
            creation_time=datetime(2026, 1, 1, tzinfo=UTC),
        )
    finally:
        writer._write_all = original
    return path


def measure(path: Path, repeats: int = 3) -> None:
    best = float("inf")
    telemetry = None
    for _ in range(repeats):
        start = time.perf_counter()
        telemetry = read_telemetry(path, keys={"ACCL", "GYRO"})
        best = min(best, time.perf_counter() - start)
    assert telemetry is not None
    samples = sum(s.samples for s in telemetry.streams.values())
    size_gb = path.stat().st_size / 1e9
    hours = telemetry.video_duration_s / 3600
    print(
        f"{path.name:<22} {size_gb:8.3f} GB {telemetry.payloads:6d} payloads "
        f"{samples:9d} IMU samples  {best * 1e3:9.1f} ms  "
        f"{best / max(size_gb, 1e-9):8.3f} s/GB  {best / max(hours, 1e-9):7.2f} s/hour"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--hours", type=float, default=1.0, help="synthetic recording length")
    parser.add_argument("--gigabytes", type=float, default=4.5, help="size of the sparse file")
    args = parser.parse_args()
    print("read_telemetry(ACCL, GYRO), best of 3")
    for name in ("karma.mp4", "max-heromode.mp4"):
        measure(SHARED / name)
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        payloads = synthetic_payloads(args.hours)
        elapsed = time.perf_counter() - start
        print(f"(encoded {len(payloads)} synthetic payloads in {elapsed:.1f} s)")
        measure(write_synthetic(Path(folder) / "synthetic_1h.mp4", payloads, 20_000_000))
        big = write_synthetic(
            Path(folder) / "synthetic_sparse.mp4", payloads, int(args.gigabytes * 1e9)
        )
        measure(big)


if __name__ == "__main__":
    main()
