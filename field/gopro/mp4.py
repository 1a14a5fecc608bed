"""Reading the MP4 boxes GoPro files need, without loading the media data.

`read_mp4(path)` walks the top-level boxes by seeking (the mdat of a 4 GB
chapter is never read), loads only `moov` (a few hundred kB), and returns an
`MP4File` with one `Track` per 'trak': handler, codec, timescale and the
sample table expanded to numpy arrays (file offset, size, decode time,
composition time, keyframe flag). Readers then fetch just the bytes they need
with `MP4File.read_sample` / `iter_samples`.

Boxes understood: ftyp, mdat, moov/mvhd, udta (FIRM, CAME, LENS, GPMF, ...),
trak/tkhd, edts/elst, mdia/mdhd, hdlr, minf/stbl with stsd (avc1/hvc1 with
avcC/hvcC, gpmd, mp4a, tmcd), stts, ctts, stsc, stsz/stz2, stco/co64, stss.
Sizes use the 64-bit 'largesize' form when the 32-bit size is 1.

A file whose recording was cut (battery died) has an mdat but no moov: we
raise `MissingMoovError`, whose `mdat_offset` / `mdat_size` give the media
data range so a salvage tool can scan it (GoPro's SOS track or a reference
file would be needed to rebuild the index; that is not done here).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import BinaryIO

import numpy as np

from shared.clock import NS_PER_S
from shared.errors import InputError

# Seconds between the MP4 epoch (1904-01-01) and the UNIX epoch (1970-01-01).
MP4_EPOCH = datetime(1904, 1, 1, tzinfo=UTC)
CONTAINER_BOXES = frozenset({"moov", "trak", "mdia", "minf", "stbl", "edts", "dinf", "udta"})
HANDLER_NAMES = {"vide": "video", "soun": "audio", "tmcd": "timecode", "meta": "metadata"}
MAX_MOOV_BYTES = 512 * 1024 * 1024  # a sane bound before reading moov into memory


class MissingMoovError(InputError):
    """The MP4 has no 'moov' index (recording not finalised); mdat range kept for salvage."""

    def __init__(self, message: str, *, mdat_offset: int | None, mdat_size: int | None) -> None:
        super().__init__(message)
        self.mdat_offset = mdat_offset
        self.mdat_size = mdat_size


@dataclass(frozen=True, slots=True)
class Box:
    """One box: its four-character type, file offset of its header, total size, header size."""

    type: str
    offset: int
    size: int
    header_size: int

    @property
    def payload_offset(self) -> int:
        return self.offset + self.header_size

    @property
    def payload_size(self) -> int:
        return self.size - self.header_size

    @property
    def end(self) -> int:
        return self.offset + self.size


def iter_boxes(file: BinaryIO, start: int, end: int, *, source: str) -> Iterator[Box]:
    """Yield the boxes between file offsets `start` and `end` (seeking, not reading payloads).

    Raises `InputError` when a box header is truncated or a size runs past `end`.
    A size of 0 (box runs to the end of the file) is honoured for the last box.
    """
    pos = start
    while pos < end:
        if end - pos < 8:
            raise InputError(f"{source}: truncated box header at byte {pos}")
        file.seek(pos)
        header = file.read(8)
        if len(header) < 8:
            raise InputError(f"{source}: truncated box header at byte {pos}")
        size, raw_type = struct.unpack(">I4s", header)
        box_type = raw_type.decode("latin-1")
        header_size = 8
        if size == 1:
            large = file.read(8)
            if len(large) < 8:
                raise InputError(f"{source}: truncated 64-bit box size at byte {pos}")
            size = struct.unpack(">Q", large)[0]
            header_size = 16
        elif size == 0:
            size = end - pos
        if size < header_size:
            raise InputError(f"{source}: box {box_type!r} at byte {pos} has invalid size {size}")
        if pos + size > end:
            raise InputError(
                f"{source}: box {box_type!r} at byte {pos} declares {size} bytes, "
                f"running past the end of its parent at byte {end}"
            )
        yield Box(box_type, pos, size, header_size)
        pos += size


def _boxes_in(data: bytes, start: int, end: int, *, source: str, base: int) -> Iterator[Box]:
    """Like `iter_boxes` over an in-memory buffer; offsets reported as file offsets (+`base`)."""
    pos = start
    while pos < end:
        if end - pos < 8:
            raise InputError(f"{source}: truncated box header at byte {base + pos}")
        size, raw_type = struct.unpack_from(">I4s", data, pos)
        header_size = 8
        if size == 1:
            if end - pos < 16:
                raise InputError(f"{source}: truncated 64-bit box size at byte {base + pos}")
            size = struct.unpack_from(">Q", data, pos + 8)[0]
            header_size = 16
        elif size == 0:
            size = end - pos
        box_type = raw_type.decode("latin-1")
        if size < header_size or pos + size > end:
            raise InputError(
                f"{source}: box {box_type!r} at byte {base + pos} declares {size} bytes, "
                f"running past the end of its parent at byte {base + end}"
            )
        yield Box(box_type, pos, size, header_size)
        pos += size


@dataclass(slots=True)
class Track:
    """One 'trak' with its sample table expanded (times in `timescale` units).

    `sample_offsets` are absolute file offsets (uint64), `sample_sizes` bytes,
    `decode_times` and `durations` in media time units (int64),
    `composition_times` = decode time + ctts offset, `keyframes` a bool mask
    (all True when the track has no stss).
    """

    track_id: int
    handler: str
    handler_name: str
    codec: str
    timescale: int
    duration: int
    width: int = 0
    height: int = 0
    codec_config: bytes = b""
    sample_offsets: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    sample_sizes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    decode_times: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    durations: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    composition_times: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    edit_media_time: int = 0

    @property
    def kind(self) -> str:
        """'video', 'audio', 'timecode', 'metadata' or the raw handler type."""
        return HANDLER_NAMES.get(self.handler, self.handler)

    @property
    def sample_count(self) -> int:
        return int(self.sample_sizes.shape[0])

    @property
    def duration_s(self) -> float:
        return self.duration / self.timescale if self.timescale else 0.0

    def sample_times_s(self) -> np.ndarray:
        """Decode time of each sample in seconds from the start of the track's media."""
        times: np.ndarray = self.decode_times / float(self.timescale)
        return times

    def pts_ns(self) -> np.ndarray:
        """Presentation time of each sample, int64 ns on the movie timeline (composition
        time minus the edit list's media start; GoPro's edit lists start at 0)."""
        ticks = self.composition_times - self.edit_media_time
        pts: np.ndarray = (ticks * NS_PER_S) // self.timescale
        return pts


