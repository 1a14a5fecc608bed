"""Crafted inputs whose length or count fields claim gigabytes: parsers must check them
against the data really there before allocating (tracemalloc peak limits), and end fast.
"""

from __future__ import annotations

import struct
import time
import tracemalloc
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from field.gopro import gpmf
from field.gopro.mp4 import read_mp4
from shared.archive import ArchiveReader, cdr
from shared.archive import mcap_records as rec
from shared.errors import InputError

pytestmark = pytest.mark.timeout(60)

MB = 1 << 20


@contextmanager
def bounded(peak_bytes: int, seconds: float = 30.0) -> Iterator[None]:
    """Fail when the block allocates more than `peak_bytes` at once or runs too long.

    The time limit is a hang guard, not a speed check: each block takes well under a second
    even on a loaded machine (0.6 s at most at load 11), an unchecked count or an expanded
    bomb runs for minutes or forever, and the memory limit catches an allocation at once."""
    tracemalloc.start()
    start = time.perf_counter()
    try:
        yield
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    elapsed = time.perf_counter() - start
    assert peak < peak_bytes, f"peak allocation {peak} bytes (limit {peak_bytes})"
    assert elapsed < seconds, f"took {elapsed:.2f} s (limit {seconds} s)"


def refused(call: Callable[[], object], match: str, peak_bytes: int = 4 * MB) -> None:
    with bounded(peak_bytes), pytest.raises(InputError, match=match):
        call()


# ------------------------------------------------------------------------------------ GPMF


def test_gpmf_repeat_of_16_mb_in_a_tiny_buffer() -> None:
    data = b"ACCL" + struct.pack(">cBH", b"s", 255, 65535) + b"\x00" * 8
    refused(lambda: gpmf.parse_payload(data, source="p.bin"), r"p\.bin: GPMF 'ACCL' at byte 0")


def test_gpmf_nesting_deeper_than_the_limit() -> None:
    data = b""
    for _ in range(40):
        data = gpmf.encode_nest("DEVC", [data]) if data else gpmf.encode_string("DVNM", "x")
    refused(lambda: gpmf.parse_payload(data, source="p.bin"), r"p\.bin: GPMF nesting deeper")


# ------------------------------------------------------------------------------------- MP4


def _box(box_type: str, *parts: bytes) -> bytes:
    body = b"".join(parts)
    return struct.pack(">I4s", 8 + len(body), box_type.encode()) + body


def _full(box_type: str, *parts: bytes) -> bytes:
    return _box(box_type, b"\x00\x00\x00\x00", *parts)


def _u32(*values: int) -> bytes:
    return struct.pack(f">{len(values)}I", *values)


def _mp4(path: Path, *, stsz: bytes, stts: bytes, stsc: bytes, extra: bytes = b"") -> Path:
    """ftyp, a 64-byte mdat (payload at byte 24), then a moov with one 'gpmd' track."""
    mdat = _box("mdat", bytes(64))
    stbl = _box(
        "stbl",
        _full("stsd", _u32(1), _box("gpmd", bytes(8))),
        _full("stts", stts),
        _full("stsc", stsc),
        _full("stsz", stsz),
        _full("stco", _u32(1, 24)),
        extra,
    )
    mdia = _box(
        "mdia",
        _full("mdhd", _u32(0, 0, 1000, 10), bytes(4)),
        _full("hdlr", _u32(0), b"meta", bytes(12), b"GoPro MET\x00"),
        _box("minf", stbl),
    )
    moov = _box("moov", _full("mvhd", _u32(0, 0, 1000, 10), bytes(80)), _box("trak", mdia))
    path.write_bytes(_box("ftyp", b"mp42", _u32(0)) + mdat + moov)
    return path


def test_mp4_stsz_of_four_billion_fixed_size_samples(tmp_path: Path) -> None:
    path = _mp4(
        tmp_path / "a.mp4",
        stsz=_u32(1, 0xFFFFFFFF),
        stts=_u32(1, 0xFFFFFFFF, 1),
        stsc=_u32(1, 1, 0xFFFFFFFF, 1),
    )
    refused(lambda: read_mp4(path), r"a\.mp4: track 0: 'stsz' declares 4294967295 samples")


def test_mp4_run_length_tables_claiming_billions_are_cut_to_the_samples(tmp_path: Path) -> None:
    """stts/stsc/ctts runs of 2^32-1 samples for a track of 10: read with tiny memory."""
    path = _mp4(
        tmp_path / "b.mp4",
        stsz=_u32(4, 10),
        stts=_u32(1, 0xFFFFFFFF, 3),
        stsc=_u32(1, 1, 0xFFFFFFFF, 1),
        extra=_full("ctts", _u32(1, 0xFFFFFFFF, 2)),
    )
    with bounded(4 * MB):
        track = read_mp4(path).tracks[0]
    assert track.sample_count == 10
    assert track.decode_times.tolist() == [3 * k for k in range(10)]
    assert track.composition_times.tolist() == [3 * k + 2 for k in range(10)]
    assert track.sample_offsets.tolist() == [24 + 4 * k for k in range(10)]


