"""Benchmark: sustained recording of two 1280x800 30 fps H.264 streams plus a 400 Hz IMU.

Runs `wreckmap-field record --source sim` as a subprocess for `--minutes` and samples its
CPU time and resident memory from /proc every second. The simulated rig replays a clip
that was rendered and encoded beforehand (in this process, cached), so the encoding cost
is not counted: the recorder process only paces pre-encoded packets, queues them and
writes the MCAP (CDR, chunks, compression, index, fsync every flush).

    .venv/bin/python bench/bench_record.py                 # 10 minutes
    .venv/bin/python bench/bench_record.py --minutes 1 --preview

Goal: under 30 % of one core, memory flat (no growth after the first minute).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TICKS = os.sysconf("SC_CLK_TCK")
PAGE_KIB = os.sysconf("SC_PAGE_SIZE") // 1024


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (s)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def rss_mib(pid: int) -> float:
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE_KIB / 1024


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="recording length")
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--imu-hz", type=float, default=400.0)
    parser.add_argument("--bitrate-kbps", type=int, default=8000, help="per camera")
    parser.add_argument("--codec", default="h264", choices=["h264", "h265", "mjpeg"])
    parser.add_argument("--compression", default="zstd", choices=["zstd", "lz4", "none"])
    parser.add_argument("--preview", action="store_true", help="also publish the zenoh preview")
    parser.add_argument("--out", type=Path, help="session folder (default: a temporary one)")
    args = parser.parse_args()

    from field.record.sources.sim import SimOptions, prepare_clip
    from shared.folders import SessionFolder

    sim = {
        "cameras": args.cameras,
        "width_px": args.width,
        "height_px": args.height,
        "render_scale": 4,  # render 320x200 and upscale: the renderer is slow, bytes are not
        "fps": args.fps,
        "codec": args.codec,
        "bitrate_kbps": args.bitrate_kbps,
        "keyframe_interval": round(args.fps),
        "imu_rate_hz": args.imu_hz,
        "clip_s": 2.0,
        "noise_dn": 3.0,
    }
    t = time.monotonic()
    clip = prepare_clip(SimOptions(**sim))
    print(f"clip: {clip} ({clip.stat().st_size / 2**20:.1f} MiB, {time.monotonic() - t:.0f} s)")

    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_record_")
        out = Path(tmp.name) / "session"
    else:
        out = args.out
    duration_s = args.minutes * 60
    command = [
        sys.executable,
        "-m",
        "field.cli",
        "record",
        "--source",
        "sim",
        "--out",
        str(out),
        "--duration",
        str(duration_s),
    ]
    for key, value in sim.items():
        command += ["--source-option", f"sim.{key}={value}"]
    if args.preview:
        command += ["--preview", "tcp/127.0.0.1:17999"]
    env = {**os.environ, "WRECKMAP_PROGRESS": "0", "PYTHONPATH": str(REPO)}
    config = out.parent / "bench_logger.yaml"
    config.parent.mkdir(parents=True, exist_ok=True)
    config.write_text(f"recorder:\n  compression: {args.compression}\n")
    command += ["--config", str(config)]
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    samples: list[tuple[float, float, float]] = []  # (wall s, cpu s, rss MiB)
    start = time.monotonic()
    try:
        while proc.poll() is None:
            try:
                samples.append((time.monotonic() - start, cpu_seconds(proc.pid), rss_mib(proc.pid)))
            except (FileNotFoundError, ProcessLookupError, IndexError):
                break
            time.sleep(1.0)
        stdout, stderr = proc.communicate(timeout=120)
    except KeyboardInterrupt:
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    if proc.returncode != 0:
        print(stderr[-3000:], file=sys.stderr)
        print(f"recorder failed with exit code {proc.returncode}", file=sys.stderr)
        return 1
    # Steady state: skip the first 5 s (imports, first file); CPU share of one core.
    steady = [s for s in samples if s[0] >= 5.0]
    if len(steady) < 2:
        steady = samples
    (w0, c0, _), (w1, c1, _) = steady[0], steady[-1]
    cpu_share = (c1 - c0) / (w1 - w0) if w1 > w0 else float("nan")
    rss = [s[2] for s in samples]
    first_min = [s[2] for s in samples if 5.0 <= s[0] < 65.0] or rss
    last_min = [s[2] for s in samples if s[0] >= samples[-1][0] - 60.0] or rss
    files = SessionFolder(out).recording_parts()
    size = sum(f.stat().st_size for f in files)
    dropped = re.search(r"(\d+) dropped", stdout)
    print(stdout.strip())
    print()
    print(
        f"streams      : {args.cameras} x {args.width}x{args.height} {args.fps:g} fps {args.codec} "
        f"{args.bitrate_kbps} kb/s + IMU {args.imu_hz:g} Hz, compression {args.compression}"
        + (", zenoh preview on" if args.preview else "")
    )
    print(f"duration     : {samples[-1][0] if samples else 0:.0f} s")
    print(f"recorder CPU : {100 * cpu_share:.1f} % of one core (steady state, goal < 30 %)")
    first_mib = sum(first_min) / len(first_min)
    last_mib = sum(last_min) / len(last_min)
    print(
        f"memory (RSS) : peak {max(rss):.0f} MiB; mean first minute {first_mib:.0f} MiB, "
        f"last minute {last_mib:.0f} MiB"
    )
    print(
        f"written      : {size / 2**20:.0f} MiB in {len(files)} file(s), "
        f"{size / 2**20 / max(duration_s, 1e-9):.2f} MiB/s"
    )
    print(f"dropped      : {dropped.group(1) if dropped else '?'} messages")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