@dataclass(frozen=True, slots=True)
class Packet:
    """One sample read from a track: its index, file offset, presentation time (int64 ns
    from the start of the movie), keyframe flag and bytes."""

    index: int
    offset: int
    pts_ns: int
    is_keyframe: bool
    data: bytes


@dataclass(frozen=True, slots=True)
class CodecConfig:
    """Parameter sets from avcC/hvcC: `parameter_sets` in the order an Annex B stream
    needs them (H.265: VPS, SPS, PPS; H.264: SPS, PPS) and the NAL length size in bytes."""

    codec: str
    parameter_sets: tuple[bytes, ...]
    nal_length_size: int

    def annexb_header(self) -> bytes:
        """The parameter sets with start codes, to put before a keyframe."""
        return b"".join(b"\x00\x00\x00\x01" + unit for unit in self.parameter_sets)


def parse_codec_config(codec: str, config: bytes, *, source: str = "<track>") -> CodecConfig:
    """Parse an avcC (codec 'avc1') or hvcC ('hvc1'/'hev1') record; InputError if malformed."""
    units: list[bytes] = []
    try:
        if codec in ("avc1", "avc3"):
            length_size = (config[4] & 0x03) + 1
            pos = 5
            for mask in (0x1F, 0xFF):  # SPS count is 5 bits, PPS count a byte
                count = config[pos] & mask
                pos += 1
                for _ in range(count):
                    (size,) = struct.unpack_from(">H", config, pos)
                    units.append(_slice(config, pos + 2, size))
                    pos += 2 + size
        elif codec in ("hvc1", "hev1"):
            length_size = (config[21] & 0x03) + 1
            arrays = config[22]
            pos = 23
            for _ in range(arrays):
                (count,) = struct.unpack_from(">H", config, pos + 1)
                pos += 3
                for _ in range(count):
                    (size,) = struct.unpack_from(">H", config, pos)
                    units.append(_slice(config, pos + 2, size))
                    pos += 2 + size
        else:
            raise InputError(f"{source}: unsupported video codec {codec!r} (expected avc1 or hvc1)")
    except (IndexError, struct.error) as error:
        raise InputError(f"{source}: truncated {codec} decoder configuration") from error
    return CodecConfig(codec=codec, parameter_sets=tuple(units), nal_length_size=length_size)


