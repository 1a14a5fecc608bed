"""Archive writer/reader throughput: IMU messages and 200 kB video packets, both writers.

Run: .venv/bin/python bench/bench_archive.py [--imu-messages N] [--video-packets N]

Writes the same streams with both record writers of `ArchiveWriter` in one
run (`engine="mcap"`, the mcap package, and `engine="wreckmap"`, our own),
interleaved so that both see the same machine load, and prints messages/s and
MB/s (MB = 1e6 bytes of CDR payload) for each, then the ratio between them.
Reads the mcap-written files back with our reader (`ArchiveReader`) and with
the mcap package's reader (`mcap.reader.make_reader`, log-time order): IMU
through `read_imu` (both decode with `cdr.decode_imu_batch`), video as raw
CDR records. The load
average is printed at the start and the end: on a shared machine the absolute
figures move with it, the ratios much less. The recorder needs >= 20k IMU
msgs/s and 30 fps video.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.archive import ArchiveWriter, CompressedVideo, Imu, imu_topic, video_topic
from shared.archive.cdr import decode_imu_batch, encode
from shared.archive.reader import ArchiveReader

ENGINES = ("wreckmap", "mcap")
T0_NS = 1_700_000_000_000_000_000
VIDEO_PACKET_BYTES = 200_000


def load_average() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} ({os.cpu_count()} cores)"


def timed(action: Callable[[], object], repeats: int) -> float:
    """Best wall time of `repeats` runs (s): the least disturbed by other jobs."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        best = min(best, time.perf_counter() - start)
    return best


def imu_messages(count: int) -> list[Imu]:
    rng = np.random.default_rng(0)
    gyro = rng.normal(size=(count, 3))
    accel = rng.normal(size=(count, 3))
    return [
        Imu(
            stamp_ns=T0_NS + i * 1_000_000,
            frame_id="imu0",
            angular_velocity_rad_s=gyro[i],
            linear_acceleration_m_s2=accel[i],
        )
        for i in range(count)
    ]


def video_messages(count: int) -> list[CompressedVideo]:
    rng = np.random.default_rng(1)
    # Random bytes stand in for H.264 slices (entropy-coded data does not compress).
    return [
        CompressedVideo(
            stamp_ns=T0_NS + i * 33_333_333,
            frame_id="cam0",
            format="h264",
            data=rng.bytes(VIDEO_PACKET_BYTES),
        )
        for i in range(count)
    ]


def write_file(
    path: Path,
    topic: str,
    messages: list[Imu] | list[CompressedVideo],
    compression: str,
    engine: str,
) -> None:
    path.unlink(missing_ok=True)
    with ArchiveWriter(path, compression=compression, engine=engine) as writer:  # type: ignore[arg-type]
        for message in messages:
            writer.write(topic, message)


def read_imu_ours(path: Path, topic: str) -> int:
    with ArchiveReader(path) as reader:
        return len(reader.read_imu(topic).stamps_ns)


def read_imu_mcap(path: Path, topic: str) -> int:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        payloads = [m.data for _, _, m in make_reader(stream).iter_messages(topics=[topic])]
    return len(decode_imu_batch(payloads, str(path)).stamps_ns)


def read_raw_ours(path: Path, topic: str) -> int:
    with ArchiveReader(path) as reader:
        return sum(1 for _ in reader.raw_messages([topic]))


def read_raw_mcap(path: Path, topic: str) -> int:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        return sum(1 for _ in make_reader(stream).iter_messages(topics=[topic]))


def bench_imu(folder: Path, count: int, repeats: int) -> dict[tuple[str, str], float]:
    messages = imu_messages(count)
    payload = count * len(encode(messages[0]))
    topic = imu_topic(0)
    rates: dict[tuple[str, str], float] = {}
    for compression in ("zstd", "lz4", "none"):
        for engine in ENGINES:
            path = folder / f"imu_{compression}_{engine}.mcap"
            elapsed = timed(
                partial(write_file, path, topic, messages, compression, engine), repeats
            )
            rate = rates[(engine, compression)] = count / elapsed
            print(
                f"IMU write   {compression:4} {engine:8}: {rate:10,.0f} msg/s  "
                f"{payload / elapsed / 1e6:7.1f} MB/s  file {path.stat().st_size / 1e6:.1f} MB  "
                f"(needs >= 20,000 msg/s: {'ok' if rate >= 20_000 else 'TOO SLOW'})"
            )
        ratio = rates[("wreckmap", compression)] / rates[("mcap", compression)]
        print(f"IMU write   {compression:4} wreckmap / mcap = {ratio:.2f}")
    path = folder / "imu_zstd_mcap.mcap"
    for name, reader in (("ours", read_imu_ours), ("mcap", read_imu_mcap)):
        assert reader(path, topic) == count
        elapsed = timed(partial(reader, path, topic), repeats)
        rates[("read_imu", name)] = count / elapsed
        print(f"IMU read_imu        {name:8}: {count / elapsed:10,.0f} msg/s")
    return rates


def bench_video(folder: Path, count: int, repeats: int) -> dict[tuple[str, str], float]:
    messages = video_messages(count)
    topic = video_topic(0)
    megabytes = count * VIDEO_PACKET_BYTES / 1e6
    rates: dict[tuple[str, str], float] = {}
    for compression in ("zstd", "none"):
        for engine in ENGINES:
            path = folder / f"video_{compression}_{engine}.mcap"
            elapsed = timed(
                partial(write_file, path, topic, messages, compression, engine), repeats
            )
            rate = count / elapsed
            rates[(engine, compression)] = megabytes / elapsed
            print(
                f"video write {compression:4} {engine:8}: {rate:8,.0f} packets/s  "
                f"{megabytes / elapsed:7.1f} MB/s  "
                f"(needs >= 30 fps: {'ok' if rate >= 30 else 'TOO SLOW'})"
            )
        ratio = rates[("wreckmap", compression)] / rates[("mcap", compression)]
        print(f"video write {compression:4} wreckmap / mcap = {ratio:.2f}")
    path = folder / "video_zstd_mcap.mcap"
    for name, reader in (("ours", read_raw_ours), ("mcap", read_raw_mcap)):
        assert reader(path, topic) == count
        elapsed = timed(partial(reader, path, topic), repeats)
        print(f"video read (raw)    {name:8}: {megabytes / elapsed:7.1f} MB/s")
    return rates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--imu-messages", type=int, default=200_000)
    parser.add_argument("--video-packets", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3, help="best of N runs per figure")
    args = parser.parse_args()
    print(f"start: {load_average()}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        imu = bench_imu(folder, args.imu_messages, args.repeats)
        video = bench_video(folder, args.video_packets, args.repeats)
    print(f"end:   {load_average()}")
    print(
        "summary (zstd): IMU wreckmap {:,.0f} / mcap {:,.0f} msg/s (x{:.2f}); "
        "video wreckmap {:.0f} / mcap {:.0f} MB/s (x{:.2f}); "
        "read_imu ours {:,.0f} / mcap {:,.0f} msg/s (x{:.2f})".format(
            imu[("wreckmap", "zstd")],
            imu[("mcap", "zstd")],
            imu[("wreckmap", "zstd")] / imu[("mcap", "zstd")],
            video[("wreckmap", "zstd")],
            video[("mcap", "zstd")],
            video[("wreckmap", "zstd")] / video[("mcap", "zstd")],
            imu[("read_imu", "ours")],
            imu[("read_imu", "mcap")],
            imu[("read_imu", "ours")] / imu[("read_imu", "mcap")],
        )
    )


if __name__ == "__main__":
    main()
