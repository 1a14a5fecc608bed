"""Writing GoPro-like MP4 files (for the simulator and for tests).

`write_gopro_mp4` lays a file out as a GoPro camera does: `ftyp` (mp41),
one `mdat` with each second of video followed by that second's GPMF payload,
then `moov` with a video track (handler 'vide', "GoPro AVC", avc1 + avcC) and
a telemetry track (handler 'meta', "GoPro MET", sample description 'gpmd',
timescale 1000, one sample per payload), and `udta` with FIRM (firmware),
CAME (camera id) and a GPMF "Global Settings" block (model, firmware,
serial). Offsets use `co64` when the file passes 4 GiB; the mdat uses the
64-bit size form then too. The same inputs always give the same bytes.

Video packets are H.264 access units in **AVCC form** (each NAL unit
prefixed by its 4-byte big-endian length, no start codes, no SPS/PPS inside),
which is what MP4 stores; `annexb_to_avcc` converts encoder output.
`encode_h264` produces such packets with PyAV's `libx264` encoder (the H.264
encoder PyAV 18's bundled FFmpeg ships; SPS/PPS come from its extradata with
the global-header flag set; no B-frames so pts == dts).

`encode_gpmf_imu_payload` builds one payload's DEVC with ACCL and GYRO
streams the way HERO8+ cameras write them (STMP, TSMP, STNM, ORIN/ORIO,
optional MTRX, SIUN, SCAL, TMPC, then int16 samples), and
`write_gopro_chapters` splits a long recording into chapter files named like
GoPro's (GX010042.MP4, GX020042.MP4, ...).
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from field.gopro import gpmf
from field.gopro.mp4 import MP4_EPOCH
from shared.fsutil import atomic_path

META_TIMESCALE = 1000  # GoPro's telemetry track counts milliseconds
VIDEO_TIMESCALE = 90000
_U32_MAX = 0xFFFFFFFF
_IDENTITY_MATRIX = struct.pack(">9I", 0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)


# ---------------------------------------------------------------- H.264 helpers


def split_annexb(data: bytes) -> list[bytes]:
    """NAL units of an Annex B byte stream (3- or 4-byte start codes removed)."""
    units: list[bytes] = []
    i = data.find(b"\x00\x00\x01")
    while i >= 0:
        start = i + 3
        nxt = data.find(b"\x00\x00\x01", start)
        end = len(data) if nxt < 0 else nxt
        unit = data[start:end]
        # A 4-byte start code leaves a trailing zero on the previous unit.
        if nxt >= 0 and unit.endswith(b"\x00"):
            unit = unit.rstrip(b"\x00")
        if unit:
            units.append(unit)
        i = nxt
    return units


def annexb_to_avcc(data: bytes, *, drop_parameter_sets: bool = True) -> bytes:
    """Annex B access unit -> AVCC (4-byte lengths). SPS/PPS/AUD dropped by default
    (they live in avcC)."""
    out = bytearray()
    for unit in split_annexb(data):
        if drop_parameter_sets and unit[0] & 0x1F in (7, 8, 9):
            continue
        out += struct.pack(">I", len(unit)) + unit
    return bytes(out)


@dataclass(frozen=True, kw_only=True)
class H264Stream:
    """Encoded video ready for `write_gopro_mp4`: AVCC packets, SPS, PPS, keyframe flags."""

    packets: list[bytes]
    sps: bytes
    pps: bytes
    keyframes: list[bool]
    width: int
    height: int
    fps: Fraction


def encode_h264(
    frames_rgb: Iterable[np.ndarray],
    *,
    fps: Fraction,
    gop_frames: int = 30,
    crf: int = 28,
    preset: str = "ultrafast",
) -> H264Stream:
    """Encode RGB frames (H x W x 3 uint8, even sizes) with PyAV's libx264.

    One thread, no B-frames, closed GOPs of `gop_frames`: the output is
    deterministic for a given libx264 build.
    """
    import av

    ctx: av.VideoCodecContext | None = None
    packets: list[bytes] = []
    keyframes: list[bool] = []
    width = height = 0

    def collect(encoded: Sequence[Any]) -> None:
        for packet in encoded:
            packets.append(annexb_to_avcc(bytes(packet)))
            keyframes.append(bool(packet.is_keyframe))

    for index, rgb in enumerate(frames_rgb):
        if ctx is None:
            height, width = int(rgb.shape[0]), int(rgb.shape[1])
            ctx = av.CodecContext.create("libx264", "w")
            ctx.width, ctx.height = width, height
            ctx.pix_fmt = "yuv420p"
            ctx.time_base = 1 / Fraction(fps)
            ctx.framerate = Fraction(fps)
            ctx.gop_size = gop_frames
            ctx.max_b_frames = 0
            ctx.thread_count = 1
            ctx.options = {
                "preset": preset,
                "crf": str(crf),
                "threads": "1",
                "keyint_min": str(gop_frames),
                "sc_threshold": "0",
            }
            ctx.flags |= av.codec.context.Flags.global_header
            ctx.open()
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame = frame.reformat(format="yuv420p")
        frame.pts = index
        collect(ctx.encode(frame))
    if ctx is None:
        raise ValueError("encode_h264: no frames")
    collect(ctx.encode(None))
    units = split_annexb(bytes(ctx.extradata or b""))
    sps = next((u for u in units if u[0] & 0x1F == 7), None)
    pps = next((u for u in units if u[0] & 0x1F == 8), None)
    if sps is None or pps is None:
        raise RuntimeError("libx264 extradata holds no SPS/PPS")
    return H264Stream(
        packets=packets, sps=sps, pps=pps, keyframes=keyframes, width=width, height=height,
        fps=Fraction(fps),
    )  # fmt: skip


# ---------------------------------------------------------------- GPMF payloads


def _imu_stream(
    key: str,
    name: str,
    units: str,
    values: np.ndarray,
    *,
    scale: int,
    first_us: int,
    total_after: int,
    temperature_c: float,
    orin: str,
    orio: str,
    matrix: np.ndarray | None,
) -> bytes:
    array = np.asarray(values, dtype=np.float64).reshape(-1, 3)
    # int16 as the sensor stores it; saturate like the sensor instead of wrapping.
    raw = np.clip(np.round(array * scale), -32768, 32767).astype(">i2")
    children = [
        gpmf.encode_array("STMP", "J", np.array([first_us], dtype=np.uint64)),
        gpmf.encode_array("TSMP", "L", np.array([total_after], dtype=np.uint32)),
        gpmf.encode_string("STNM", name),
    ]
    if matrix is not None:
        children.append(gpmf.encode_klv("MTRX", "f", 36, 1, np.asarray(matrix, ">f4").tobytes()))
    children += [
        gpmf.encode_klv("ORIN", "c", 1, len(orin), orin.encode("latin-1")),
        gpmf.encode_klv("ORIO", "c", 1, len(orio), orio.encode("latin-1")),
        gpmf.encode_string("SIUN", units),
        gpmf.encode_array("SCAL", "s", np.array([scale])),
        gpmf.encode_array("TMPC", "f", np.array([temperature_c])),
        gpmf.encode_klv(key, "s", 6, raw.shape[0], raw.tobytes()),
    ]
    return gpmf.encode_nest("STRM", children)


def encode_gpmf_imu_payload(
    *,
    accl_mps2: np.ndarray,
    gyro_rads: np.ndarray,
    accl_first_us: int,
    gyro_first_us: int,
    accl_total_before: int = 0,
    gyro_total_before: int = 0,
    temperature_c: float = 35.0,
    accl_scale: int = 418,
    gyro_scale: int = 939,
    orientation_in: str = "ZXY",
    orientation_out: str = "ZXY",
    matrix: np.ndarray | None = None,
    cori_quat_wxyz: np.ndarray | None = None,
    cori_first_us: int = 0,
    cori_total_before: int = 0,
    device_name: str = "HERO9 Black",
) -> bytes:
    """One GPMF payload: DEVC(DVID 1, DVNM) with a STRM for ACCL and one for GYRO.

    `accl_mps2` (n, 3) m/s² and `gyro_rads` (m, 3) rad/s are in the file's axis
    order (`orientation_in`, e.g. "ZXY" as HERO cameras store them); they are
    stored as int16 `round(value * scale)` (saturating), so a reader gets them
    back within 0.5 / scale. `*_first_us` is STMP: microseconds of the first
    sample since the recording started (media time 0 = first video frame).
    `*_total_before`: samples of that stream in earlier payloads (TSMP here is
    that plus this payload's count). `matrix` (3x3, file order -> camera) is
    written as MTRX when given.

    `cori_quat_wxyz` (k, 4), one camera orientation per video frame, adds a
    CORI stream (int16 / 32767) whose STMP `cori_first_us` is the start of its
    first frame: readers take the first CORI STMP as video frame 0, which keeps
    the times right in chapter files whose media time restarts at 0.
    """
    accl = np.asarray(accl_mps2, dtype=np.float64).reshape(-1, 3)
    gyro = np.asarray(gyro_rads, dtype=np.float64).reshape(-1, 3)
    sensor_matrix = None if matrix is None else np.asarray(matrix).reshape(3, 3)
    imu_streams = [
        _imu_stream(
            key,
            name,
            units,
            values,
            scale=scale,
            first_us=first_us,
            total_after=total_before + values.shape[0],
            temperature_c=temperature_c,
            orin=orientation_in,
            orio=orientation_out,
            matrix=sensor_matrix,
        )
        for key, name, units, values, scale, first_us, total_before in (
            ("ACCL", "Accelerometer", "m/s\u00b2", accl, accl_scale, accl_first_us,
             accl_total_before),
            ("GYRO", "Gyroscope", "rad/s", gyro, gyro_scale, gyro_first_us, gyro_total_before),
        )
    ]  # fmt: skip
    children = [
        gpmf.encode_array("DVID", "L", np.array([1])),
        gpmf.encode_string("DVNM", device_name),
        *imu_streams,
    ]
    if cori_quat_wxyz is not None:
        quats = np.asarray(cori_quat_wxyz, dtype=np.float64).reshape(-1, 4)
        raw = np.clip(np.round(quats * 32767), -32768, 32767).astype(">i2")
        children.append(
            gpmf.encode_nest(
                "STRM",
                [
                    gpmf.encode_array("STMP", "J", np.array([cori_first_us], dtype=np.uint64)),
                    gpmf.encode_array("TSMP", "L", np.array([cori_total_before + quats.shape[0]])),
                    gpmf.encode_string("STNM", "CameraOrientation"),
                    gpmf.encode_array("SCAL", "s", np.array([32767])),
                    gpmf.encode_klv("CORI", "s", 8, raw.shape[0], raw.tobytes()),
                ],
            )
        )
    return gpmf.encode_nest("DEVC", children)


def encode_global_settings(*, camera_model: str, firmware: str, serial: str) -> bytes:
    """The udta GPMF block HERO8+ cameras write: DEVC "Global Settings" with
    FMWR (firmware), CASN (serial) and MINF (model)."""
    return gpmf.encode_nest(
        "DEVC",
        [
            gpmf.encode_array("DVID", "L", np.array([1])),
            gpmf.encode_string("DVNM", "Global Settings"),
            gpmf.encode_string("FMWR", firmware),
            gpmf.encode_string("CASN", serial),
            gpmf.encode_string("MINF", camera_model),
        ],
    )


# ---------------------------------------------------------------- MP4 boxes


def _box(box_type: str, *parts: bytes) -> bytes:
    body = b"".join(parts)
    size = 8 + len(body)
    if size > _U32_MAX:
        return struct.pack(">I4sQ", 1, box_type.encode("latin-1"), size + 8) + body
    return struct.pack(">I4s", size, box_type.encode("latin-1")) + body


def _full_box(box_type: str, version: int, flags: int, *parts: bytes) -> bytes:
    return _box(box_type, struct.pack(">I", (version << 24) | flags), *parts)


def _mp4_seconds(when: datetime) -> int:
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return int((when - MP4_EPOCH).total_seconds())


def _runs(values: Sequence[int]) -> list[tuple[int, int]]:
    """Run-length pairs (count, value) for stts."""
    out: list[tuple[int, int]] = []
    for value in values:
        if out and out[-1][1] == value:
            out[-1] = (out[-1][0] + 1, value)
        else:
            out.append((1, value))
    return out


def _stbl(
    sample_entry: bytes,
    durations: Sequence[int],
    sizes: Sequence[int],
    offsets: Sequence[int],
    keyframes: Sequence[bool] | None,
) -> bytes:
    runs = _runs(durations)
    stts = _full_box(
        "stts", 0, 0, struct.pack(">I", len(runs)), b"".join(struct.pack(">II", *r) for r in runs)
    )
    # One sample per chunk, as GoPro does: stsc has a single run.
    stsc = _full_box("stsc", 0, 0, struct.pack(">IIII", 1, 1, 1, 1))
    stsz = _full_box(
        "stsz", 0, 0, struct.pack(">II", 0, len(sizes)), np.asarray(sizes, ">u4").tobytes()
    )
    if offsets and max(offsets) > _U32_MAX:
        chunk = _full_box(
            "co64", 0, 0, struct.pack(">I", len(offsets)), np.asarray(offsets, ">u8").tobytes()
        )
    else:
        chunk = _full_box(
            "stco", 0, 0, struct.pack(">I", len(offsets)), np.asarray(offsets, ">u4").tobytes()
        )
    parts = [_full_box("stsd", 0, 0, struct.pack(">I", 1), sample_entry), stts]
    if keyframes is not None and not all(keyframes):
        sync = [i + 1 for i, k in enumerate(keyframes) if k]
        parts.append(
            _full_box("stss", 0, 0, struct.pack(">I", len(sync)), np.asarray(sync, ">u4").tobytes())
        )
    parts += [stsc, stsz, chunk]
    return _box("stbl", *parts)


def _hdlr(handler: str, name: str) -> bytes:
    # QuickTime style like GoPro: component type 'mhlr' and a Pascal-string name.
    raw_name = name.encode("latin-1")
    return _full_box(
        "hdlr", 0, 0, b"mhlr", handler.encode("latin-1"), b"\x00" * 12,
        bytes([len(raw_name)]), raw_name,
    )  # fmt: skip


def _dinf() -> bytes:
    url = _full_box("url ", 0, 1)  # flag 1: media data in this file
    return _box("dinf", _full_box("dref", 0, 0, struct.pack(">I", 1), url))


def _tkhd(track_id: int, created: int, duration: int, width: int, height: int) -> bytes:
    return _full_box(
        "tkhd", 0, 0x0F,
        struct.pack(">IIIII", created, created, track_id, 0, duration),
        b"\x00" * 8, struct.pack(">hhhH", 0, 0, 0, 0), _IDENTITY_MATRIX,
        struct.pack(">II", width << 16, height << 16),
    )  # fmt: skip


def _mdhd(created: int, timescale: int, duration: int) -> bytes:
    language = 0x55C4  # 'und'
    return _full_box(
        "mdhd", 0, 0, struct.pack(">IIIIHH", created, created, timescale, duration, language, 0)
    )


def _avcc(sps: bytes, pps: bytes) -> bytes:
    if len(sps) < 4:
        raise ValueError("SPS too short (expected at least 4 bytes)")
    return _box(
        "avcC",
        bytes([1, sps[1], sps[2], sps[3], 0xFF, 0xE1]),
        struct.pack(">H", len(sps)), sps, b"\x01", struct.pack(">H", len(pps)), pps,
    )  # fmt: skip


def _avc1(width: int, height: int, sps: bytes, pps: bytes) -> bytes:
    compressor = b"GoPro AVC encoder"
    return _box(
        "avc1",
        b"\x00" * 6, struct.pack(">H", 1), b"\x00" * 16,
        struct.pack(">HHIIIH", width, height, 0x00480000, 0x00480000, 0, 1),
        bytes([len(compressor)]) + compressor.ljust(31, b"\x00"),
        struct.pack(">Hh", 0x18, -1),
        _avcc(sps, pps),
    )  # fmt: skip


def _gpmd_entry() -> bytes:
    return _box("gpmd", b"\x00" * 6, struct.pack(">H", 1), b"\x00" * 4)


def _video_timescale(fps: Fraction) -> tuple[int, int]:
    """(timescale, frame duration): 90 kHz as GoPro when it divides evenly."""
    if (VIDEO_TIMESCALE * fps.denominator) % fps.numerator == 0:
        return VIDEO_TIMESCALE, VIDEO_TIMESCALE * fps.denominator // fps.numerator
    return fps.numerator, fps.denominator


def camera_id(serial: str) -> bytes:
    """16 bytes for the CAME atom, derived from the serial (real cameras store a hash too)."""
    return hashlib.md5(serial.encode("utf-8"), usedforsecurity=False).digest()


def write_gopro_mp4(
    path: Path | str,
    *,
    video_packets: Sequence[bytes],
    sps: bytes,
    pps: bytes,
    width: int,
    height: int,
    fps: Fraction,
    keyframe_flags: Sequence[bool],
    gpmf_payloads: Sequence[bytes],
    payload_durations_s: Sequence[Fraction] | None = None,
    creation_time: datetime,
    camera_model: str = "HERO9 Black",
    firmware: str = "HD9.01.01.72.00",
    serial: str = "C3441324567890",
    overwrite: bool = False,
) -> Path:
    """Write a GoPro-like MP4 (see the module docstring for the layout).

    `video_packets`: H.264 access units in AVCC form, one per frame, decode
    order == presentation order; frame i is at i / fps seconds. `keyframe_flags`
    one per packet (the first must be a keyframe). `gpmf_payloads`: one GPMF
    payload per telemetry sample; `payload_durations_s` their durations
    (default: round(fps) frames each, i.e. 1.001 s at 29.97 fps), stored in
    milliseconds as GoPro does. `creation_time`: mvhd/mdhd creation time (UTC).
    Returns `path`; refuses to replace an existing file unless `overwrite`.
    """
    fps = Fraction(fps)
    if len(keyframe_flags) != len(video_packets):
        raise ValueError(
            f"{len(keyframe_flags)} keyframe flags for {len(video_packets)} video packets"
        )
    if not video_packets or not keyframe_flags[0]:
        raise ValueError("the video must start with a keyframe")
    if payload_durations_s is None:
        per = Fraction(round(fps)) / fps
        payload_durations_s = [per] * len(gpmf_payloads)
    if len(payload_durations_s) != len(gpmf_payloads):
        raise ValueError(
            f"{len(payload_durations_s)} payload durations for {len(gpmf_payloads)} payloads"
        )
    timescale, frame_ticks = _video_timescale(fps)
    payload_ms = [round(Fraction(d) * META_TIMESCALE) for d in payload_durations_s]
    payload_starts = np.concatenate([[0], np.cumsum(payload_ms)]).astype(np.int64)
    # Interleave: the frames before each payload's end, then the payload (as GoPro does).
    frame_ms = [Fraction(i, 1) / fps * META_TIMESCALE for i in range(len(video_packets))]
    order: list[tuple[str, int]] = []
    frame = 0
    for p in range(len(gpmf_payloads)):
        while frame < len(video_packets) and frame_ms[frame] < payload_starts[p + 1]:
            order.append(("v", frame))
            frame += 1
        order.append(("m", p))
    order += [("v", f) for f in range(frame, len(video_packets))]

    ftyp = _box("ftyp", b"mp41", struct.pack(">I", 0x20131018), b"mp41")
    data_size = sum(len(p) for p in video_packets) + sum(len(p) for p in gpmf_payloads)
    large = data_size + 8 > _U32_MAX
    mdat_header = (
        struct.pack(">I4sQ", 1, b"mdat", data_size + 16)
        if large
        else struct.pack(">I4s", data_size + 8, b"mdat")
    )
    video_offsets = [0] * len(video_packets)
    meta_offsets = [0] * len(gpmf_payloads)
    position = len(ftyp) + len(mdat_header)
    for kind, index in order:
        if kind == "v":
            video_offsets[index] = position
            position += len(video_packets[index])
        else:
            meta_offsets[index] = position
            position += len(gpmf_payloads[index])

    created = _mp4_seconds(creation_time)
    video_duration = frame_ticks * len(video_packets)
    meta_duration = int(payload_starts[-1])
    movie_duration = max(video_duration, meta_duration * timescale // META_TIMESCALE)
    video_trak = _box(
        "trak",
        _tkhd(1, created, video_duration, width, height),
        _box(
            "mdia",
            _mdhd(created, timescale, video_duration),
            _hdlr("vide", "GoPro AVC"),
            _box(
                "minf",
                _full_box("vmhd", 0, 1, b"\x00" * 8),
                _dinf(),
                _stbl(
                    _avc1(width, height, sps, pps),
                    [frame_ticks] * len(video_packets),
                    [len(p) for p in video_packets],
                    video_offsets,
                    list(keyframe_flags),
                ),
            ),
        ),
    )
    gmhd = _box("gmhd", _full_box("gmin", 0, 0, b"\x00" * 12), _box("gpmd", b"\x00" * 4))
    meta_trak = _box(
        "trak",
        _tkhd(2, created, meta_duration * timescale // META_TIMESCALE, 0, 0),
        _box(
            "mdia",
            _mdhd(created, META_TIMESCALE, meta_duration),
            _hdlr("meta", "GoPro MET"),
            _box(
                "minf",
                gmhd,
                _dinf(),
                _stbl(
                    _gpmd_entry(),
                    payload_ms,
                    [len(p) for p in gpmf_payloads],
                    meta_offsets,
                    None,
                ),
            ),
        ),
    )
    mvhd = _full_box(
        "mvhd", 0, 0,
        struct.pack(">IIII", created, created, timescale, movie_duration),
        struct.pack(">IH", 0x00010000, 0x0100), b"\x00" * 10, _IDENTITY_MATRIX,
        b"\x00" * 24, struct.pack(">I", 3),
    )  # fmt: skip
    udta = _box(
        "udta",
        _box("FIRM", firmware.encode("latin-1")),
        _box("CAME", camera_id(serial)),
        _box("GPMF", encode_global_settings(
            camera_model=camera_model, firmware=firmware, serial=serial)),
    )  # fmt: skip
    moov = _box("moov", mvhd, udta, video_trak, meta_trak)

    with atomic_path(path, overwrite=overwrite) as tmp, tmp.open("wb") as out:
        _write_all(out, ftyp, mdat_header, order, video_packets, gpmf_payloads, moov)
    return Path(path)


def _write_all(
    out: BinaryIO,
    ftyp: bytes,
    mdat_header: bytes,
    order: list[tuple[str, int]],
    video_packets: Sequence[bytes],
    gpmf_payloads: Sequence[bytes],
    moov: bytes,
) -> None:
    out.write(ftyp)
    out.write(mdat_header)
    for kind, index in order:
        out.write(video_packets[index] if kind == "v" else gpmf_payloads[index])
    out.write(moov)


# ---------------------------------------------------------------- chapters


def chapter_file_name(chapter: int, file_number: int, *, prefix: str = "GX") -> str:
    """GoPro's chapter naming (HERO6+): GX + 2-digit chapter + 4-digit file number + .MP4.

    `prefix` "GX" for HEVC-era cameras (as HERO9 names all files), "GH" for AVC.
    """
    if not 1 <= chapter <= 99 or not 0 <= file_number <= 9999:
        raise ValueError(f"chapter {chapter} / file number {file_number} out of GoPro's range")
    return f"{prefix}{chapter:02d}{file_number:04d}.MP4"


def chapter_ranges(
    keyframe_flags: Sequence[bool],
    *,
    fps: Fraction,
    payload_durations_s: Sequence[Fraction],
    payloads_per_chapter: int,
) -> list[tuple[range, range]]:
    """(frame range, payload range) of each chapter: payloads are cut every
    `payloads_per_chapter`; each video cut is at the first keyframe at or after
    the chapter's start time (so every chapter starts with a keyframe)."""
    if payloads_per_chapter < 1:
        raise ValueError("payloads_per_chapter must be at least 1")
    starts = np.concatenate([[0], np.cumsum([Fraction(d) for d in payload_durations_s])])
    n_payloads = len(payload_durations_s)
    cuts_p = [*range(0, n_payloads, payloads_per_chapter), n_payloads]
    cuts_f = [0]
    for p in cuts_p[1:-1]:
        first = int(np.ceil(float(starts[p] * fps) - 1e-9))
        while first < len(keyframe_flags) and not keyframe_flags[first]:
            first += 1
        cuts_f.append(min(first, len(keyframe_flags)))
    cuts_f.append(len(keyframe_flags))
    return [
        (range(cuts_f[i], cuts_f[i + 1]), range(cuts_p[i], cuts_p[i + 1]))
        for i in range(len(cuts_p) - 1)
    ]


def write_gopro_chapters(
    folder: Path | str,
    *,
    file_number: int,
    payloads_per_chapter: int,
    video_packets: Sequence[bytes],
    sps: bytes,
    pps: bytes,
    width: int,
    height: int,
    fps: Fraction,
    keyframe_flags: Sequence[bool],
    gpmf_payloads: Sequence[bytes],
    payload_durations_s: Sequence[Fraction] | None = None,
    creation_time: datetime,
    camera_model: str = "HERO9 Black",
    firmware: str = "HD9.01.01.72.00",
    serial: str = "C3441324567890",
    overwrite: bool = False,
) -> list[Path]:
    """Split one recording into GoPro chapter files GX01NNNN.MP4, GX02NNNN.MP4, ...

    Payloads keep their STMP/TSMP (they count from the start of the recording,
    as on the camera); each chapter's media time starts again at 0. Returns the
    paths in chapter order.
    """
    fps = Fraction(fps)
    if payload_durations_s is None:
        payload_durations_s = [Fraction(round(fps)) / fps] * len(gpmf_payloads)
    ranges = chapter_ranges(
        keyframe_flags,
        fps=fps,
        payload_durations_s=payload_durations_s,
        payloads_per_chapter=payloads_per_chapter,
    )
    paths: list[Path] = []
    for chapter, (frames, payloads) in enumerate(ranges, start=1):
        if not len(frames):
            raise ValueError(f"chapter {chapter} has no keyframe to start on")
        paths.append(
            write_gopro_mp4(
                Path(folder) / chapter_file_name(chapter, file_number),
                video_packets=video_packets[frames.start : frames.stop],
                sps=sps,
                pps=pps,
                width=width,
                height=height,
                fps=fps,
                keyframe_flags=keyframe_flags[frames.start : frames.stop],
                gpmf_payloads=gpmf_payloads[payloads.start : payloads.stop],
                payload_durations_s=payload_durations_s[payloads.start : payloads.stop],
                creation_time=creation_time,
                camera_model=camera_model,
                firmware=firmware,
                serial=serial,
                overwrite=overwrite,
            )
        )
    return paths
