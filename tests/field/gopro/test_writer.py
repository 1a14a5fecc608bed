"""GoPro-like MP4 writer: write synthetic IMU + H.264, read back with our parser, PyAV, OpenCV."""

from __future__ import annotations

import struct
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from field.gopro import writer
from field.gopro.gpmf import parse_payload
from field.gopro.mp4 import read_mp4
from field.gopro.telemetry import read_telemetry
from field.gopro.writer import (
    annexb_to_avcc,
    chapter_file_name,
    encode_gpmf_imu_payload,
    encode_h264,
    write_gopro_chapters,
    write_gopro_mp4,
)
from shared.errors import OutputExistsError

FPS = Fraction(30000, 1001)
RATE_HZ = 200.0
WHEN = datetime(2026, 3, 4, 5, 6, 7, tzinfo=UTC)


@pytest.fixture(scope="module")
def video() -> writer.H264Stream:
    # 5 payloads of 30 frames (1.001 s each); GOP of 30 so every payload starts on a keyframe.
    frames = []
    for i in range(150):
        frame = np.zeros((64, 96, 3), np.uint8)
        frame[:, (i % 96) :, 0] = 200
        frame[(i % 64) :, :, 1] = 100
        frames.append(frame)
    return encode_h264(frames, fps=FPS, gop_frames=30)


def imu_truth(n_payloads: int, seed: int = 7) -> dict[str, np.ndarray]:
    """Uniform 200 Hz samples over n payloads of 1.001 s; values inside the int16 range."""
    rng = np.random.default_rng(seed)
    n = int(n_payloads * 1.001 * RATE_HZ)
    return {
        "t_s": np.arange(n) / RATE_HZ,
        "accl": rng.normal(0, 2, (n, 3)) + np.array([9.81, 0, 0]),
        "gyro": rng.normal(0, 0.5, (n, 3)),
    }


def payloads_from(truth: dict[str, np.ndarray], n_payloads: int) -> list[bytes]:
    t = truth["t_s"]
    out = []
    for p in range(n_payloads):
        inside = np.flatnonzero((t >= p * 1.001) & (t < (p + 1) * 1.001))
        frames = np.arange(30 * p, 30 * (p + 1))
        first_us = round(t[inside[0]] * 1e6)
        out.append(
            encode_gpmf_imu_payload(
                accl_mps2=truth["accl"][inside],
                gyro_rads=truth["gyro"][inside],
                accl_first_us=first_us,
                gyro_first_us=first_us,
                accl_total_before=int(inside[0]),
                gyro_total_before=int(inside[0]),
                temperature_c=30.0 + p,
                cori_quat_wxyz=np.tile([1.0, 0, 0, 0], (30, 1)),
                cori_first_us=round(frames[0] / FPS * 1_000_000),
                cori_total_before=int(frames[0]),
            )
        )
    return out


def write(path: Path, video: writer.H264Stream, payloads: list[bytes], **extra) -> Path:
    return write_gopro_mp4(
        path,
        video_packets=video.packets,
        sps=video.sps,
        pps=video.pps,
        width=video.width,
        height=video.height,
        fps=FPS,
        keyframe_flags=video.keyframes,
        gpmf_payloads=payloads,
        creation_time=WHEN,
        serial="C3441324500000",
        **extra,
    )


def test_encoder_is_libx264_with_sps_pps_and_gops(video: writer.H264Stream) -> None:
    import av

    assert "libx264" in av.codecs_available
    assert video.sps[0] & 0x1F == 7 and video.pps[0] & 0x1F == 8
    assert len(video.packets) == 150
    assert [i for i, k in enumerate(video.keyframes) if k] == [0, 30, 60, 90, 120]
    # AVCC: each packet is a chain of 4-byte lengths that ends exactly at its end.
    for packet in video.packets[:5]:
        pos = 0
        while pos < len(packet):
            pos += 4 + struct.unpack_from(">I", packet, pos)[0]
        assert pos == len(packet)


