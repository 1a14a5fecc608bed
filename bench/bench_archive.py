"""Archive writer/reader throughput: IMU messages and 200 kB video packets.

Run: .venv/bin/python bench/bench_archive.py
Prints messages/s and MB/s (MB = 1e6 bytes of CDR payload) for writing and
reading each stream. The recorder needs >= 20k IMU msgs/s and 30 fps video.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.archive import ArchiveWriter, CompressedVideo, Imu, imu_topic, video_topic
from shared.archive.cdr import encode
from shared.archive.reader import ArchiveReader

IMU_MESSAGES = 200_000
VIDEO_PACKETS = 300
VIDEO_PACKET_BYTES = 200_000
T0_NS = 1_700_000_000_000_000_000


def bench_imu(folder: Path, compression: str) -> None:
    rng = np.random.default_rng(0)
    gyro = rng.normal(size=(IMU_MESSAGES, 3))
    accel = rng.normal(size=(IMU_MESSAGES, 3))
    messages = [
        Imu(
            stamp_ns=T0_NS + i * 1_000_000,
            frame_id="imu0",
            angular_velocity_rad_s=gyro[i],
            linear_acceleration_m_s2=accel[i],
        )
        for i in range(IMU_MESSAGES)
    ]
    path = folder / f"imu_{compression}.mcap"
    topic = imu_topic(0)
    start = time.perf_counter()
    with ArchiveWriter(path, compression=compression) as writer:  # type: ignore[arg-type]
        for message in messages:
            writer.write(topic, message)
    elapsed = time.perf_counter() - start
    size = path.stat().st_size
    payload = IMU_MESSAGES * len(encode(messages[0]))
    rate = IMU_MESSAGES / elapsed
    print(
        f"IMU write ({compression:4}): {rate:10,.0f} msg/s  "
        f"{payload / elapsed / 1e6:7.1f} MB/s  file {size / 1e6:.1f} MB  "
        f"(needs >= 20,000 msg/s: {'ok' if rate >= 20_000 else 'TOO SLOW'})"
    )
    start = time.perf_counter()
    with ArchiveReader(path) as reader:
        series = reader.read_imu(topic)
    elapsed = time.perf_counter() - start
    assert len(series.stamps_ns) == IMU_MESSAGES
    print(f"IMU read_imu   : {IMU_MESSAGES / elapsed:10,.0f} msg/s")
    start = time.perf_counter()
    with ArchiveReader(path) as reader:
        count = sum(1 for _ in reader.messages([topic]))
    elapsed = time.perf_counter() - start
    print(f"IMU messages() : {count / elapsed:10,.0f} msg/s")


def bench_video(folder: Path, compression: str) -> None:
    rng = np.random.default_rng(1)
    # Random bytes stand in for H.264 slices (entropy-coded data does not compress).
    packets = [rng.bytes(VIDEO_PACKET_BYTES) for _ in range(VIDEO_PACKETS)]
    path = folder / f"video_{compression}.mcap"
    topic = video_topic(0)
    start = time.perf_counter()
    with ArchiveWriter(path, compression=compression) as writer:  # type: ignore[arg-type]
        for i, packet in enumerate(packets):
            writer.write(
                topic,
                CompressedVideo(
                    stamp_ns=T0_NS + i * 33_333_333, frame_id="cam0", format="h264", data=packet
                ),
            )
    elapsed = time.perf_counter() - start
    rate = VIDEO_PACKETS / elapsed
    print(
        f"video write ({compression:4}): {rate:8,.0f} packets/s  "
        f"{VIDEO_PACKETS * VIDEO_PACKET_BYTES / elapsed / 1e6:7.1f} MB/s  "
        f"(needs >= 30 fps: {'ok' if rate >= 30 else 'TOO SLOW'})"
    )
    start = time.perf_counter()
    with ArchiveReader(path) as reader:
        count = sum(1 for _ in reader.messages([topic]))
    elapsed = time.perf_counter() - start
    print(
        f"video read        : {count / elapsed:8,.0f} packets/s  "
        f"{count * VIDEO_PACKET_BYTES / elapsed / 1e6:7.1f} MB/s"
    )


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for compression in ("zstd", "lz4", "none"):
            bench_imu(folder, compression)
        for compression in ("zstd", "none"):
            bench_video(folder, compression)


if __name__ == "__main__":
    main()