def test_mp4_stz2_shorter_than_its_header(tmp_path: Path) -> None:
    path = _mp4(tmp_path / "e.mp4", stsz=_u32(4, 2), stts=_u32(1, 2, 1), stsc=_u32(1, 1, 2, 1))
    data = path.read_bytes().replace(b"stsz", b"stz2")  # same box, now read as 'stz2'
    at = data.index(b"stz2") - 4
    # Shrink the box to its 4-byte version/flags (the field size byte is missing) and pad
    # with a 'free' box so that every parent size stays right.
    short = data[:at] + _u32(12) + b"stz2" + bytes(4) + _u32(8) + b"free" + data[at + 20 :]
    path.write_bytes(short)
    refused(lambda: read_mp4(path), r"e\.mp4: box '\w+' at byte \d+ ")


def test_mp4_negative_ctts_count(tmp_path: Path) -> None:
    """A version-1 ctts whose sample count reads as negative (a corrupt count)."""
    ctts = _box("ctts", b"\x01\x00\x00\x00", _u32(2), struct.pack(">iIiI", -5, 7, 10, 1))
    path = _mp4(tmp_path / "f.mp4", stsz=_u32(4, 3), stts=_u32(1, 3, 1), stsc=_u32(1, 1, 3, 1),
                extra=ctts)  # fmt: skip
    track = read_mp4(path).tracks[0]
    assert track.composition_times.tolist() == [1, 2, 3]


def test_mp4_64_bit_box_size_of_8_exabytes(tmp_path: Path) -> None:
    path = tmp_path / "c.mp4"
    path.write_bytes(_box("ftyp", b"mp42", _u32(0)) + _u32(1) + b"moov" + struct.pack(">Q", 2**63))
    refused(lambda: read_mp4(path), r"c\.mp4: box 'moov' at byte 16 declares 9223372036854775808")


def test_mp4_timescale_zero_and_creation_time_beyond_year_9999(tmp_path: Path) -> None:
    path = _mp4(tmp_path / "d.mp4", stsz=_u32(4, 2), stts=_u32(1, 2, 1), stsc=_u32(1, 1, 2, 1))
    data = bytearray(path.read_bytes())
    mvhd = data.index(b"mvhd")
    data[mvhd + 8 : mvhd + 12] = _u32(0xFFFFFFFF)  # 136 years after 1904: fine
    path.write_bytes(bytes(data))
    assert read_mp4(path).creation_time is not None
    mdhd = data.index(b"mdhd")
    data[mdhd + 16 : mdhd + 20] = _u32(0)
    path.write_bytes(bytes(data))
    refused(lambda: read_mp4(path), r"d\.mp4: track 0 has a media timescale of 0")


# ------------------------------------------------------------------------------------ MCAP


def _mcap(path: Path, body: bytes) -> Path:
    footer = rec.record(rec.OP_FOOTER, rec.FOOTER_BODY.pack(0, 0, 0))
    path.write_bytes(rec.MAGIC + rec.header_record("ros2", "t") + body + footer + rec.MAGIC)
    return path


def test_mcap_header_length_of_4_gb(tmp_path: Path) -> None:
    path = tmp_path / "h.mcap"
    path.write_bytes(rec.MAGIC + rec.RECORD_HEAD.pack(rec.OP_HEADER, 2**32) + bytes(64))
    refused(
        lambda: ArchiveReader(path),
        r"h\.mcap: truncated MCAP file \(Header record cut short at byte 17",
    )


def test_mcap_zstd_bomb_chunk_is_skipped_without_inflating_it(tmp_path: Path) -> None:
    """A chunk that says 100 bytes but whose zstd frame inflates to 64 MB."""
    import zstandard

    bomb = zstandard.ZstdCompressor(level=1).compress(bytes(64 * MB))
    chunk_body = (
        struct.pack("<QQQI", 1, 2, 100, 0) + rec.pack_str("zstd") + struct.pack("<Q", len(bomb))
    )
    path = _mcap(tmp_path / "z.mcap", rec.record(rec.OP_CHUNK, chunk_body + bomb))
    del bomb
    with bounded(8 * MB), ArchiveReader(path, salvage=True) as reader:
        assert list(reader.messages()) == []
        assert any("skipped" in w and "index says 100" in w for w in reader.warnings)
    with pytest.raises(InputError), ArchiveReader(path) as reader:
        # Without salvage a damaged chunk of an unindexed file is skipped too (scan mode),
        # but there is then nothing to time: the archive is empty.
        reader.time_span_ns()


