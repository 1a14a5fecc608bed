"""MP4 box walking on the real GoPro files and on hand-built or broken files."""

from __future__ import annotations

import struct
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from field.gopro.mp4 import (
    MissingMoovError,
    avcc_to_annexb,
    iter_boxes,
    parse_codec_config,
    read_mp4,
)
from shared.errors import InputError


def box(box_type: bytes, *parts: bytes) -> bytes:
    body = b"".join(parts)
    return struct.pack(">I", 8 + len(body)) + box_type + body


def full(box_type: bytes, *parts: bytes) -> bytes:
    return box(box_type, b"\0\0\0\0", *parts)


def trak(handler: bytes, codec: bytes, *, offsets_box: bytes = b"", timescale: int = 1000) -> bytes:
    """A small trak: 2 samples of 10 and 20 bytes in one chunk, 100 ticks each, sample 2 sync."""
    stbl = box(
        b"stbl",
        full(b"stsd", struct.pack(">I", 1), box(codec, b"\0" * 6, b"\0\1", b"\0" * 4)),
        full(b"stts", struct.pack(">III", 1, 2, 100)),
        full(b"stss", struct.pack(">II", 1, 2)),
        full(b"stsc", struct.pack(">IIII", 1, 1, 2, 1)),
        full(b"stsz", struct.pack(">IIII", 0, 2, 10, 20)),
        offsets_box or full(b"stco", struct.pack(">II", 1, 8)),
    )
    return box(
        b"trak",
        full(b"tkhd", b"\0" * 8, struct.pack(">I", 7), b"\0" * 68),
        box(
            b"mdia",
            full(b"mdhd", b"\0" * 8, struct.pack(">II", timescale, 200), b"\0" * 4),
            full(b"hdlr", b"\0" * 4, handler, b"\0" * 12, b"Handler\0"),
            box(b"minf", stbl),
        ),
    )


def test_karma_tracks_and_sample_tables(shared_data: Path) -> None:
    mp4 = read_mp4(shared_data / "gopro" / "karma.mp4")
    assert mp4.major_brand == "mp41"
    assert mp4.creation_time == datetime(2017, 4, 17, 19, 27, 57, tzinfo=UTC)
    assert mp4.text_atom("FIRM") == "HD5.02.02.00.00"
    assert mp4.text_atom("NOPE") is None
    assert [(t.handler, t.codec) for t in mp4.tracks] == [
        ("vide", "avc1"), ("soun", "mp4a"), ("tmcd", "tmcd"), ("meta", "gpmd"), ("meta", "fdsc"),
    ]  # fmt: skip
    video = mp4.video_track()
    assert (video.width, video.height, video.timescale) == (854, 480, 90000)
    assert video.handler_name == "GoPro AVC" and video.kind == "video"
    # stts: 362 frames of 3003 ticks (29.97 fps); stss: 46 keyframes, frame 0 the first.
    assert video.sample_count == 362 and set(video.durations.tolist()) == {3003}
    assert int(video.keyframes.sum()) == 46 and video.keyframes[0] and video.keyframes[8]
    assert not video.keyframes[1]
    assert video.codec_config[0] == 1  # avcC configurationVersion
    np.testing.assert_array_equal(video.composition_times, video.decode_times)  # no ctts
    # stco at byte 4119087: 00 00 01 6a (362 chunks) 00 00 01 e0 (first chunk at 480);
    # stsz at 4117619: first sample 0x0000d6f9 bytes.
    assert int(video.sample_offsets[0]) == 480 and int(video.sample_sizes[0]) == 0xD6F9
    gpmd = mp4.gpmf_track()
    assert gpmd.timescale == 1000 and gpmd.sample_count == 13
    assert gpmd.decode_times.tolist() == [1001 * i for i in range(13)]
    assert int(gpmd.sample_offsets[0]) == 0x4EF35  # stco of the gpmd track
    ((mdat_offset, mdat_size),) = mp4.mdat_ranges
    ends = video.sample_offsets.astype(np.int64) + video.sample_sizes
    assert int(video.sample_offsets.min()) >= mdat_offset
    assert int(ends.max()) <= mdat_offset + mdat_size
    # One sample read on its own equals the same sample read by the iterator.
    first_offset, first_bytes = next(mp4.iter_samples(gpmd))
    assert first_offset == 0x4EF35 and first_bytes == mp4.read_sample(gpmd, 0)
    assert first_bytes[:4] == b"DEVC"


def test_max_gpmd_last_payload_is_short_and_udta_has_gpmf(shared_data: Path) -> None:
    mp4 = read_mp4(shared_data / "gopro" / "max-heromode.mp4")
    gpmd = mp4.gpmf_track()
    # stts: 10 x 1001 then 1 x 533 (0x215): the video stopped mid-second.
    assert gpmd.durations.tolist() == [1001] * 10 + [533]
    assert mp4.user_data["GPMF"][:4] == b"DEVC"
    assert mp4.video_track().duration == 945945
    assert mp4.duration_s == pytest.approx(946560 / 90000)