def _slice(data: bytes, start: int, size: int) -> bytes:
    if start + size > len(data):
        raise IndexError(start + size)
    return data[start : start + size]


def avcc_to_annexb(data: bytes, *, nal_length_size: int = 4, source: str = "<packet>") -> bytes:
    """Length-prefixed NAL units (MP4) -> Annex B with 4-byte start codes (what
    foxglove CompressedVideo and most decoders' raw input expect)."""
    out = bytearray()
    pos = 0
    while pos < len(data):
        if pos + nal_length_size > len(data):
            raise InputError(f"{source}: truncated NAL length at byte {pos}")
        size = int.from_bytes(data[pos : pos + nal_length_size], "big")
        pos += nal_length_size
        if pos + size > len(data):
            raise InputError(
                f"{source}: NAL unit of {size} bytes at byte {pos} runs past the packet end"
            )
        out += b"\x00\x00\x00\x01" + data[pos : pos + size]
        pos += size
    return bytes(out)


@dataclass(slots=True)
class MP4File:
    """What `read_mp4` found: brand, creation time, duration, tracks, udta atoms."""

    path: Path
    major_brand: str
    creation_time: datetime | None
    timescale: int
    duration: int
    tracks: list[Track]
    user_data: dict[str, bytes]
    mdat_ranges: list[tuple[int, int]]

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def duration_s(self) -> float:
        return self.duration / self.timescale if self.timescale else 0.0

    def video_track(self) -> Track:
        """The first video track ('vide' handler); InputError when there is none."""
        for track in self.tracks:
            if track.handler == "vide":
                return track
        raise InputError(f"{self.name}: no video track (found: {self._kinds()})")

    def gpmf_track(self) -> Track:
        """The GPMF telemetry track (handler 'meta', sample description 'gpmd')."""
        for track in self.tracks:
            if track.codec == "gpmd":
                return track
        raise InputError(
            f"{self.name}: no GPMF track (expected a 'gpmd' metadata track, found: {self._kinds()})"
        )

    def _kinds(self) -> str:
        kinds = [t.kind if t.codec != "fdsc" else "metadata (fdsc)" for t in self.tracks]
        return ", ".join(kinds) if kinds else "no tracks"

    def text_atom(self, key: str) -> str | None:
        """A udta text atom such as FIRM (firmware), stripped of NULs; None when absent."""
        raw = self.user_data.get(key)
        if raw is None:
            return None
        return raw.split(b"\x00", 1)[0].decode("latin-1").strip()

    def read_sample(self, track: Track, index: int) -> bytes:
        """Bytes of one sample (reads only that range of the file)."""
        offset = int(track.sample_offsets[index])
        size = int(track.sample_sizes[index])
        with self.path.open("rb") as file:
            file.seek(offset)
            data = file.read(size)
        if len(data) != size:
            raise InputError(
                f"{self.name}: sample {index} of track {track.track_id} at byte {offset} "
                f"needs {size} bytes, file ends after {len(data)}"
            )
        return data

    def iter_packets(self, track: Track) -> Iterator[Packet]:
        """Every sample of `track` as a `Packet` (bytes, file offset, pts in ns, keyframe),
        in decode order, reading only those bytes. For video the bytes are AVCC
        (length-prefixed NAL units); `avcc_to_annexb` converts them."""
        pts = track.pts_ns()
        for index, (offset, data) in enumerate(self.iter_samples(track)):
            yield Packet(
                index=index,
                offset=offset,
                pts_ns=int(pts[index]),
                is_keyframe=bool(track.keyframes[index]),
                data=data,
            )

    def iter_samples(self, track: Track) -> Iterator[tuple[int, bytes]]:
        """(file offset, bytes) of each sample of `track`, in decode order, one open file."""
        with self.path.open("rb") as file:
            for index in range(track.sample_count):
                offset = int(track.sample_offsets[index])
                size = int(track.sample_sizes[index])
                file.seek(offset)
                data = file.read(size)
                if len(data) != size:
                    raise InputError(
                        f"{self.name}: sample {index} of track {track.track_id} at byte "
                        f"{offset} needs {size} bytes, file ends after {len(data)}"
                    )
                yield offset, data


