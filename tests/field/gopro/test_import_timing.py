"""The importer's IMU times come from the one telemetry reader: lost payloads shift nothing,
a late IMU keeps its true times and is said to be late."""

from __future__ import annotations

import re
from collections.abc import Callable
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from field.gopro import cameras
from field.gopro.cameras import GoProCamera
from field.gopro.importer import ImportOptions, import_recording
from field.gopro.mp4 import read_mp4
from field.gopro.telemetry import read_telemetry
from field.gopro.writer import encode_gpmf_imu_payload, encode_h264, write_gopro_mp4
from shared.archive import ArchiveReader
from shared.errors import InputError

FPS = Fraction(30000, 1001)
FRAMES = 30  # per 1.001 s payload
IMU = 200  # samples per payload and stream
PAYLOAD_US = 1_001_000
CREATED = datetime(2024, 6, 2, 9, 30, 0, tzinfo=UTC)
CREATED_NS = int(CREATED.timestamp()) * 10**9


@pytest.fixture(scope="module")
def video() -> dict[str, object]:
    rng = np.random.default_rng(11)
    base = rng.integers(0, 255, size=(120, 160, 3), dtype=np.uint8)
    stream = encode_h264([np.roll(base, 2 * i, axis=0) for i in range(5 * FRAMES)], fps=FPS)
    return {
        "video_packets": stream.packets,
        "sps": stream.sps,
        "pps": stream.pps,
        "width": stream.width,
        "height": stream.height,
        "fps": FPS,
        "keyframe_flags": stream.keyframes,
        "creation_time": CREATED,
    }


def _write(
    path: Path,
    video: dict[str, object],
    *,
    imu_late_us: int = 0,
    patch: Callable[[bytes], bytes] = lambda payload: payload,
) -> Path:
    """Five payloads of HERO8+-style telemetry: ACCL/GYRO at 200 Hz with STMP/TSMP, and
    CORI (one sample per frame, STMP = the frame's start) tying STMP to video frame 0."""
    payloads = []
    for p in range(5):
        k = p * IMU + np.arange(IMU)
        gyro = np.column_stack([np.sin(k / 50.0), np.cos(k / 70.0), 0.01 * k]) * 0.3
        payloads.append(
            patch(
                encode_gpmf_imu_payload(
                    accl_mps2=np.tile([0.0, -9.81, 0.0], (IMU, 1)),
                    gyro_rads=gyro,
                    accl_first_us=p * PAYLOAD_US + imu_late_us,
                    gyro_first_us=p * PAYLOAD_US + imu_late_us,
                    accl_total_before=p * IMU,
                    gyro_total_before=p * IMU,
                    orientation_in="XzY",
                    orientation_out="XYZ",
                    cori_quat_wxyz=np.tile([1.0, 0.0, 0.0, 0.0], (FRAMES, 1)),
                    cori_first_us=p * PAYLOAD_US,
                    cori_total_before=p * FRAMES,
                )
            )
        )
    return write_gopro_mp4(path, gpmf_payloads=payloads, **video)  # type: ignore[arg-type]


def _corrupt_payloads(source: Path, target: Path, indices: list[int]) -> Path:
    """A copy of `source` whose gpmd samples `indices` have a nest longer than the payload."""
    meta = read_mp4(source).gpmf_track()
    data = bytearray(source.read_bytes())
    for index in indices:
        offset = int(meta.sample_offsets[index])
        data[offset + 6 : offset + 8] = b"\xff\xff"
    target.write_bytes(bytes(data))
    return target


def _import(
    source: Path, session: Path
) -> tuple[np.ndarray, np.ndarray, list[str], dict[str, Any]]:
    """IMU media times (ns from the first frame), gyro, warnings, session.yaml."""
    result = import_recording(ImportOptions(), [source], session)
    with ArchiveReader(session / "recording.mcap") as reader:
        imu = reader.read_imu("/imu0")
    document = yaml.safe_load((session / "session.yaml").read_text())
    start_ns = document["chapters"][0]["start_ns"]
    return imu.stamps_ns - start_ns, imu.gyro_rad_s, result.warnings, document