def test_round_trip_values_and_times(tmp_path: Path, video: writer.H264Stream) -> None:
    truth = imu_truth(5)
    path = write(tmp_path / "GX010001.MP4", video, payloads_from(truth, 5))
    telemetry = read_telemetry(path)
    assert telemetry.camera == "HERO9 Black" and telemetry.firmware == "HD9.01.01.72.00"
    assert telemetry.serial == "C3441324500000"
    assert telemetry.creation_time == WHEN
    for key, scale in (("ACCL", 418), ("GYRO", 939)):
        stream = telemetry.stream(key)
        assert stream.timing_method == "stmp"
        assert stream.samples == len(truth["t_s"])
        # int16 quantisation: at most half a step of 1 / SCAL.
        np.testing.assert_allclose(stream.values, truth[key.lower()], atol=0.5 / scale + 1e-12)
        # Times: STMP holds whole microseconds, so equal to 1 us.
        np.testing.assert_allclose(stream.times_s, truth["t_s"], atol=1.5e-6)
        assert stream.rate_hz == pytest.approx(RATE_HZ, rel=1e-5)
        assert stream.temperature_c.tolist() == [30, 31, 32, 33, 34]
    assert telemetry.stream("ACCL").units == "m/s²"
    # udta: FIRM, CAME and the Global Settings GPMF with the model and serial.
    mp4 = read_mp4(path)
    assert mp4.text_atom("FIRM") == "HD9.01.01.72.00" and len(mp4.user_data["CAME"]) == 16
    settings = parse_payload(mp4.user_data["GPMF"]).klvs[0].children
    assert {k.key: k.value for k in settings}["MINF"] == b"HERO9 Black"
    assert {k.key: k.value for k in settings}["CASN"] == b"C3441324500000"


def test_mp4_structure_pyav_and_opencv(tmp_path: Path, video: writer.H264Stream) -> None:
    import av
    import cv2

    path = write(tmp_path / "clip.mp4", video, payloads_from(imu_truth(5), 5))
    mp4 = read_mp4(path)
    track = mp4.video_track()
    assert (track.codec, track.handler_name, track.timescale) == ("avc1", "GoPro AVC", 90000)
    assert track.composition_times.tolist() == [3003 * i for i in range(150)]
    assert np.flatnonzero(track.keyframes).tolist() == [0, 30, 60, 90, 120]
    gpmd = mp4.gpmf_track()
    assert (gpmd.handler, gpmd.handler_name, gpmd.timescale) == ("meta", "GoPro MET", 1000)
    assert gpmd.durations.tolist() == [1001] * 5
    # The first packet read back through the sample table is the one written.
    assert mp4.read_sample(track, 0) == video.packets[0]
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert (stream.codec_context.width, stream.codec_context.height) == (96, 64)
        assert stream.average_rate == FPS
        assert [s.type for s in container.streams] == ["video", "data"]
        decoded = list(container.decode(video=0))
    assert len(decoded) == 150
    assert decoded[1].pts == 3003 and decoded[1].time_base == Fraction(1, 90000)
    capture = cv2.VideoCapture(str(path))
    frames = 0
    while capture.read()[0]:
        frames += 1
    capture.release()
    assert frames == 150


def test_same_inputs_same_bytes(tmp_path: Path, video: writer.H264Stream) -> None:
    payloads = payloads_from(imu_truth(5), 5)
    a = write(tmp_path / "a.mp4", video, payloads)
    b = write(tmp_path / "b.mp4", video, payloads_from(imu_truth(5), 5))
    assert a.read_bytes() == b.read_bytes()
    again = encode_h264([np.zeros((32, 32, 3), np.uint8)] * 3, fps=FPS)
    assert again.packets == encode_h264([np.zeros((32, 32, 3), np.uint8)] * 3, fps=FPS).packets


def test_refuses_to_overwrite_and_checks_inputs(tmp_path: Path, video: writer.H264Stream) -> None:
    payloads = payloads_from(imu_truth(5), 5)
    path = write(tmp_path / "x.mp4", video, payloads)
    with pytest.raises(OutputExistsError):
        write(path, video, payloads)
    write(path, video, payloads, overwrite=True)
    with pytest.raises(ValueError, match="payload durations for 5 payloads"):
        write(tmp_path / "y.mp4", video, payloads, payload_durations_s=[Fraction(1)])
    base: dict[str, Any] = dict(
        sps=video.sps, pps=video.pps, width=96, height=64, fps=FPS, gpmf_payloads=payloads,
        creation_time=WHEN,
    )  # fmt: skip
    with pytest.raises(ValueError, match="2 keyframe flags for 1 video packets"):
        write_gopro_mp4(
            tmp_path / "z.mp4", video_packets=[b"x"], keyframe_flags=[True, True], **base
        )
    with pytest.raises(ValueError, match="must start with a keyframe"):
        write_gopro_mp4(tmp_path / "z.mp4", video_packets=[b"x"], keyframe_flags=[False], **base)
    assert not (tmp_path / "y.mp4").exists() and not (tmp_path / "z.mp4").exists()