def read_mp4(path: Path | str) -> MP4File:
    """Index an MP4/MOV file: top-level walk by seeking, then parse only 'moov'.

    Raises `InputError` for a file that is not an MP4 or has a corrupt box
    structure, and `MissingMoovError` (an InputError) when there is no moov.
    """
    path = Path(path)
    source = path.name
    try:
        file_size = path.stat().st_size
        file = path.open("rb")
    except OSError as error:
        raise InputError(f"{source}: cannot open ({error.strerror})") from error
    with file:
        major_brand = ""
        moov: Box | None = None
        mdat_ranges: list[tuple[int, int]] = []
        first = True
        for box in _top_level_boxes(file, file_size, source=source):
            if first and box.type not in ("ftyp", "mdat", "moov", "free", "skip", "wide"):
                raise InputError(
                    f"{source}: not an MP4 file (expected an 'ftyp' box at byte 0, "
                    f"found {box.type!r})"
                )
            first = False
            if box.type == "ftyp":
                file.seek(box.payload_offset)
                major_brand = file.read(4).decode("latin-1")
            elif box.type == "moov":
                moov = box
            elif box.type == "mdat":
                mdat_ranges.append((box.payload_offset, box.payload_size))
        if first:
            raise InputError(f"{source}: empty file (expected an MP4)")
        if moov is None:
            mdat = mdat_ranges[0] if mdat_ranges else (None, None)
            raise MissingMoovError(
                f"{source}: no 'moov' index (expected one after the media data; the "
                "recording was probably not finalised)",
                mdat_offset=mdat[0],
                mdat_size=mdat[1],
            )
        if moov.payload_size > MAX_MOOV_BYTES:
            raise InputError(f"{source}: 'moov' of {moov.payload_size} bytes is implausibly large")
        file.seek(moov.payload_offset)
        moov_data = file.read(moov.payload_size)
    return _parse_moov(
        moov_data, path=path, base=moov.payload_offset, major_brand=major_brand,
        mdat_ranges=mdat_ranges, file_size=file_size,
    )  # fmt: skip


def _top_level_boxes(file: BinaryIO, file_size: int, *, source: str) -> Iterator[Box]:
    """Top-level boxes; an 'mdat' running past the end (cut recording) is clamped to the file."""
    pos = 0
    while pos < file_size:
        file.seek(pos)
        header = file.read(16)
        if len(header) < 8:
            raise InputError(f"{source}: truncated box header at byte {pos}")
        size, raw_type = struct.unpack_from(">I4s", header)
        box_type = raw_type.decode("latin-1")
        header_size = 8
        if size == 1:
            if len(header) < 16:
                raise InputError(f"{source}: truncated 64-bit box size at byte {pos}")
            size = struct.unpack_from(">Q", header, 8)[0]
            header_size = 16
        elif size == 0:
            size = file_size - pos
        if size < header_size:
            raise InputError(f"{source}: box {box_type!r} at byte {pos} has invalid size {size}")
        if pos + size > file_size:
            if box_type == "mdat":
                # The camera writes mdat's final size only when it finalises the file.
                raise MissingMoovError(
                    f"{source}: 'mdat' at byte {pos} declares {size} bytes but the file has "
                    f"{file_size}, and there is no 'moov' index (recording not finalised?)",
                    mdat_offset=pos + header_size,
                    mdat_size=file_size - pos - header_size,
                )
            raise InputError(
                f"{source}: box {box_type!r} at byte {pos} declares {size} bytes, running "
                f"past the end of the file ({file_size} bytes; truncated copy?)"
            )
        yield Box(box_type, pos, size, header_size)
        pos += size