def test_corrupt_first_payload_keeps_the_survivors_times(tmp_path: Path, video) -> None:
    clean = _write(tmp_path / "GX010001.MP4", video)
    broken = _corrupt_payloads(clean, tmp_path / "GX010002.MP4", [0])
    times, gyro, _, _ = _import(clean, tmp_path / "clean")
    survived, survived_gyro, warnings, document = _import(broken, tmp_path / "broken")
    assert times[0] == 0 and survived.size == 4 * IMU
    # Payloads 1-4 as in the clean file: same samples at the same times (not 1.001 s early).
    np.testing.assert_array_equal(survived, times[IMU:])
    np.testing.assert_array_equal(survived_gyro, gyro[IMU:])
    assert survived[0] == PAYLOAD_US * 1000
    assert any("1 of 5 GPMF payloads corrupt and skipped" in w for w in warnings)
    assert any("IMU starts 1001.0 ms after the first video frame" in w for w in warnings)
    assert document["chapters"][0]["imu_start_s"] == pytest.approx(1.001)
    assert "payload 1" in document["devices"]["imu0"]["clock_origin"]
    # `gopro telemetry` reads the same file the same way (one reader), skipping the payload.
    telemetry = read_telemetry(broken, keys={"GYRO"})
    assert telemetry.corrupt_payloads == 1 and "1 of 5" in telemetry.warnings[0]
    np.testing.assert_array_equal(telemetry.stream("GYRO").times_ns, survived)


def test_missing_payload_mid_chapter_leaves_a_gap_only(tmp_path: Path, video) -> None:
    clean = _write(tmp_path / "GX010001.MP4", video)
    broken = _corrupt_payloads(clean, tmp_path / "GX010002.MP4", [2])
    times, gyro, _, _ = _import(clean, tmp_path / "clean")
    survived, survived_gyro, warnings, _ = _import(broken, tmp_path / "broken")
    kept = np.r_[0 : 2 * IMU, 3 * IMU : 5 * IMU]
    np.testing.assert_array_equal(survived, times[kept])
    np.testing.assert_array_equal(survived_gyro, gyro[kept])
    gap = np.diff(survived).max()
    assert gap == pytest.approx((IMU + 1) * PAYLOAD_US * 1000 / IMU, rel=1e-6)
    assert any("1 of 5 GPMF payloads corrupt" in w for w in warnings)


def test_late_imu_keeps_its_true_times_and_is_said(tmp_path: Path, video) -> None:
    late = _write(tmp_path / "GX010003.MP4", video, imu_late_us=59_000)
    times, _, warnings, document = _import(late, tmp_path / "late")
    assert times[0] == 59_000_000  # ns after the first frame, as STMP says
    np.testing.assert_allclose(np.diff(times), PAYLOAD_US * 1000 / IMU, atol=1)
    assert document["chapters"][0]["imu_start_s"] == pytest.approx(0.059)
    assert [w for w in warnings if "IMU starts" in w] == [
        "GX010003.MP4: the IMU starts 59.0 ms after the first video frame (its samples keep "
        "the camera's times; the first frames have no IMU before them)"
    ]
    # On time: nothing said.
    on_time = _write(tmp_path / "GX010004.MP4", video)
    _, _, quiet, document = _import(on_time, tmp_path / "on_time")
    assert not [w for w in quiet if "IMU starts" in w]
    assert document["chapters"][0]["imu_start_s"] == 0.0


