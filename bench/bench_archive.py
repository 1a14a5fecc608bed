"""Archive writer/reader throughput: IMU messages and 200 kB video packets, both writers.

Run: .venv/bin/python bench/bench_archive.py [--imu-messages N] [--video-packets N]
     [--recorder-seconds S] [--repeats N]

Writes the same streams with both record writers of `ArchiveWriter` in one
run (`engine="mcap"`, the mcap package, and `engine="wreckmap"`, our own),
interleaved so that both see the same machine load, and prints messages/s and
MB/s (MB = 1e6 bytes of CDR payload) for each, then the ratio between them.
Decodes IMU CDR with our codec and with mcap-ros2-support's. Reads the
mcap-written files back with our reader (`ArchiveReader`) and with the mcap
package's reader (`mcap.reader.make_reader`, log-time order, chunk CRCs
checked as ours always does): IMU through `read_imu` (both decode with
`cdr.decode_imu_batch`), video as raw CDR records. The load average is
printed at the start and the end: on a shared machine the absolute figures
move with it, the ratios much less. The recorder needs >= 20k IMU msgs/s and
30 fps video; the last figures are the CPU time each writer spends on the
recorder's own stream (bench_record.py's rig, at its writer settings) as a
share of one core, the writer's part of the recorder's 10 % budget.
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

from shared.archive import (
    ArchiveWriter,
    CompressedVideo,
    DepthSample,
    Imu,
    depth_topic,
    imu_topic,
    video_topic,
)
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
        reader = make_reader(stream, validate_crcs=True)
        payloads = [m.data for _, _, m in reader.iter_messages(topics=[topic])]
    return len(decode_imu_batch(payloads, str(path)).stamps_ns)


def read_raw_ours(path: Path, topic: str) -> int:
    with ArchiveReader(path) as reader:
        return sum(1 for _ in reader.raw_messages([topic]))


def read_raw_mcap(path: Path, topic: str) -> int:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        return sum(1 for _ in reader.iter_messages(topics=[topic]))


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


def bench_cdr_decode(folder: Path, repeats: int) -> dict[str, float]:
    """Decoding IMU CDR one message at a time: our codec against mcap-ros2-support's,
    which builds its decoder from the schema stored in the file (a dev dependency)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from shared.archive.cdr import decode_imu

    path = folder / "imu_zstd_mcap.mcap"
    with path.open("rb") as stream:
        items = list(make_reader(stream).iter_messages(topics=[imu_topic(0)]))
    schema = items[0][0]
    payloads = [message.data for _, _, message in items[:50_000]]
    theirs = DecoderFactory().decoder_for("cdr", schema)
    assert theirs is not None
    rates = {}
    for name, decode in (("ours", decode_imu), ("mcap_ros2", theirs)):
        elapsed = timed(partial(lambda d: [d(p) for p in payloads], decode), repeats)
        rates[name] = len(payloads) / elapsed
        print(f"IMU CDR decode      {name:9}: {rates[name]:10,.0f} msg/s")
    print(f"IMU CDR decode      ours / mcap_ros2 = {rates['ours'] / rates['mcap_ros2']:.2f}")
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


def recorder_stream(seconds: float) -> list[tuple[float, str, Imu | CompressedVideo | DepthSample]]:
    """What `wreckmap-field record` writes (bench_record's rig): two 30 fps H.264 streams
    at 8 Mb/s, a 400 Hz IMU and a 4 Hz depth sensor; (stream time s, topic, message)."""
    rng = np.random.default_rng(2)
    packet_bytes = 8_000_000 // 8 // 30
    out: list[tuple[float, str, Imu | CompressedVideo | DepthSample]] = []
    for i in range(round(seconds * 400)):
        t = i / 400
        out.append(
            (
                t,
                imu_topic(0),
                Imu(
                    stamp_ns=T0_NS + i * 2_500_000,
                    frame_id="imu0",
                    angular_velocity_rad_s=rng.normal(size=3),
                    linear_acceleration_m_s2=rng.normal(size=3),
                ),
            )
        )
        if i % 100 == 0:
            out.append(
                (t, depth_topic(0), DepthSample(stamp_ns=T0_NS + i * 2_500_000, frame_id="d"))
            )
    for i in range(round(seconds * 30)):
        for camera in (0, 1):
            # Fresh random bytes per packet: H.264 does not compress (a repeated buffer would).
            message = CompressedVideo(
                stamp_ns=T0_NS + i * 33_333_333,
                frame_id=f"cam{camera}",
                format="h264",
                data=rng.bytes(packet_bytes),
            )
            out.append((i / 30, video_topic(camera), message))
    out.sort(key=lambda item: item[0])
    return out


