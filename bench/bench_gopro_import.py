"""How fast is `gopro import` against a plain copy and a decode + re-encode baseline?

    .venv/bin/python bench/bench_gopro_import.py [--size-gb 1.0] [--keep DIR]

Measured in one run, on the same files (warm page cache for all three, since
the files were just written; on a cold SD card every figure is bounded by
the card):

1. plain copy of the MP4 (shutil.copyfile): the physical limit;
2. our import (packets copied, AVCC -> Annex B, MCAP + IMU + session.yaml);
3. a decode-and-re-encode baseline (what gopro_ros does): decode every frame
   with PyAV and JPEG-encode it with OpenCV, on a real-encoded 1080p clip,
   expressed per second of video and extrapolated to the big chapter.

The big chapter is synthetic: 60 fps H.264-shaped packets (valid AVCC NAL
framing, random payload, a keyframe every 30 frames) at ~150 Mbit/s, the
bitrate of GoPro's highest modes, with real GPMF IMU payloads at 200 Hz.
The import never decodes, so random payloads cost it exactly what real
ones would. Figures print as a table; ratios at the end.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path

import numpy as np

os.environ.setdefault("WRECKMAP_PROGRESS", "0")

REPO = Path(__file__).resolve().parents[1]
FPS = Fraction(60000, 1001)


def make_big_chapter(path: Path, *, size_bytes: int) -> float:
    """Write a synthetic high-bitrate GoPro chapter; returns its duration in seconds."""
    from field.gopro.writer import encode_gpmf_imu_payload, encode_h264, write_gopro_mp4

    tiny = encode_h264([np.zeros((64, 64, 3), np.uint8)], fps=FPS)
    frame_bytes = 150e6 / 8 / float(FPS)  # ~150 Mbit/s
    frames = int(size_bytes // frame_bytes)
    frames -= frames % 60
    rng = np.random.default_rng(0)
    pool = rng.integers(0, 256, size=int(frame_bytes * 2.5), dtype=np.uint8).tobytes()
    packets, keys = [], []
    for i in range(frames):
        key = i % 30 == 0
        size = int(frame_bytes * (2.0 if key else 0.96))
        start = (i * 7919) % (len(pool) - size)
        body = (b"\x65" if key else b"\x41") + pool[start : start + size - 1]
        packets.append(len(body).to_bytes(4, "big") + body)
        keys.append(key)
    seconds = frames / float(FPS)
    payloads = []
    n_payloads = int(np.ceil(seconds / 1.001))
    for p in range(n_payloads):
        t = np.arange(200) / 200.0
        payloads.append(
            encode_gpmf_imu_payload(
                accl_mps2=np.column_stack([9.81 + 0 * t, 0.1 * t, 0 * t]),
                gyro_rads=np.column_stack([np.sin(t), np.cos(t), t]),
                accl_first_us=p * 1_001_000,
                gyro_first_us=p * 1_001_000,
                accl_total_before=200 * p,
                gyro_total_before=200 * p,
            )
        )
    write_gopro_mp4(
        path,
        video_packets=packets,
        sps=tiny.sps,
        pps=tiny.pps,
        width=3840,
        height=2160,
        fps=FPS,
        keyframe_flags=keys,
        gpmf_payloads=payloads,
        creation_time=datetime(2024, 6, 1, 9, 30, tzinfo=UTC),
    )
    return seconds


def make_real_clip(path: Path, *, seconds: float) -> None:
    """A really encoded 1080p30 clip (high quality, noisy texture) for the decode baseline."""
    from field.gopro.writer import encode_gpmf_imu_payload, encode_h264, write_gopro_mp4

    fps = Fraction(30000, 1001)
    rng = np.random.default_rng(1)
    texture = rng.integers(0, 256, size=(1080, 1920 + 600, 3), dtype=np.uint8)
    count = int(seconds * float(fps))
    frames = (np.ascontiguousarray(texture[:, 10 * i : 10 * i + 1920]) for i in range(count))
    stream = encode_h264(frames, fps=fps, gop_frames=30, crf=18)
    payloads = [
        encode_gpmf_imu_payload(
            accl_mps2=np.tile([9.81, 0, 0], (200, 1)),
            gyro_rads=np.zeros((200, 3)),
            accl_first_us=p * 1_001_000,
            gyro_first_us=p * 1_001_000,
            accl_total_before=200 * p,
            gyro_total_before=200 * p,
        )
        for p in range(int(np.ceil(seconds / 1.001)))
    ]
    write_gopro_mp4(
        path,
        video_packets=stream.packets,
        sps=stream.sps,
        pps=stream.pps,
        width=stream.width,
        height=stream.height,
        fps=fps,
        keyframe_flags=stream.keyframes,
        gpmf_payloads=payloads,
        creation_time=datetime(2024, 6, 1, 9, 30, tzinfo=UTC),
    )


def time_copy(source: Path, target: Path) -> float:
    os.sync()
    start = time.perf_counter()
    shutil.copyfile(source, target)
    with target.open("rb") as f:
        os.fsync(f.fileno())
    return time.perf_counter() - start


def time_import(source: Path, session: Path) -> tuple[float, int]:
    from field.gopro.importer import ImportOptions, import_recording

    os.sync()
    start = time.perf_counter()
    result = import_recording(ImportOptions(), [source], session)
    return time.perf_counter() - start, result.imu_samples


def time_decode_reencode(source: Path, *, max_frames: int | None = None) -> tuple[float, int]:
    """Decode every frame with PyAV, JPEG-encode it with OpenCV (quality 95). (seconds, frames)"""
    import av
    import cv2

    start = time.perf_counter()
    count = 0
    with av.open(str(source)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        for frame in container.decode(stream):
            image = frame.to_ndarray(format="bgr24")
            ok, _ = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            if not ok:
                raise RuntimeError("JPEG encoding failed")
            count += 1
            if max_frames is not None and count >= max_frames:
                break
    return time.perf_counter() - start, count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-gb", type=float, default=1.0, help="synthetic chapter size, GB")
    parser.add_argument("--clip-s", type=float, default=6.0, help="real 1080p clip length, s")
    parser.add_argument("--keep", type=Path, help="work in this folder (default: a temp dir)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_gopro_", dir=args.keep))
    try:
        big = work / "GX010001.MP4"
        t0 = time.perf_counter()
        seconds = make_big_chapter(big, size_bytes=int(args.size_gb * 1e9))
        size = big.stat().st_size
        print(
            f"synthetic chapter: {size / 1e9:.2f} GB, {seconds:.1f} s at 60 fps, "
            f"{size * 8 / seconds / 1e6:.0f} Mbit/s (written in {time.perf_counter() - t0:.1f} s)"
        )
        clip = work / "GX010002.MP4"
        make_real_clip(clip, seconds=args.clip_s)
        clip_size = clip.stat().st_size
        print(f"real 1080p clip: {clip_size / 1e6:.1f} MB, {args.clip_s:.1f} s")

        rows = []
        # Best of two, each after a sync so no earlier write-back competes with it.
        copy_s = min(time_copy(big, work / f"copy{i}.MP4") for i in range(2))
        for i in range(2):
            (work / f"copy{i}.MP4").unlink()
        rows.append(("plain copy (big)", copy_s, size, seconds))
        import_s = float("inf")
        imu = 0
        for i in range(2):
            elapsed, imu = time_import(big, work / f"session_big{i}")
            import_s = min(import_s, elapsed)
            shutil.rmtree(work / f"session_big{i}")
        rows.append(("our import (big)", import_s, size, seconds))
        shm = Path("/dev/shm")
        ram_copy_s = ram_import_s = None
        if shm.is_dir() and shutil.disk_usage(shm).free > 3 * size:
            # Output to a RAM disk: what the CPU alone allows (input from the page cache).
            ram = Path(tempfile.mkdtemp(prefix="bench_gopro_", dir=shm))
            try:
                ram_copy_s = time_copy(big, ram / "copy.MP4")
                (ram / "copy.MP4").unlink()
                ram_import_s, _ = time_import(big, ram / "session")
            finally:
                shutil.rmtree(ram, ignore_errors=True)
            rows.append(("plain copy (big, to RAM disk)", ram_copy_s, size, seconds))
            rows.append(("our import (big, to RAM disk)", ram_import_s, size, seconds))
        clip_copy_s = time_copy(clip, work / "copy2.MP4")
        rows.append(("plain copy (1080p clip)", clip_copy_s, clip_size, args.clip_s))
        clip_import_s, _ = time_import(clip, work / "session_clip")
        rows.append(("our import (1080p clip)", clip_import_s, clip_size, args.clip_s))
        decode_s, frames = time_decode_reencode(clip)
        rows.append(("decode + JPEG (1080p clip)", decode_s, clip_size, args.clip_s))
        karma = REPO.parent / "shared" / "data" / "gopro" / "karma.mp4"
        if karma.is_file():
            ksize = karma.stat().st_size
            rows.append(("plain copy (karma.mp4)", time_copy(karma, work / "k.mp4"), ksize, 12.08))
            rows.append(
                ("our import (karma.mp4)", time_import(karma, work / "sk")[0], ksize, 12.08)
            )
            rows.append(("decode + JPEG (karma.mp4)", time_decode_reencode(karma)[0], ksize, 12.08))

        print()
        print(f"{'what':30s} {'seconds':>8s} {'MB/s':>9s} {'x real time':>12s}")
        for name, elapsed, nbytes, video_s in rows:
            print(
                f"{name:30s} {elapsed:8.2f} {nbytes / elapsed / 1e6:9.1f} {video_s / elapsed:12.1f}"
            )
        import_mb_s = size / import_s / 1e6
        copy_mb_s = size / copy_s / 1e6
        decode_fps = frames / decode_s
        print()
        print(f"import / copy speed (big chapter):       {import_s and copy_s / import_s:.2f}")
        print(f"import real-time factor (big chapter):   {seconds / import_s:.0f}x")
        print(f"import IMU samples (big chapter):        {imu}")
        print(
            f"4 GB chapter, extrapolated:              import {4e9 / import_mb_s / 1e6:.1f} s, "
            f"copy {4e9 / copy_mb_s / 1e6:.1f} s, "
            f"{4e9 / size * seconds / (4e9 / import_mb_s / 1e6):.0f}x real time"
        )
        # The baseline decodes frames: its cost is per frame of 1080p (4K costs ~4x more).
        big_frames = seconds * float(FPS)
        print(f"decode + JPEG baseline: {decode_fps:.1f} frames/s at 1080p "
              f"= {decode_fps / float(FPS):.2f}x real time for 60 fps; the big chapter "
              f"would take >= {big_frames / decode_fps:.0f} s at 1080p "
              f"(~{4 * big_frames / decode_fps:.0f} s at 4K), "
              f"{4 * big_frames / decode_fps / import_s:.0f}x our import")  # fmt: skip
        if ram_copy_s and ram_import_s:
            print(
                f"to a RAM disk (CPU limit): import {size / ram_import_s / 1e6:.0f} MB/s = "
                f"{seconds / ram_import_s:.0f}x real time, "
                f"copy {size / ram_copy_s / 1e6:.0f} MB/s, "
                f"import / copy {ram_copy_s / ram_import_s:.2f}"
            )
        print(
            "import vs decode + JPEG on the same 1080p clip: "
            f"{decode_s / clip_import_s:.0f}x faster"
        )
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