def test_iter_boxes_walks_without_reading_payloads(shared_data: Path) -> None:
    path = shared_data / "gopro" / "karma.mp4"
    with path.open("rb") as f:
        top = list(iter_boxes(f, 0, path.stat().st_size, source=path.name))
    assert [(b.type, b.offset, b.size) for b in top] == [
        ("ftyp", 0, 20), ("mdat", 20, 4115964), ("moov", 4115984, 18663),
    ]  # fmt: skip


def test_hand_built_co64_and_large_mdat_in_sparse_file(tmp_path: Path) -> None:
    """A 5 GB file (sparse) whose samples sit past 4 GiB: 64-bit mdat size and co64."""
    offset = 5_000_000_000
    ftyp = box(b"ftyp", b"mp41", b"\0\0\0\0")
    co64 = full(b"co64", struct.pack(">IQ", 1, offset))
    moov = box(b"moov", trak(b"meta", b"gpmd", offsets_box=co64))
    mdat_size = offset + 30 - len(ftyp)
    path = tmp_path / "big.mp4"
    with path.open("wb") as f:
        f.write(ftyp + struct.pack(">I4sQ", 1, b"mdat", mdat_size))
        f.seek(offset)
        f.write(b"A" * 10 + b"B" * 20)
        f.write(moov)
    mp4 = read_mp4(path)
    (track,) = mp4.tracks
    assert track.sample_offsets.tolist() == [offset, offset + 10]
    assert track.decode_times.tolist() == [0, 100]
    assert track.keyframes.tolist() == [False, True]
    assert mp4.read_sample(track, 1) == b"B" * 20
    assert mp4.mdat_ranges == [(len(ftyp) + 16, mdat_size - 16)]


def test_no_gpmd_track_names_what_was_found(tmp_path: Path) -> None:
    path = tmp_path / "X.mp4"
    moov = box(b"moov", trak(b"vide", b"avc1"), trak(b"soun", b"mp4a"))
    path.write_bytes(box(b"ftyp", b"mp41\0\0\0\0") + box(b"mdat", b"\0" * 40) + moov)
    mp4 = read_mp4(path)
    with pytest.raises(
        InputError,
        match=r"^X\.mp4: no GPMF track \(expected a 'gpmd' metadata track, found: video, audio\)$",
    ):
        mp4.gpmf_track()


def test_no_video_track_raises(tmp_path: Path) -> None:
    path = tmp_path / "meta.mp4"
    path.write_bytes(box(b"ftyp", b"mp41\0\0\0\0") + box(b"moov", trak(b"meta", b"gpmd")))
    with pytest.raises(InputError, match=r"meta\.mp4: no video track \(found: metadata\)"):
        read_mp4(path).video_track()


def test_unfinalised_recording_raises_missing_moov_with_salvage_info(tmp_path: Path) -> None:
    ftyp = box(b"ftyp", b"mp41\0\0\0\0")
    # Camera died: mdat size never written (0 = to the end of the file).
    zero = tmp_path / "GX010001.MP4"
    zero.write_bytes(ftyp + struct.pack(">I4s", 0, b"mdat") + b"\x11" * 100)
    with pytest.raises(MissingMoovError, match=r"GX010001\.MP4: no 'moov' index") as caught:
        read_mp4(zero)
    assert (caught.value.mdat_offset, caught.value.mdat_size) == (len(ftyp) + 8, 100)
    # Or a placeholder size larger than what was written.
    big = tmp_path / "GX020001.MP4"
    big.write_bytes(ftyp + struct.pack(">I4s", 10_000, b"mdat") + b"\x11" * 100)
    with pytest.raises(MissingMoovError, match="declares 10000 bytes") as caught:
        read_mp4(big)
    assert (caught.value.mdat_offset, caught.value.mdat_size) == (len(ftyp) + 8, 100)
    assert isinstance(caught.value, InputError)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty file"),
        (b"\x00\x00\x00\x10abcdefghijkl", r"not an MP4 file \(expected an 'ftyp' box at byte 0"),
        (box(b"ftyp", b"mp41") + b"\0\0\0", "truncated box header at byte 12"),
        (box(b"ftyp", b"mp41") + struct.pack(">I4s", 4, b"free"), "invalid size 4"),
        (box(b"ftyp", b"mp41") + struct.pack(">I4s", 500, b"moov"), "'moov' at byte 12 declares"),
        (box(b"ftyp", b"mp41") + struct.pack(">I4s", 1, b"free"), "truncated 64-bit box size"),
        (box(b"ftyp", b"mp41") + box(b"moov", full(b"mvhd")), "'mvhd' at byte 20 is too short"),
    ],
)
def test_broken_files_raise_input_error(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "broken.mp4"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message):
        read_mp4(path)