def _two_values_per_sample(payload: bytes) -> bytes:
    """ACCL's 200 samples of 3 int16 relabelled as 300 samples of 2 (same bytes)."""
    header = b"ACCLs\x06" + IMU.to_bytes(2, "big")
    assert payload.count(header) == 1
    return payload.replace(header, b"ACCLs\x04" + (IMU * 3 // 2).to_bytes(2, "big"))


@pytest.mark.parametrize(
    ("patch", "camera", "problem"),
    [
        (_two_values_per_sample, None, "ACCL has 2 values per sample (expected 3)"),
        (
            lambda payload: payload.replace(b"ORIN", b"XRIN"),  # an unknown key: no ORIN
            GoProCamera(
                name="Mystery Cam", firmware_prefixes=(), hfov_wide_deg=118.2, imu_axis_order=None
            ),
            "ACCL has no ORIN and the axis order of this camera model (Mystery Cam) is unknown",
        ),
    ],
)
def test_unusable_imu_streams_keep_the_video(
    tmp_path: Path,
    video,
    monkeypatch: pytest.MonkeyPatch,
    patch: Callable[[bytes], bytes],
    camera: GoProCamera | None,
    problem: str,
) -> None:
    if camera is not None:  # a model whose data order nobody knows (every listed one is known)
        monkeypatch.setattr(cameras, "lookup_camera", lambda **_: camera)
    path = _write(tmp_path / "GX010005.MP4", video, patch=patch)
    result = import_recording(ImportOptions(), [path], tmp_path / "s")
    assert result.frames == 5 * FRAMES and result.imu_samples == 0
    assert [w for w in result.warnings if problem in w and "without IMU" in w]
    with pytest.raises(InputError, match=re.escape(problem)):
        import_recording(ImportOptions(require_imu=True), [path], tmp_path / "strict")
    assert not (tmp_path / "strict").exists()


def test_every_payload_corrupt(tmp_path: Path, video) -> None:
    clean = _write(tmp_path / "GX010001.MP4", video)
    broken = _corrupt_payloads(clean, tmp_path / "GX010006.MP4", list(range(5)))
    with pytest.raises(InputError, match=r"GX010006\.MP4: 5 of 5 GPMF payloads corrupt.*left"):
        read_telemetry(broken)
    result = import_recording(ImportOptions(), [broken], tmp_path / "s")
    assert result.frames == 5 * FRAMES and result.imu_samples == 0
    assert any("5 of 5 GPMF payloads corrupt" in w for w in result.warnings)
    assert any("no ACCL or GYRO samples" in w for w in result.warnings)


@pytest.mark.parametrize(("name", "timing"), [("karma.mp4", "tsmp"), ("max-heromode.mp4", "stmp")])
def test_real_file_with_corrupt_payloads(
    shared_data: Path, tmp_path: Path, name: str, timing: str
) -> None:
    """Real telemetry, its first and a middle payload corrupted: each surviving sample keeps
    its time within 5 ms (STMP files exactly; TSMP files refit the line through fewer
    payload starts, which are in whole milliseconds)."""
    source = shared_data / "gopro" / name
    count = read_mp4(source).gpmf_track().sample_count
    lost_payloads = [0, count // 2]
    broken = _corrupt_payloads(source, tmp_path / name, lost_payloads)
    for key in ("ACCL", "GYRO"):
        clean = read_telemetry(source, keys={key}).stream(key)
        survived = read_telemetry(broken, keys={key}).stream(key)
        lost = np.isin(clean.payload_index, lost_payloads)
        assert survived.timing_method == timing
        np.testing.assert_array_equal(survived.values, clean.values[~lost])  # the same samples
        shift_ns = np.abs(survived.times_ns - clean.times_ns[~lost]).max()
        assert shift_ns < (5_000_000 if timing == "tsmp" else 100_000), (key, shift_ns)
    # The importer's IMU is those samples: the faster stream's times, first payload absent.
    stamps, _, warnings, document = _import(broken, tmp_path / "broken")
    base = read_telemetry(broken, keys={"GYRO"}).stream("GYRO")
    assert np.isin(stamps, base.times_ns).all() and stamps[0] > 0.9e9
    assert document["devices"]["imu0"]["timing"] == timing
    assert any(f"2 of {count} GPMF payloads corrupt" in w for w in warnings)