def _u32(data: bytes, pos: int) -> int:
    return int(struct.unpack_from(">I", data, pos)[0])


def _parse_moov(
    data: bytes,
    *,
    path: Path,
    base: int,
    major_brand: str,
    mdat_ranges: list[tuple[int, int]],
    file_size: int,
) -> MP4File:
    source = path.name
    creation_time: datetime | None = None
    timescale = 0
    duration = 0
    tracks: list[Track] = []
    user_data: dict[str, bytes] = {}
    for box in _boxes_in(data, 0, len(data), source=source, base=base):
        body = data[box.payload_offset : box.end]
        try:
            if box.type == "mvhd":
                version = body[0]
                if version == 1:
                    created, _, timescale, duration = struct.unpack_from(">QQIQ", body, 4)
                else:
                    created, _, timescale, duration = struct.unpack_from(">IIII", body, 4)
                creation_time = _mp4_time(created)
            elif box.type == "udta":
                for child in _boxes_in(
                    body, 0, len(body), source=source, base=base + box.payload_offset
                ):
                    user_data.setdefault(child.type, body[child.payload_offset : child.end])
            elif box.type == "trak":
                tracks.append(
                    _parse_trak(
                        body, source=source, base=base + box.payload_offset, file_size=file_size
                    )
                )
        except (struct.error, IndexError) as error:
            raise InputError(
                f"{source}: box {box.type!r} at byte {base + box.offset} is too short ({error})"
            ) from error
    for track in tracks:
        if track.sample_count:
            last_end = int(np.max(track.sample_offsets.astype(np.int64) + track.sample_sizes))
            if last_end > file_size:
                raise InputError(
                    f"{source}: track {track.track_id} ({track.kind}) has samples beyond the "
                    f"end of the file (byte {last_end} > {file_size}; truncated copy?)"
                )
    return MP4File(
        path=path,
        major_brand=major_brand,
        creation_time=creation_time,
        timescale=timescale,
        duration=duration,
        tracks=tracks,
        user_data=user_data,
        mdat_ranges=mdat_ranges,
    )


def _mp4_time(seconds: int) -> datetime | None:
    """mvhd creation time (seconds since 1904) as UTC; None when 0 or beyond year 9999."""
    try:
        return MP4_EPOCH + timedelta(seconds=seconds) if seconds else None
    except OverflowError:  # a corrupt header: keep the file readable, drop the date
        return None


def _children(data: bytes, *, source: str, base: int) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    for box in _boxes_in(data, 0, len(data), source=source, base=base):
        out.setdefault(box.type, data[box.payload_offset : box.end])
    return out


def _parse_trak(data: bytes, *, source: str, base: int, file_size: int) -> Track:
    trak = _children(data, source=source, base=base)
    tkhd = trak.get("tkhd", b"")
    track_id = 0
    if tkhd:
        track_id = _u32(tkhd, 20 if tkhd[0] == 1 else 12)
    edit_media_time = 0
    if "edts" in trak:
        edts = _children(trak["edts"], source=source, base=base)
        elst = edts.get("elst", b"")
        if len(elst) >= 8 and _u32(elst, 4) >= 1:
            if elst[0] == 1:
                edit_media_time = int(struct.unpack_from(">q", elst, 16)[0])
            else:
                edit_media_time = int(struct.unpack_from(">i", elst, 12)[0])
    mdia = _children(trak.get("mdia", b""), source=source, base=base)
    mdhd = mdia.get("mdhd", b"")
    if not mdhd:
        raise InputError(f"{source}: track {track_id} has no 'mdhd' (media header)")
    if mdhd[0] == 1:
        timescale, duration = struct.unpack_from(">IQ", mdhd, 20)
    else:
        timescale, duration = struct.unpack_from(">II", mdhd, 12)
    if timescale == 0:
        raise InputError(f"{source}: track {track_id} has a media timescale of 0 ('mdhd')")
    hdlr = mdia.get("hdlr", b"")
    handler = hdlr[8:12].decode("latin-1") if len(hdlr) >= 12 else ""
    handler_name = _handler_name(hdlr[24:])
    minf = _children(mdia.get("minf", b""), source=source, base=base)
    stbl = _children(minf.get("stbl", b""), source=source, base=base)
    track = Track(
        track_id=track_id,
        handler=handler,
        handler_name=handler_name,
        codec="",
        timescale=int(timescale),
        duration=int(duration),
        edit_media_time=edit_media_time,
    )
    _parse_stsd(stbl.get("stsd", b""), track, source=source, base=base)
    _parse_sample_table(stbl, track, source=source, file_size=file_size)
    return track