def test_missing_file_and_samples_past_the_end(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"absent\.mp4: cannot open"):
        read_mp4(tmp_path / "absent.mp4")
    path = tmp_path / "cut.mp4"
    co = full(b"stco", struct.pack(">II", 1, 10_000))
    path.write_bytes(box(b"ftyp", b"mp41") + box(b"moov", trak(b"meta", b"gpmd", offsets_box=co)))
    with pytest.raises(InputError, match="samples beyond the end of the file"):
        read_mp4(path)


def test_inner_box_overrun_and_short_tables_raise(tmp_path: Path) -> None:
    path = tmp_path / "inner.mp4"
    bad_trak = struct.pack(">I4s", 400, b"trak") + b"\0" * 8
    path.write_bytes(box(b"ftyp", b"mp41") + box(b"moov", bad_trak))
    with pytest.raises(InputError, match=r"inner\.mp4: box 'trak' at byte 20 declares 400"):
        read_mp4(path)
    path2 = tmp_path / "short.mp4"
    short_stsz = full(b"stsz", struct.pack(">II", 0, 1000))  # 1000 entries announced, none given
    stbl = box(b"stbl", short_stsz)
    moov = box(
        b"moov",
        box(
            b"trak",
            box(
                b"mdia",
                full(b"mdhd", b"\0" * 8, struct.pack(">II", 1000, 0), b"\0" * 4),
                box(b"minf", stbl),
            ),
        ),
    )
    path2.write_bytes(box(b"ftyp", b"mp41") + moov)
    with pytest.raises(InputError, match="'stsz' box is 12 bytes, its entry count needs 4012"):
        read_mp4(path2)
    path3 = tmp_path / "nomdhd.mp4"
    path3.write_bytes(box(b"ftyp", b"mp41") + box(b"moov", box(b"trak", box(b"mdia"))))
    with pytest.raises(InputError, match="has no 'mdhd'"):
        read_mp4(path3)


def test_video_packets_for_an_importer_decode_as_annexb(shared_data: Path) -> None:
    """What an importer does: packets with pts, avcC -> SPS/PPS, AVCC -> Annex B, decode."""
    import av

    mp4 = read_mp4(shared_data / "gopro" / "karma.mp4")
    video = mp4.video_track()
    config = parse_codec_config(video.codec, video.codec_config, source=mp4.name)
    assert config.nal_length_size == 4
    assert [unit[0] & 0x1F for unit in config.parameter_sets] == [7, 8]
    decoder = av.CodecContext.create("h264", "r")
    frames = []
    for packet in mp4.iter_packets(video):
        if packet.index == 8:  # the first GOP (keyframes at 0 and 8)
            break
        assert packet.pts_ns == (packet.index * 3003 * 10**9) // 90000
        annexb = avcc_to_annexb(packet.data, nal_length_size=config.nal_length_size)
        if packet.is_keyframe:
            annexb = config.annexb_header() + annexb
        frames += decoder.decode(av.Packet(annexb))
    frames += decoder.decode(None)
    # The raw decoder shows the coded width (854 rounded up to 16-pixel macroblocks: 864);
    # only the container's 854 tells the demuxer to crop.
    assert len(frames) == 8 and (frames[0].width, frames[0].height) == (864, 480)


def test_codec_config_and_annexb_errors() -> None:
    with pytest.raises(InputError, match="truncated avc1 decoder configuration"):
        parse_codec_config("avc1", b"\x01\x64\x00\x28\xff\xe1\x00\x20abc", source="t.mp4")
    with pytest.raises(InputError, match="unsupported video codec 'mp4v'"):
        parse_codec_config("mp4v", b"")
    # A minimal hvcC: 22 header bytes (length size 4), one array of one 2-byte VPS.
    hvcc = bytes(21) + b"\x03" + b"\x01" + b"\x20\x00\x01" + b"\x00\x02" + b"\x40\x01"
    config = parse_codec_config("hvc1", hvcc)
    assert config.parameter_sets == (b"\x40\x01",) and config.nal_length_size == 4
    assert avcc_to_annexb(b"\0\0\0\2ab\0\0\0\1c") == b"\0\0\0\1ab\0\0\0\1c"
    with pytest.raises(InputError, match="runs past the packet end"):
        avcc_to_annexb(b"\0\0\0\x09ab")
    with pytest.raises(InputError, match="truncated NAL length at byte 0"):
        avcc_to_annexb(b"\0\0")
