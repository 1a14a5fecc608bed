"""Both real GoPro clips of ../shared/data/gopro through `wreckmap-field gopro import`.

No truth comes with them, so this checks what a file says about itself, each
fact from a source other than the importer's own arithmetic where there is one:
the frame count against PyAV's demuxer, the IMU rate against the raw TSMP
counters over the video's length, stamps that only go forward, the IMU inside
the video's span (give or take one 1.001 s payload), and gravity at the mean
(both clips are held or flown nearly still on average).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from field.gopro.mp4 import read_mp4
from field.gopro.telemetry import iter_gpmf_payloads
from shared.archive import ArchiveReader, CompressedVideo

REPO = Path(__file__).resolve().parents[2]
PAYLOAD_NS = 1_001_000_000
# name, camera model, (ACCL, GYRO) rates in Hz: HERO5 samples its gyro at 400 Hz.
CLIPS = [
    ("karma.mp4", "HERO5 Black", (200.0, 400.0)),
    ("max-heromode.mp4", "GoPro Max", (200.0, 200.0)),
]


def _tsmp_rate_hz(path: Path, key: str) -> float:
    """Samples per second from the camera's own counter: the last TSMP over the video length."""
    mp4 = read_mp4(path)
    total = 0
    for _, _, _, payload in iter_gpmf_payloads(mp4):
        for stream in payload.find(key):
            if stream.device_id in (None, 1) and stream.total_samples is not None:
                total = stream.total_samples
    return total / mp4.video_track().duration_s


@pytest.mark.parametrize(("name", "model", "rates_hz"), CLIPS)
def test_real_clip_through_gopro_import(
    shared_data: Path, tmp_path: Path, name: str, model: str, rates_hz: tuple[float, float]
) -> None:
    import av

    source = shared_data / "gopro" / name
    session = tmp_path / "session"
    done = subprocess.run(
        [sys.executable, "-m", "field.cli", "gopro", "import", str(source), "--out", str(session)],
        cwd=REPO,
        env={**os.environ, "WRECKMAP_PROGRESS": "0"},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    document = yaml.safe_load((session / "session.yaml").read_text())
    imu_doc = document["devices"]["imu0"]
    assert document["devices"]["cam0"]["model"] == model

    # Frames: every packet PyAV's demuxer finds, each stamped one frame after the last.
    with av.open(str(source)) as container:
        packets = sum(1 for p in container.demux(container.streams.video[0]) if p.size)
    with ArchiveReader(session / "recording.mcap") as reader:
        frames = [m.stamp_ns for _, _, m in reader.messages(["/cam0/video"])]
        assert all(isinstance(m, CompressedVideo) for _, _, m in reader.messages(["/cam0/video"]))
        imu = reader.read_imu("/imu0")
    assert len(frames) == packets == document["chapters"][0]["frames"]
    fps = document["devices"]["cam0"]["fps"]
    np.testing.assert_allclose(np.diff(frames), 1e9 / fps, atol=1.0)

    # Rates: ~200 Hz (400 Hz gyro on the HERO5), and as the camera's own counters say.
    for key, nominal, measured in zip(
        ("ACCL", "GYRO"), rates_hz, (imu_doc["accel_rate_hz"], imu_doc["gyro_rate_hz"]), strict=True
    ):
        assert measured == pytest.approx(nominal, rel=0.03), key
        assert measured == pytest.approx(_tsmp_rate_hz(source, key), rel=0.01), key
    stamps = imu.stamps_ns
    assert np.all(np.diff(stamps) > 0)
    rate = (stamps.size - 1) / ((stamps[-1] - stamps[0]) * 1e-9)
    assert rate == pytest.approx(max(rates_hz), rel=0.03)

    # The IMU lies within the video, give or take one payload; on a sub-payload scale the
    # start is recorded (session.yaml) rather than assumed.
    video_end = frames[-1] + round(1e9 / fps)
    assert frames[0] - PAYLOAD_NS <= stamps[0] and stamps[-1] <= video_end + PAYLOAD_NS
    start_s = document["chapters"][0]["imu_start_s"]
    assert start_s == pytest.approx((stamps[0] - frames[0]) * 1e-9, abs=1e-9)
    assert abs(start_s) < 0.05
    assert (video_end - stamps[-1]) * 1e-9 == pytest.approx(0.0, abs=0.05)

    # Gravity: the mean specific force of a still-on-average camera is 1 g.
    assert np.linalg.norm(imu.accel_m_s2.mean(axis=0)) == pytest.approx(9.81, abs=0.3)
    assert not [w for w in document.get("warnings") or [] if "corrupt" in w]