def test_chapters_are_named_like_gopro_and_keep_times(
    tmp_path: Path, video: writer.H264Stream
) -> None:
    truth = imu_truth(5)
    paths = write_gopro_chapters(
        tmp_path,
        file_number=42,
        payloads_per_chapter=2,
        video_packets=video.packets,
        sps=video.sps,
        pps=video.pps,
        width=96,
        height=64,
        fps=FPS,
        keyframe_flags=video.keyframes,
        gpmf_payloads=payloads_from(truth, 5),
        creation_time=WHEN,
    )
    assert [p.name for p in paths] == ["GX010042.MP4", "GX020042.MP4", "GX030042.MP4"]
    assert [read_mp4(p).video_track().sample_count for p in paths] == [60, 60, 30]
    second = read_telemetry(paths[1]).stream("ACCL")
    # Chapter 2 starts at payload 2 (2.002 s of the recording); its media time restarts at 0.
    expected = truth["t_s"][(truth["t_s"] >= 2.002) & (truth["t_s"] < 4.004)] - 2.002
    np.testing.assert_allclose(second.times_s, expected, atol=2e-6)


def test_chapter_names_and_ranges() -> None:
    assert chapter_file_name(1, 1) == "GX010001.MP4"
    assert chapter_file_name(12, 345, prefix="GH") == "GH120345.MP4"
    with pytest.raises(ValueError, match="out of GoPro's range"):
        chapter_file_name(100, 1)
    with pytest.raises(ValueError, match="at least 1"):
        writer.chapter_ranges([True], fps=FPS, payload_durations_s=[Fraction(1)],
                              payloads_per_chapter=0)  # fmt: skip
    # Keyframes only every 45 frames: the cut moves to the next keyframe.
    flags = [i % 45 == 0 for i in range(120)]
    ranges = writer.chapter_ranges(
        flags, fps=FPS, payload_durations_s=[Fraction(1001, 1000)] * 4, payloads_per_chapter=2
    )
    assert ranges == [(range(0, 90), range(0, 2)), (range(90, 120), range(2, 4))]


def test_annexb_to_avcc_and_large_offsets() -> None:
    stream = b"\0\0\0\1\x67SPS\0\0\1\x68PPS\0\0\0\1\x65IDR1\0\0\1\x06SEI"
    assert writer.split_annexb(stream) == [b"\x67SPS", b"\x68PPS", b"\x65IDR1", b"\x06SEI"]
    avcc = annexb_to_avcc(stream)
    assert avcc == b"\0\0\0\5\x65IDR1" + b"\0\0\0\4\x06SEI"
    assert annexb_to_avcc(stream, drop_parameter_sets=False).startswith(b"\0\0\0\4\x67SPS")
    # Offsets past 4 GiB switch the chunk table to co64.
    stbl = writer._stbl(writer._gpmd_entry(), [1000], [8], [5_000_000_000], None)
    assert b"co64" in stbl and b"stco" not in stbl
    assert struct.pack(">Q", 5_000_000_000) in stbl


def test_empty_payload_is_valid_and_skipped_in_timing(tmp_path: Path, video) -> None:
    """A second with no IMU samples (e.g. before the sensor starts) keeps its payload."""
    truth = imu_truth(5)
    payloads = payloads_from(truth, 5)
    t = truth["t_s"]
    # Replace payload 0 by an empty one; later payloads keep their TSMP (samples since start).
    payloads[0] = encode_gpmf_imu_payload(
        accl_mps2=np.zeros((0, 3)), gyro_rads=np.zeros((0, 3)), accl_first_us=0, gyro_first_us=0
    )
    (accl,) = parse_payload(payloads[0]).find("ACCL")
    assert accl.samples == 0 and accl.total_samples == 0
    stream = read_telemetry(write(tmp_path / "e.mp4", video, payloads)).stream("ACCL")
    np.testing.assert_allclose(stream.times_s, t[t >= 1.001], atol=1.5e-6)