def test_mcap_message_index_of_a_terabyte(tmp_path: Path) -> None:
    from shared.archive import ArchiveWriter, DepthSample, depth_topic

    path = tmp_path / "i.mcap"
    with ArchiveWriter(path, compression="none") as writer:
        writer.write(depth_topic(0), DepthSample(stamp_ns=10, frame_id="d", depth_m=1.0))
    from .mutators import mcap_records

    data = bytearray(path.read_bytes())
    # The chunk index's field after the channel map is the message index length (u64);
    # its compression string (empty here) follows: claim 1 TB.
    index_at, _, length = next(r for r in mcap_records(bytes(data)) if r[1] == rec.OP_CHUNK_INDEX)
    body_end = index_at + 9 + length
    compression_len = 4 + 0  # "" as a u32-prefixed string
    size_fields = 8 + 8  # compressed and uncompressed size
    struct.pack_into("<Q", data, body_end - compression_len - size_fields - 8, 1 << 40)
    path.write_bytes(bytes(data))
    with ArchiveReader(path) as reader:
        refused(reader.topics, r"i\.mcap: damaged message index at offset \d+")


def test_cdr_string_of_4_gb() -> None:
    data = cdr.ENCAPSULATION_HEADER + struct.pack("<iII", 1, 2, 0xFFFFFFFF) + b"imu0"
    refused(lambda: cdr.decode_imu(data, "rec.mcap /imu0"), r"rec\.mcap /imu0: CDR message trunc")


# ----------------------------------------------------------------------------- text formats


def test_tum_timestamp_with_a_billion_digit_exponent(tmp_path: Path) -> None:
    from shared.formats.tum import read_tum

    path = tmp_path / "t.tum"
    path.write_text("1e999999999 0 0 0 0 0 0 1\n", encoding="utf-8")
    refused(lambda: read_tum(path), r"t\.tum:1: expected 8 numbers")
    path.write_text("1e18 0 0 0 0 0 0 1\n", encoding="utf-8")  # fits Decimal, not int64 ns
    refused(lambda: read_tum(path), r"t\.tum:1: expected 8 numbers")


@pytest.mark.parametrize("reader", ["kalibr imu", "kalibr target", "kalibr camchain", "euroc"])
def test_yaml_alias_bomb_is_not_expanded(tmp_path: Path, reader: str) -> None:
    """Nine levels of nine aliases: 387 million strings if anything walks or prints it."""
    from shared.calibration.kalibr import read_camchain, read_imu_yaml, read_target_yaml
    from shared.formats.euroc import _read_imu_yaml

    from .mutators import yaml_alias_bomb

    first = {"kalibr imu": "update_rate", "kalibr target": "tagCols"}.get(reader, "cam0")
    path = tmp_path / "bomb.yaml"
    path.write_text(
        yaml_alias_bomb(f"{first}: 1") + "target_type: aprilgrid\nT_BS: *l8\n", encoding="utf-8"
    )
    call = {
        "kalibr imu": lambda: read_imu_yaml(path),
        "kalibr target": lambda: read_target_yaml(path),
        "kalibr camchain": lambda: read_camchain(path),
        "euroc": lambda: _read_imu_yaml(path),
    }[reader]
    refused(call, r"bomb\.yaml: ", peak_bytes=8 * MB)


@pytest.mark.parametrize("kind", ["yaml", "json"])
def test_deeply_nested_documents(tmp_path: Path, kind: str) -> None:
    from shared.calibration.kalibr import read_imu_yaml
    from shared.formats.diveprofile import read_dive_index

    if kind == "yaml":
        path = tmp_path / "imu.yaml"
        path.write_text("update_rate: " + "[" * 50_000 + "]" * 50_000 + "\n", encoding="utf-8")
        refused(lambda: read_imu_yaml(path), r"imu\.yaml:1: not valid YAML", peak_bytes=64 * MB)
    else:
        (tmp_path / "dives.json").write_text("[" * 200_000, encoding="utf-8")
        refused(lambda: read_dive_index(tmp_path), r"dives\.json: not valid JSON", 64 * MB)


def test_csv_cell_beyond_the_field_limit(tmp_path: Path) -> None:
    from field.divecomputer.importers.shearwater_csv import read_shearwater_csv
    from shared.formats.diveprofile import read_dive_csv_arrays

    path = tmp_path / "d.csv"
    path.write_text("timestamp_s,depth_m,temperature_c\n" + "1" * 200_000 + ",1,1\n", "utf-8")
    refused(lambda: read_dive_csv_arrays(path), r"d\.csv:2: not a valid CSV line", 8 * MB)
    path.write_text("Start Date\n" + '"' + "x" * 200_000 + '"\n', "utf-8")
    refused(lambda: read_shearwater_csv(path), r"d\.csv:2: not a valid CSV line", 8 * MB)