def write_like_the_recorder(
    path: Path, stream: list[tuple[float, str, Imu | CompressedVideo | DepthSample]], engine: str
) -> None:
    """The recorder's writer settings: 1 MiB chunks, zstd, flush + fsync every 0.5 s."""
    path.unlink(missing_ok=True)
    next_flush = 0.5
    with ArchiveWriter(path, chunk_size=2**20, compression="zstd", engine=engine) as writer:  # type: ignore[arg-type]
        for t, topic, message in stream:
            if t >= next_flush:
                writer.flush(fsync=True)
                next_flush += 0.5
            writer.write(topic, message)


def bench_recorder_share(folder: Path, seconds: float, repeats: int) -> dict[str, float]:
    """CPU time (user + system, this process) of writing `seconds` of the recorder's
    stream, as a share of one core at real-time rate: the writer's part of the
    recorder's CPU figure (bench_record.py measures the whole recorder)."""
    stream = recorder_stream(seconds)
    shares: dict[str, float] = {}
    for engine in ENGINES:
        path = folder / f"recorder_{engine}.mcap"
        best = float("inf")
        for _ in range(repeats):
            start = time.process_time()
            write_like_the_recorder(path, stream, engine)
            best = min(best, time.process_time() - start)
        shares[engine] = best / seconds
        print(
            f"recorder stream ({seconds:.0f} s, {len(stream)} messages, "
            f"{path.stat().st_size / 2**20:.0f} MiB) {engine:8}: writer CPU "
            f"{100 * shares[engine]:.2f} % of one core"
        )
    return shares


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--imu-messages", type=int, default=200_000)
    parser.add_argument("--video-packets", type=int, default=300)
    parser.add_argument("--recorder-seconds", type=float, default=60.0)
    parser.add_argument("--repeats", type=int, default=3, help="best of N runs per figure")
    args = parser.parse_args()
    print(f"start: {load_average()}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        imu = bench_imu(folder, args.imu_messages, args.repeats)
        bench_cdr_decode(folder, args.repeats)
        video = bench_video(folder, args.video_packets, args.repeats)
        shares = bench_recorder_share(folder, args.recorder_seconds, args.repeats)
    print(f"end:   {load_average()}")
    print(
        "summary (zstd): IMU wreckmap {:,.0f} / mcap {:,.0f} msg/s (x{:.2f}); "
        "video wreckmap {:.0f} / mcap {:.0f} MB/s (x{:.2f}); "
        "read_imu ours {:,.0f} / mcap {:,.0f} msg/s (x{:.2f}); "
        "recorder writer CPU wreckmap {:.2f} % / mcap {:.2f} % of one core".format(
            imu[("wreckmap", "zstd")],
            imu[("mcap", "zstd")],
            imu[("wreckmap", "zstd")] / imu[("mcap", "zstd")],
            video[("wreckmap", "zstd")],
            video[("mcap", "zstd")],
            video[("wreckmap", "zstd")] / video[("mcap", "zstd")],
            imu[("read_imu", "ours")],
            imu[("read_imu", "mcap")],
            imu[("read_imu", "ours")] / imu[("read_imu", "mcap")],
            100 * shares["wreckmap"],
            100 * shares["mcap"],
        )
    )


if __name__ == "__main__":
    main()