def _handler_name(raw: bytes) -> str:
    # QuickTime writes a Pascal string (length byte first), ISO a NUL-terminated one.
    if raw and raw[0] < 32 and raw[0] <= len(raw) - 1:
        raw = raw[1 : 1 + raw[0]]
    return raw.split(b"\x00", 1)[0].decode("latin-1").strip()


def _parse_stsd(stsd: bytes, track: Track, *, source: str, base: int) -> None:
    if len(stsd) < 16:
        return
    entry_size = _u32(stsd, 8)
    track.codec = stsd[12:16].decode("latin-1")
    entry = stsd[8 : 8 + entry_size]
    if track.handler == "vide" and len(entry) >= 86:
        track.width, track.height = struct.unpack_from(">HH", entry, 32)
        # 8-byte header + 78 bytes of VisualSampleEntry, then child boxes (avcC/hvcC...).
        for box in _boxes_in(entry, 86, len(entry), source=source, base=base):
            if box.type in ("avcC", "hvcC"):
                track.codec_config = entry[box.payload_offset : box.end]


def _repeat_limited(values: np.ndarray, counts: np.ndarray, limit: int) -> np.ndarray:
    """`np.repeat(values, counts)[:limit]` without building more than `limit` items
    (run-length tables of a corrupt file may declare billions of samples)."""
    counts = np.maximum(counts.astype(np.int64), 0)  # ctts v1 reads counts as signed
    totals = np.cumsum(counts)
    if totals.size and int(totals[-1]) > limit:
        last = int(np.searchsorted(totals, limit))
        counts = counts[: last + 1].copy()
        counts[last] -= int(totals[last]) - limit
        values = values[: last + 1]
    repeated: np.ndarray = np.repeat(values, counts)
    return repeated


