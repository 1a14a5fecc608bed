"""GPMF KLV parsing and scaling: hand-built buffers and bytes decoded by hand from real files."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from field.gopro import gpmf
from field.gopro.gpmf import GPMFError, decode_value, encode_array, encode_klv, encode_nest
from field.gopro.mp4 import read_mp4
from shared.errors import InputError


def klv(key: bytes, type_char: bytes, size: int, repeat: int, value: bytes) -> bytes:
    """Hand-written KLV (independent of the module's encoder)."""
    pad = (-len(value)) % 4
    return key + type_char + bytes([size]) + struct.pack(">H", repeat) + value + b"\0" * pad


def nest(key: bytes, *children: bytes) -> bytes:
    body = b"".join(children)
    return klv(key, b"\0", 4, len(body) // 4, body)


def test_header_and_padding_of_one_byte_value() -> None:
    data = klv(b"DEMO", b"b", 1, 1, b"\xff") + klv(b"DMO2", b"B", 1, 5, bytes(range(5)))
    items = gpmf.parse_klv(data)
    assert [(k.key, k.type, k.struct_size, k.repeat, k.offset) for k in items] == [
        ("DEMO", "b", 1, 1, 0),
        ("DMO2", "B", 1, 5, 12),
    ]
    assert decode_value(items[0]) == -1
    array = decode_value(items[1])
    assert isinstance(array, np.ndarray)
    assert array.reshape(-1).tolist() == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(
    ("type_char", "raw", "expected"),
    [
        (b"b", b"\x80", -128),
        (b"B", b"\x80", 128),
        (b"s", b"\xff\xfe", -2),
        (b"S", b"\xff\xfe", 65534),
        (b"l", b"\xff\xff\xff\xfd", -3),
        (b"L", b"\xff\xff\xff\xfd", 4294967293),
        (b"j", b"\xff" * 7 + b"\xfc", -4),
        (b"J", b"\x00" * 7 + b"\x05", 5),
        (b"f", struct.pack(">f", 1.5), 1.5),
        (b"d", struct.pack(">d", -2.25), -2.25),
    ],
)
def test_numeric_types(type_char: bytes, raw: bytes, expected: float) -> None:
    (item,) = gpmf.parse_klv(klv(b"TEST", type_char, len(raw), 1, raw))
    assert decode_value(item) == expected


def test_text_fourcc_date_guid_types() -> None:
    data = (
        klv(b"SIUN", b"c", 4, 1, b"m/s\xb2")
        + klv(b"UNIT", b"c", 3, 2, b"degm\0\0")
        + klv(b"FOUR", b"F", 4, 2, b"SNOWURBA")
        + klv(b"GPSU", b"U", 16, 1, b"170417192757.123")
        + klv(b"GUID", b"G", 16, 1, bytes(range(16)))
        + klv(b"UTF8", b"u", 3, 1, "µ".encode() + b"m")
    )
    items = gpmf.parse_klv(data)
    assert decode_value(items[0]) == "m/s²"
    assert decode_value(items[1]) == ["deg", "m"]
    assert decode_value(items[2]) == ["SNOW", "URBA"]
    assert decode_value(items[3]) == ["170417192757.123"]
    assert decode_value(items[4]) == bytes(range(16))
    assert decode_value(items[5]) == "µm"


def test_nested_stream_with_scal_and_units() -> None:
    accl = struct.pack(">6h", 418, -836, 1254, 0, 1, -1)
    payload = nest(
        b"DEVC",
        klv(b"DVID", b"L", 4, 1, struct.pack(">I", 1)),
        klv(b"DVNM", b"c", 1, 6, b"Camera"),
        nest(
            b"STRM",
            klv(b"TSMP", b"L", 4, 1, struct.pack(">I", 2)),
            klv(b"STNM", b"c", 1, 5, b"Accel"),
            klv(b"SIUN", b"c", 4, 1, b"m/s\xb2"),
            klv(b"SCAL", b"s", 2, 1, struct.pack(">h", 418)),
            klv(b"ACCL", b"s", 6, 2, accl),
        ),
    )
    parsed = gpmf.parse_payload(payload, source="t.mp4")
    (stream,) = parsed.find("ACCL")
    assert stream.device_id == 1 and stream.device_name == "Camera"
    assert stream.name == "Accel" and stream.units == "m/s²" and stream.total_samples == 2
    assert stream.raw().tolist() == [[418, -836, 1254], [0, 1, -1]]
    np.testing.assert_allclose(stream.scaled(), np.array([[1, -2, 3], [0, 1 / 418, -1 / 418]]))


def test_per_axis_scal_and_complex_type() -> None:
    # TYPE "fs[2]L": float, two int16, uint32 = 12 bytes a sample; SCAL one per element.
    sample = struct.pack(">fhhI", 2.5, 100, -300, 7)
    payload = nest(
        b"DEVC",
        nest(
            b"STRM",
            klv(b"TYPE", b"c", 1, 6, b"fs[2]L"),
            klv(b"SIUN", b"c", 2, 4, b"uTmmmm  "),
            klv(b"SCAL", b"l", 4, 4, struct.pack(">4i", 1, 10, 100, 1)),
            klv(b"MYDD", b"?", 12, 2, sample * 2),
        ),
    )
    (stream,) = gpmf.parse_payload(payload).find("MYDD")
    assert stream.type_string == "fs[2]L"
    assert stream.units == ["uT", "mm", "mm", ""]
    assert stream.elements == 4
    np.testing.assert_allclose(stream.scaled(), [[2.5, 10.0, -3.0, 7.0]] * 2)
    records = gpmf.structured_array(stream.data, stream.type_string)
    assert records["f3"].tolist() == [7, 7]


def test_scal_count_mismatch_and_zero_scale_raise() -> None:
    data = klv(b"XYZW", b"s", 6, 1, b"\0" * 6)
    (item,) = gpmf.parse_klv(data)
    bad = gpmf.GPMFStream(key="XYZW", data=item, scale=(1.0, 2.0))
    with pytest.raises(GPMFError, match="2 SCAL values for 3 elements"):
        bad.scaled()
    with pytest.raises(GPMFError, match="SCAL 0"):
        gpmf.GPMFStream(key="XYZW", data=item, scale=(0.0,)).scaled()


def test_fixed_point_q_types() -> None:
    data = klv(b"QNUM", b"q", 4, 1, struct.pack(">i", -(3 << 15)))  # -1.5 in Q15.16
    data += klv(b"QBIG", b"Q", 8, 1, struct.pack(">q", 5 << 31))  # 2.5 in Q31.32
    payload = nest(b"DEVC", nest(b"STRM", data))
    streams = gpmf.parse_payload(payload).streams
    assert streams[0].scaled().item() == -1.5
    assert streams[1].scaled().item() == 2.5


def test_stmp_tmpc_orin_orio_mtrx() -> None:
    matrix = [0, -1, 0, 1, 0, 0, 0, 0, 1]
    payload = nest(
        b"DEVC",
        nest(
            b"STRM",
            klv(b"STMP", b"J", 8, 1, struct.pack(">Q", 80577)),
            klv(b"MTRX", b"f", 36, 1, struct.pack(">9f", *matrix)),
            klv(b"ORIN", b"c", 3, 1, b"XzY"),
            klv(b"ORIO", b"c", 1, 3, b"ZXY"),
            klv(b"TMPC", b"f", 4, 1, struct.pack(">f", 31.125)),
            klv(b"GYRO", b"s", 6, 1, struct.pack(">3h", 1, 2, 3)),
        ),
    )
    (stream,) = gpmf.parse_payload(payload).streams
    assert stream.timestamp_us == 80577 and stream.temperature_c == 31.125
    assert stream.orientation_in == "XzY" and stream.orientation_out == "ZXY"
    np.testing.assert_array_equal(stream.orientation_matrix(), np.reshape(matrix, (3, 3)))
    # Without MTRX the matrix comes from ORIN/ORIO; a lower-case input axis is negated.
    no_mtrx = gpmf.GPMFStream(
        key="GYRO", data=stream.data, orientation_in="XzY", orientation_out="ZXY"
    )
    np.testing.assert_array_equal(no_mtrx.orientation_matrix(), [[0, -1, 0], [1, 0, 0], [0, 0, 1]])


def test_unknown_keys_and_types_are_skipped() -> None:
    payload = nest(
        b"DEVC",
        klv(b"ZZZZ", b"~", 2, 3, b"abcdef"),  # unknown type: kept as a KLV, no stream
        nest(b"STRM", klv(b"NEWK", b"S", 2, 2, b"\x00\x01\x00\x02")),  # unknown key: a stream
    )
    parsed = gpmf.parse_payload(payload)
    assert [k.key for k in parsed.klvs[0].children] == ["ZZZZ", "STRM"]
    assert [s.key for s in parsed.streams] == ["NEWK"]
    assert parsed.streams[0].raw().reshape(-1).tolist() == [1, 2]
    with pytest.raises(GPMFError, match="unsupported type '~'"):
        decode_value(parsed.klvs[0].children[0])


def test_compressed_and_missing_type_raise() -> None:
    (comp,) = gpmf.parse_klv(klv(b"ACCL", b"#", 4, 1, b"\0\0\0\0"))
    with pytest.raises(GPMFError, match="compressed GPMF 'ACCL'"):
        decode_value(comp, source="c.mp4")
    (complex_klv,) = gpmf.parse_klv(klv(b"MYDD", b"?", 4, 1, b"\0\0\0\0"))
    with pytest.raises(GPMFError, match="no preceding TYPE"):
        gpmf.raw_array(complex_klv)
    with pytest.raises(GPMFError, match="unsupported GPMF TYPE"):
        gpmf.expand_type_string("f[x]")
    with pytest.raises(GPMFError, match="is 2 bytes but the structure size is 4"):
        gpmf.raw_array(complex_klv, "s")
    (odd,) = gpmf.parse_klv(klv(b"ODDS", b"s", 3, 1, b"\0\0\0"))
    with pytest.raises(GPMFError, match="not a multiple"):
        gpmf.raw_array(odd)
    (text,) = gpmf.parse_klv(klv(b"TEXT", b"c", 2, 1, b"ab"))
    with pytest.raises(GPMFError, match="non-numeric"):
        gpmf.raw_array(text)


def test_length_past_buffer_raises_with_file_and_offset() -> None:
    good = klv(b"DVID", b"L", 4, 1, b"\0\0\0\1")
    # repeat 0xFFFF x size 255 = 16 MB declared in a 24-byte buffer.
    bad = good + b"ACCL" + b"s" + bytes([255]) + b"\xff\xff" + b"\0" * 8
    with pytest.raises(GPMFError, match=r"x\.mp4: GPMF 'ACCL' at byte 1012 declares 16711425"):
        gpmf.parse_klv(bad, source="x.mp4", base_offset=1000)
    # A child running past its nest (not past the buffer) is caught too.
    inner = b"TSMP" + b"L" + bytes([4]) + b"\x00\x02" + b"\0" * 8  # 2 x 4 bytes declared
    short_nest = b"STRM\0\x04\x00\x03" + inner  # the nest holds 12 bytes, its child needs 16
    with pytest.raises(GPMFError, match="'TSMP' at byte 8 declares 8 bytes but only 4 remain"):
        gpmf.parse_klv(short_nest)
    with pytest.raises(GPMFError, match="truncated GPMF header at byte 12"):
        gpmf.parse_klv(good + b"DEV")
    assert isinstance(GPMFError("x"), InputError)


def test_nesting_depth_is_bounded() -> None:
    data = klv(b"LEAF", b"L", 4, 1, b"\0\0\0\0")
    for _ in range(20):
        data = nest(b"DEVC", data)
    with pytest.raises(GPMFError, match="nesting deeper than 16"):
        gpmf.parse_klv(data)


def test_trailing_zero_padding_ends_the_list() -> None:
    data = klv(b"DVID", b"L", 4, 1, b"\0\0\0\1") + b"\0" * 12
    assert [k.key for k in gpmf.parse_klv(data)] == ["DVID"]


def test_encoder_round_trip() -> None:
    values = np.array([[1, -2, 3], [32767, -32768, 0]])
    data = encode_nest("DEVC", [encode_nest("STRM", [encode_array("GYRO", "s", values)])])
    (stream,) = gpmf.parse_payload(data).streams
    assert stream.raw().tolist() == values.tolist()
    with pytest.raises(ValueError, match="4 characters"):
        encode_klv("TOOLONG", "s", 2, 1, b"\0\0")
    with pytest.raises(ValueError, match="3 bytes for 2 x 1"):
        encode_klv("ABCD", "s", 2, 1, b"\0\0\0")


# Bytes copied from the real files with `xxd` (file offsets in the first gpmd payload).
#
# karma.mp4 (HERO5 Black), byte 323533:
#   53 49 55 4e 63 04 00 01 6d 2f 73 b2   SIUN 'c' 4x1 "m/s\xb2"
#   53 43 41 4c 73 02 00 01 01 a2 00 00   SCAL 's' 2x1 0x01a2 = 418
#   41 43 43 4c 73 06 00 c4               ACCL 's' 6 x 0x00c4 = 196 samples
#   10 96 fe 9c f9 f5                     4246, -356, -1547
#   10 af fe af fa 7b                     4271, -337, -1413
# karma.mp4, byte 324829: SCAL 's' 2x1 0x0eab = 3755; GYRO 's' 6 x 0x0188 = 392
#   00 ac 00 46 00 7d                     172, 70, 125
#   ff c3 00 09 fe e3                     -61, 9, -285
# max-heromode.mp4 (GoPro MAX), byte 417096: STMP 'J' 8x1 00 00 00 00 00 01 3a c1 = 80577 us
#   byte 417228: SCAL 's' 0x01a1 = 417; byte 417252: ACCL 's' 6 x 0x00c6 = 198
#   00 c6 f1 f7 02 a3                     198, -3593, 675
#   00 e3 f2 1b 02 6b                     227, -3557, 619
#   byte 418588: SCAL 's' 0x03ab = 939; GYRO first sample 00 44 00 d1 ff 6e = 68, 209, -146
REAL_FIRST_SAMPLES = {
    ("karma.mp4", "ACCL"): (418, 196, None, [[4246, -356, -1547], [4271, -337, -1413]]),
    ("karma.mp4", "GYRO"): (3755, 392, None, [[172, 70, 125], [-61, 9, -285]]),
    ("max-heromode.mp4", "ACCL"): (417, 198, 80577, [[198, -3593, 675], [227, -3557, 619]]),
    ("max-heromode.mp4", "GYRO"): (939, 198, 80577, [[68, 209, -146]]),
}


@pytest.mark.parametrize(("name", "key"), list(REAL_FIRST_SAMPLES))
def test_first_samples_of_real_files_match_hand_decoding(shared_data, name: str, key: str) -> None:
    scale, count, stmp, first = REAL_FIRST_SAMPLES[(name, key)]
    mp4 = read_mp4(shared_data / "gopro" / name)
    track = mp4.gpmf_track()
    payload = gpmf.parse_payload(
        mp4.read_sample(track, 0), source=name, base_offset=int(track.sample_offsets[0])
    )
    (stream,) = payload.find(key)
    assert stream.scale == (float(scale),)
    assert stream.samples == count and stream.total_samples == count
    assert stream.timestamp_us == stmp
    raw = stream.raw()
    assert raw[: len(first)].tolist() == first
    np.testing.assert_allclose(stream.scaled()[: len(first)], np.array(first) / scale)


def test_real_complex_streams_scale_per_element(shared_data) -> None:
    """The Karma drone's SYST ('?', TYPE "JJ", SCAL 1e6 and 1e3) and KBAT (15 elements)."""
    mp4 = read_mp4(shared_data / "gopro" / "karma.mp4")
    track = mp4.gpmf_track()
    payload = gpmf.parse_payload(mp4.read_sample(track, 0), source="karma.mp4")
    (syst,) = payload.find("SYST")
    assert syst.type_string == "JJ" and syst.scale == (1e6, 1e3)
    np.testing.assert_allclose(syst.scaled(), syst.raw() / [1e6, 1e3])
    (kbat,) = payload.find("KBAT")
    assert kbat.elements == 15 and len(kbat.scale) == 15
    assert kbat.scaled().shape == (kbat.samples, 15)