def _parse_sample_table(
    stbl: dict[str, bytes], track: Track, *, source: str, file_size: int
) -> None:
    where = f"{source}: track {track.track_id}"
    # Sample sizes.
    if "stsz" in stbl:
        stsz = stbl["stsz"]
        fixed, count = struct.unpack_from(">II", stsz, 4)
        if fixed:
            # Checked before allocating: every sample is `fixed` bytes of this file.
            if count * fixed > file_size:
                raise InputError(
                    f"{where}: 'stsz' declares {count} samples of {fixed} bytes, more than "
                    f"the file's {file_size} bytes"
                )
            sizes = np.full(count, fixed, dtype=np.uint32)
        else:
            _need(stsz, 12 + 4 * count, where, "stsz")
            sizes = np.frombuffer(stsz, ">u4", count, 12).astype(np.uint32)
    elif "stz2" in stbl:
        stz2 = stbl["stz2"]
        field_size = stz2[7]
        count = _u32(stz2, 8)
        if field_size == 16:
            _need(stz2, 12 + 2 * count, where, "stz2")
            sizes = np.frombuffer(stz2, ">u2", count, 12).astype(np.uint32)
        elif field_size == 8:
            _need(stz2, 12 + count, where, "stz2")
            sizes = np.frombuffer(stz2, "u1", count, 12).astype(np.uint32)
        else:
            raise InputError(f"{where}: unsupported stz2 field size {field_size}")
    else:
        return
    n = int(sizes.shape[0])
    # Chunk offsets.
    if "co64" in stbl:
        co = stbl["co64"]
        chunks = _u32(co, 4)
        _need(co, 8 + 8 * chunks, where, "co64")
        chunk_offsets = np.frombuffer(co, ">u8", chunks, 8).astype(np.uint64)
    elif "stco" in stbl:
        co = stbl["stco"]
        chunks = _u32(co, 4)
        _need(co, 8 + 4 * chunks, where, "stco")
        chunk_offsets = np.frombuffer(co, ">u4", chunks, 8).astype(np.uint64)
    else:
        raise InputError(f"{where}: sample table without stco/co64")
    # Sample-to-chunk runs: (first_chunk (1-based), samples_per_chunk, description index).
    stsc = stbl.get("stsc", b"")
    runs = _u32(stsc, 4) if stsc else 0
    _need(stsc, 8 + 12 * runs, where, "stsc")
    table = np.frombuffer(stsc, ">u4", 3 * runs, 8).reshape(runs, 3).astype(np.int64)
    samples_per_chunk = np.zeros(len(chunk_offsets), dtype=np.int64)
    for i in range(runs):
        first = int(table[i, 0]) - 1
        last = int(table[i + 1, 0]) - 1 if i + 1 < runs else len(chunk_offsets)
        samples_per_chunk[first:last] = table[i, 1]
    if int(samples_per_chunk.sum()) < n:
        raise InputError(
            f"{where}: stsc/stco describe {int(samples_per_chunk.sum())} samples, stsz {n}"
        )
    chunk_of_sample = _repeat_limited(np.arange(len(chunk_offsets)), samples_per_chunk, n)
    first_in_chunk = np.concatenate([[0], np.cumsum(samples_per_chunk)[:-1]])
    size_cumsum = np.concatenate([[0], np.cumsum(sizes.astype(np.uint64))])
    within = size_cumsum[:n] - size_cumsum[first_in_chunk[chunk_of_sample]]
    track.sample_offsets = chunk_offsets[chunk_of_sample] + within.astype(np.uint64)
    track.sample_sizes = sizes
    # Decode times from stts runs (count, delta).
    stts = stbl.get("stts", b"")
    entries = _u32(stts, 4) if stts else 0
    _need(stts, 8 + 8 * entries, where, "stts")
    pairs = np.frombuffer(stts, ">u4", 2 * entries, 8).reshape(entries, 2).astype(np.int64)
    durations = _repeat_limited(pairs[:, 1], pairs[:, 0], n)
    if durations.shape[0] < n:
        raise InputError(f"{where}: stts covers {durations.shape[0]} samples, stsz {n}")
    track.durations = durations[:n]
    track.decode_times = np.concatenate([[0], np.cumsum(track.durations)[:-1]]).astype(np.int64)
    track.composition_times = track.decode_times.copy()
    if "ctts" in stbl:
        ctts = stbl["ctts"]
        entries = _u32(ctts, 4)
        _need(ctts, 8 + 8 * entries, where, "ctts")
        dtype = ">i4" if ctts[0] == 1 else ">u4"
        raw = np.frombuffer(ctts, dtype, 2 * entries, 8).reshape(entries, 2).astype(np.int64)
        offsets = _repeat_limited(raw[:, 1], raw[:, 0], n)
        track.composition_times[: offsets.shape[0]] += offsets
    if "stss" in stbl:
        stss = stbl["stss"]
        entries = _u32(stss, 4)
        _need(stss, 8 + 4 * entries, where, "stss")
        sync = np.frombuffer(stss, ">u4", entries, 8).astype(np.int64) - 1
        track.keyframes = np.zeros(n, dtype=bool)
        track.keyframes[sync[(sync >= 0) & (sync < n)]] = True
    else:
        track.keyframes = np.ones(n, dtype=bool)


def _need(data: bytes, size: int, where: str, box: str) -> None:
    if len(data) < size:
        raise InputError(f"{where}: '{box}' box is {len(data)} bytes, its entry count needs {size}")
