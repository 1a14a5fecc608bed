"""ArchiveReader: read an archive MCAP back as dataclasses or bulk numpy arrays.

A complete archive is read through its summary: chunk indexes select the
chunks that overlap the asked time range and topics, so nothing else is
read. A file without a summary (written by a tool that writes none) is read
by walking its records. A truncated file (a crashed writer's `.part`) is
refused unless opened with `salvage=True`: then the records are walked, a
damaged chunk or a cut tail is skipped, and `warnings` / `skipped_bytes`
say what was lost. `iter_records_salvage` gives the raw CDR records in file
order for tools that rebuild a damaged recording.

What the mcap package does here and what stays ours (measured with mcap 1.6.0,
tests/shared/test_archive_engines.py and bench/bench_archive.py):

- The summary section (schemas, channels, statistics, chunk and metadata
  indexes) and Metadata records are parsed by mcap's `StreamReader`.
- Salvage stays ours: on a file without footer and summary, mcap's
  `make_reader` reads garbage as the footer and raises, its `NonSeekingReader`
  returns nothing in log-time order (it sorts at the end, and the cut raises
  first) and, in file order, stops for good at the cut or at the first damaged
  chunk; this reader returns every complete chunk and goes past damaged ones.
- Loading chunks and messages stays ours: mcap's `iter_messages` builds a
  record object per message and a heap entry in log-time order; with our
  batch CDR decode it reads IMU about 4x slower than `read_imu` here. Ours
  also pulls zstd output in pieces, never past the chunk's declared size (the
  zstd-bomb fuzz case), and always checks chunk CRCs.
- Topic counts and spans come from the message indexes, read with numpy
  (mcap's reader has no public access to them).
"""

from __future__ import annotations

import heapq
import io
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, NamedTuple

import numpy as np
from mcap.exceptions import McapError
from numpy.typing import NDArray

from shared.archive import mcap_records as rec
from shared.archive.cdr import DECODERS, decode_imu_batch
from shared.archive.messages import ArchiveMessage, Imu
from shared.errors import InputError

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHANNEL_FIXED = struct.Struct("<HH")
_MESSAGE_FIELDS = rec.MESSAGE_FIELDS
_RECORD_HEAD = rec.RECORD_HEAD

Decoder = Callable[[bytes | memoryview, str], ArchiveMessage]


@dataclass(frozen=True)
class TopicInfo:
    """One topic of an archive: its ROS type, message count and log-time span (ns since epoch)."""

    topic: str
    schema_name: str
    message_count: int
    first_log_time_ns: int
    last_log_time_ns: int


@dataclass
class ImuSeries:
    """All samples of one IMU topic, in log-time order.

    `stamps_ns` is the sensor clock (header.stamp), `log_times_ns` the host
    receive time, both int64 ns since epoch, shape (N,); `gyro_rad_s` and
    `accel_m_s2` are (N, 3) float64 in the IMU frame.
    """

    topic: str
    stamps_ns: NDArray[np.int64]
    log_times_ns: NDArray[np.int64]
    gyro_rad_s: NDArray[np.float64]
    accel_m_s2: NDArray[np.float64]


class RawRecord(NamedTuple):
    """One undecoded message: topic, log time (ns since epoch), ROS type name, CDR bytes."""

    topic: str
    log_time_ns: int
    schema_name: str
    data: bytes


@dataclass
class _Schema:
    schema_id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class _Channel:
    channel_id: int
    schema_id: int
    topic: str
    message_encoding: str


@dataclass
class _Segment:
    """A run of records to load: a Chunk record, or a run of top-level (unchunked) records."""

    start_time: int
    end_time: int
    offset: int
    length: int
    channel_ids: frozenset[int] | None = None  # from the message indexes; None = unknown
    message_index_offset: int = 0
    message_index_length: int = 0
    is_chunk: bool = True


class _Fields:
    """Sequential little-endian field reader over a bytes-like body."""

    __slots__ = ("data", "pos")

    def __init__(self, data: bytes | memoryview, pos: int = 0) -> None:
        self.data = data
        self.pos = pos

    def _take(self, size: int) -> int:
        start = self.pos
        if start + size > len(self.data):
            raise ValueError("record field runs past the end of its record")
        self.pos = start + size
        return start

    def u8(self) -> int:
        return int(self.data[self._take(1)])

    def u16(self) -> int:
        return int(_U16.unpack_from(self.data, self._take(2))[0])

    def u32(self) -> int:
        return int(_U32.unpack_from(self.data, self._take(4))[0])

    def u64(self) -> int:
        return int(_U64.unpack_from(self.data, self._take(8))[0])

    def raw(self, size: int) -> bytes:
        start = self._take(size)
        return bytes(self.data[start : start + size])

    def string(self) -> str:
        return self.raw(self.u32()).decode("utf-8")

    def str_map(self) -> dict[str, str]:
        end = self.u32() + self.pos
        values: dict[str, str] = {}
        while self.pos < end:
            key = self.string()
            values[key] = self.string()
        return values


def _parse_schema(body: bytes | memoryview) -> _Schema:
    fields = _Fields(body)
    schema_id = fields.u16()
    name = fields.string()
    encoding = fields.string()
    return _Schema(schema_id, name, encoding, fields.raw(fields.u32()))


def _parse_channel(body: bytes | memoryview) -> _Channel:
    fields = _Fields(body)
    channel_id = fields.u16()
    schema_id = fields.u16()
    topic = fields.string()
    return _Channel(channel_id, schema_id, topic, fields.string())


_DECOMPRESS_PIECE = 1 << 20


def _decompress(compression: str, data: bytes, uncompressed_size: int) -> bytes:
    """The chunk's records; ValueError when they cannot be had.

    Memory stays bounded by what the data really holds: a zstd frame may declare any
    content size (and the chunk any `uncompressed_size`), so output is pulled in
    pieces and never more than `uncompressed_size` + 1 bytes.
    """
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        out = bytearray()
        try:
            with zstandard.ZstdDecompressor().stream_reader(data) as stream:
                while len(out) <= uncompressed_size:
                    piece = stream.read(min(_DECOMPRESS_PIECE, uncompressed_size + 1 - len(out)))
                    if not piece:
                        break
                    out += piece
        except zstandard.ZstdError as error:
            raise ValueError(f"zstd: {error}") from None
        return bytes(out)
    if compression == "lz4":
        try:
            import lz4.frame  # type: ignore[import-untyped, import-not-found, unused-ignore]
        except ImportError:
            raise ValueError("chunk compressed with lz4, which is not installed") from None
        try:
            return bytes(lz4.frame.decompress(data))
        except RuntimeError as error:
            raise ValueError(f"lz4: {error}") from None
    raise ValueError(f"unknown chunk compression {compression!r}")


class ArchiveReader:
    """Read an archive MCAP written by `ArchiveWriter` (or any ROS 2 MCAP of the same types).

    Args:
        path: the `.mcap` (or `.part`) file.
        salvage: read a truncated or damaged file as far as it goes instead of
            raising InputError; what was skipped is listed in `warnings` and
            counted in `skipped_bytes`.

    Raises InputError (naming the file) for a file that is not MCAP, is
    truncated (without `salvage`), or whose index is damaged.
    """

    def __init__(self, path: Path | str, *, salvage: bool = False) -> None:
        self.path = Path(path)
        self.salvage = salvage
        self.warnings: list[str] = []
        """What a salvage read skipped (one line each)."""
        self.skipped_bytes = 0
        """Bytes of the file that could not be read (damaged chunks, cut tail)."""
        self.indexed = False
        """True when the file's summary (chunk indexes) is used."""
        self._schemas: dict[int, _Schema] = {}
        self._channels: dict[int, _Channel] = {}
        self._segments: list[_Segment] = []
        self._metadata_offsets: list[tuple[int, int]] = []
        self._metadata: dict[str, dict[str, str]] = {}
        self._statistics: tuple[int, int, int] | None = None  # count, start, end
        self._topic_info: dict[str, TopicInfo] | None = None
        self._orphans: dict[int, int] = {}  # undefined channel id -> messages skipped
        try:
            self._file: BinaryIO = self.path.open("rb")
        except OSError as error:
            raise InputError(f"{self.path}: cannot open archive ({error.strerror})") from None
        try:
            self._open()
        except BaseException:
            self._file.close()
            raise

    # -- opening ------------------------------------------------------------

    def _error(self, what: str) -> InputError:
        return InputError(f"{self.path}: {what}")

    def _read_at(self, offset: int, size: int) -> bytes:
        # Checked before reading: a corrupt length must not make read() allocate it.
        if offset < 0 or size < 0 or offset + size > self._size:
            raise ValueError(
                f"{size} bytes at offset {offset} run past the end of the file ({self._size})"
            )
        self._file.seek(offset)
        data = self._file.read(size)
        if len(data) != size:
            raise ValueError(f"file ends at {offset + len(data)}, expected {offset + size} bytes")
        return data

    def _open(self) -> None:
        self._size = self.path.stat().st_size
        self._file.seek(0)
        head = self._file.read(len(rec.MAGIC) + _RECORD_HEAD.size)
        if head[: len(rec.MAGIC)] != rec.MAGIC:
            raise self._error(
                f"not an MCAP file (expected magic {rec.MAGIC.hex(' ')}, "
                f"found {head[:8].hex(' ') or 'an empty file'})"
            )
        if len(head) < len(rec.MAGIC) + _RECORD_HEAD.size or head[8] != rec.OP_HEADER:
            raise self._error(
                f"truncated MCAP file (no Header record after the magic at byte {len(rec.MAGIC)})"
            )
        header_length = _U64.unpack_from(head, 9)[0]
        self._data_start = len(head) + header_length
        try:
            header = _Fields(self._read_at(len(head), header_length))
            self.profile = header.string()
            self.library = header.string()
        except (ValueError, UnicodeDecodeError):
            raise self._error(
                f"truncated MCAP file (Header record cut short at byte {len(head)})"
            ) from None
        footer = self._footer()
        if footer is None:
            if not self.salvage:
                raise self._error(
                    "truncated MCAP file (no footer: the writer did not finish; "
                    f"open it with salvage=True or recover it; file ends at byte {self._size})"
                )
            self.warnings.append(f"{self.path.name}: no footer (unfinished recording)")
            self._scan(self._size)
            return
        summary_start, _ = footer
        footer_offset = self._size - len(rec.MAGIC) - rec.FOOTER_RECORD_SIZE
        if summary_start == 0:
            self._scan(footer_offset)
            return
        try:
            self._read_summary(summary_start, footer_offset)
        except (ValueError, UnicodeDecodeError, KeyError, struct.error, McapError) as error:
            where = f"summary at offset {summary_start}"
            if not self.salvage:
                raise self._error(f"damaged MCAP {where} ({error})") from None
            self.warnings.append(f"{self.path.name}: damaged {where} ({error}); scanning")
            self._schemas.clear()
            self._channels.clear()
            self._segments.clear()
            self._metadata_offsets.clear()
            self._statistics = None
            self._scan(footer_offset)
            return
        if not self._segments:
            # No chunk index (an unchunked file, or chunks left unindexed): walk the records.
            self._statistics = None
            self._scan(summary_start)
            return
        self.indexed = True

    def _footer(self) -> tuple[int, int] | None:
        tail_size = rec.FOOTER_RECORD_SIZE + len(rec.MAGIC)
        if self._size < self._data_start + tail_size:
            return None
        tail = self._read_at(self._size - tail_size, tail_size)
        if tail[-8:] != rec.MAGIC or tail[0] != rec.OP_FOOTER:
            return None
        if _U64.unpack_from(tail, 1)[0] != rec.FOOTER_BODY.size:
            return None
        summary_start, offset_start, _crc = rec.FOOTER_BODY.unpack_from(tail, 9)
        if summary_start > self._size:
            return None
        return int(summary_start), int(offset_start)

    def _read_summary(self, start: int, end: int) -> None:
        """The summary section [start, end) and the footer, parsed by the mcap package."""
        from mcap.records import Channel, ChunkIndex, MetadataIndex, Schema, Statistics
        from mcap.stream_reader import StreamReader

        if not self._data_start <= start <= end:
            raise ValueError(f"summary offset {start} outside the file")
        data = self._read_at(start, self._size - start)  # summary, footer, closing magic
        records = StreamReader(io.BytesIO(data), skip_magic=True, record_size_limit=len(data))
        for record in records.records:
            if isinstance(record, Schema):
                self._schemas[record.id] = _Schema(
                    record.id, record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel):
                self._channels[record.id] = _Channel(
                    record.id, record.schema_id, record.topic, record.message_encoding
                )
            elif isinstance(record, ChunkIndex):
                self._segments.append(self._segment_from_index(record))
            elif isinstance(record, MetadataIndex):
                self._metadata_offsets.append((record.offset, record.length))
            elif isinstance(record, Statistics):
                self._statistics = (
                    record.message_count,
                    record.message_start_time,
                    record.message_end_time,
                )

    def _segment_from_index(self, index: Any) -> _Segment:
        """A chunk to load, from an `mcap.records.ChunkIndex`."""
        offset, length = index.chunk_start_offset, index.chunk_length
        if offset + length > self._size:
            raise ValueError(f"chunk at {offset} runs past the end of the file")
        index_offsets: dict[int, int] = index.message_index_offsets
        return _Segment(
            start_time=index.message_start_time,
            end_time=index.message_end_time,
            offset=offset,
            length=length,
            channel_ids=frozenset(index_offsets) if index_offsets else None,
            message_index_offset=min(index_offsets.values()) if index_offsets else 0,
            message_index_length=index.message_index_length,
        )

    def _skip(self, offset: int, size: int, why: str) -> None:
        self.skipped_bytes += size
        self.warnings.append(f"{self.path.name}: skipped {size} bytes at offset {offset} ({why})")

    def _scan(self, end: int) -> None:
        """Walk the top-level records of the data section (no usable summary)."""
        self._topic_info = None
        pos = self._data_start
        run: _Segment | None = None  # top-level messages, schemas and channels
        while pos < end:
            if pos + 9 > end:
                self._skip(pos, end - pos, "truncated record header")
                break
            opcode, length = _RECORD_HEAD.unpack(self._read_at(pos, 9))
            if pos + 9 + length > end:
                self._skip(pos, end - pos, "truncated record")
                break
            record_end = pos + 9 + length
            if opcode in (rec.OP_MESSAGE, rec.OP_SCHEMA, rec.OP_CHANNEL):
                if run is None:
                    run = _Segment(start_time=-1, end_time=0, offset=pos, length=0, is_chunk=False)
                run.length = record_end - run.offset
                if opcode == rec.OP_MESSAGE and length >= _MESSAGE_FIELDS.size:
                    log_time = _MESSAGE_FIELDS.unpack(self._read_at(pos + 9, 22))[2]
                    if run.start_time < 0 or log_time < run.start_time:
                        run.start_time = log_time
                    run.end_time = max(run.end_time, log_time)
                pos = record_end
                continue
            if run is not None:
                self._segments.append(run)
                run = None
            if opcode == rec.OP_CHUNK and length >= 16:
                start_time, end_time = struct.unpack("<QQ", self._read_at(pos + 9, 16))
                self._segments.append(_Segment(start_time, end_time, pos, record_end - pos))
            elif opcode == rec.OP_METADATA:
                self._metadata_offsets.append((pos, record_end - pos))
            elif opcode in (rec.OP_DATA_END, rec.OP_FOOTER):
                break
            pos = record_end
        if run is not None:
            self._segments.append(run)
        for segment in self._segments:
            segment.start_time = max(segment.start_time, 0)

    # -- loading chunks -----------------------------------------------------

    def _segment_records(self, segment: _Segment) -> bytes:
        """The records of a segment, decompressed and CRC-checked."""
        data = self._read_at(segment.offset, segment.length)
        if not segment.is_chunk:
            return data
        if not data or data[0] != rec.OP_CHUNK:
            raise ValueError(f"no Chunk record at offset {segment.offset}")
        fields = _Fields(data, 9)
        fields.pos += 16
        uncompressed_size = fields.u64()
        crc = fields.u32()
        compression = fields.string()
        size = fields.u64()
        records = _decompress(compression, fields.raw(size), uncompressed_size)
        if len(records) != uncompressed_size:
            raise ValueError(f"chunk holds {len(records)} bytes, index says {uncompressed_size}")
        if crc and zlib.crc32(records) != crc:
            raise ValueError("chunk CRC mismatch")
        return records

    def _segment_messages(
        self,
        segment: _Segment,
        channel_ids: set[int] | None,
        wanted_topics: set[str] | None,
        start_ns: int | None,
        end_ns: int | None,
    ) -> list[tuple[int, int, int, memoryview]]:
        """(log_time, order, channel_id, cdr) of the wanted messages of a segment, sorted.

        Channels met in the segment are registered; when their topic is wanted
        they join `channel_ids` (a file read without its summary learns its
        channels chunk by chunk).
        """
        try:
            records = memoryview(self._segment_records(segment))
            found: list[tuple[int, int, int, memoryview]] = []
            pos = 0
            size = len(records)
            unpack_head = _RECORD_HEAD.unpack_from
            unpack_message = _MESSAGE_FIELDS.unpack_from
            while pos < size:
                opcode, length = unpack_head(records, pos)
                body_start = pos + 9
                pos = body_start + length
                if pos > size:
                    raise ValueError("record runs past the end of its chunk")
                if opcode == rec.OP_MESSAGE:
                    channel_id, _seq, log_time, _pub = unpack_message(records, body_start)
                    if channel_ids is not None and channel_id not in channel_ids:
                        continue
                    if start_ns is not None and log_time < start_ns:
                        continue
                    if end_ns is not None and log_time >= end_ns:
                        continue
                    found.append((log_time, len(found), channel_id, records[body_start + 22 : pos]))
                elif opcode == rec.OP_SCHEMA:
                    schema = _parse_schema(records[body_start:pos])
                    self._schemas.setdefault(schema.schema_id, schema)
                elif opcode == rec.OP_CHANNEL:
                    channel = _parse_channel(records[body_start:pos])
                    self._channels.setdefault(channel.channel_id, channel)
                    if (
                        channel_ids is not None
                        and wanted_topics is not None
                        and channel.topic in wanted_topics
                    ):
                        channel_ids.add(channel.channel_id)
        except (ValueError, UnicodeDecodeError, struct.error) as error:
            what = "chunk" if segment.is_chunk else "records"
            if self.indexed and not self.salvage:
                raise self._error(f"damaged {what} at offset {segment.offset} ({error})") from None
            self._skip(segment.offset, segment.length, f"damaged {what}: {error}")
            return []
        found.sort(key=lambda item: (item[0], item[1]))
        return found

    def _iter_raw(
        self,
        topics: Iterable[str] | None,
        start_ns: int | None,
        end_ns: int | None,
    ) -> Iterator[tuple[_Channel, int, memoryview]]:
        """(channel, log_time, cdr) in log-time order, loading chunks lazily by start time."""
        wanted = None if topics is None else set(topics)
        channel_ids = (
            None
            if wanted is None
            else {c.channel_id for c in self._channels.values() if c.topic in wanted}
        )
        candidates = []
        for segment in self._segments:
            if start_ns is not None and segment.end_time < start_ns:
                continue
            if end_ns is not None and segment.start_time >= end_ns:
                continue
            if (
                channel_ids is not None
                and self.indexed
                and segment.channel_ids is not None
                and not segment.channel_ids & channel_ids
            ):
                continue
            candidates.append(segment)
        candidates.sort(key=lambda s: (s.start_time, s.offset))
        loaded: dict[int, list[tuple[int, int, int, memoryview]]] = {}
        heap: list[tuple[int, int, int]] = []  # (log_time, segment order, position)
        next_segment = 0
        while True:
            # Load every chunk that may hold a message earlier than the next one to yield.
            while next_segment < len(candidates) and (
                not heap or candidates[next_segment].start_time <= heap[0][0]
            ):
                found = self._segment_messages(
                    candidates[next_segment], channel_ids, wanted, start_ns, end_ns
                )
                if found:
                    loaded[next_segment] = found
                    heapq.heappush(heap, (found[0][0], next_segment, 0))
                next_segment += 1
            if not heap:
                return
            _, order, position = heap[0]
            found = loaded[order]
            if len(heap) == 1 and (
                next_segment == len(candidates)
                or candidates[next_segment].start_time > found[-1][0]
            ):
                # One chunk alone until its end (the usual case): no heap work per message.
                for log_time, _, channel_id, data in found[position:]:
                    channel = self._known_channel(channel_id)
                    if channel is not None:
                        yield channel, log_time, data
                heapq.heappop(heap)
                del loaded[order]
                continue
            log_time, _, channel_id, data = found[position]
            if position + 1 < len(found):
                heapq.heapreplace(heap, (found[position + 1][0], order, position + 1))
            else:
                heapq.heappop(heap)
                del loaded[order]
            channel = self._known_channel(channel_id)
            if channel is not None:
                yield channel, log_time, data

    def _known_channel(self, channel_id: int) -> _Channel | None:
        """The channel of a message; None (and a warning, once) when no Channel record
        defines it (a damaged id): the message cannot be attributed to a topic."""
        channel = self._channels.get(channel_id)
        if channel is None:
            self._orphans[channel_id] = self._orphans.get(channel_id, 0) + 1
            if self._orphans[channel_id] == 1:
                self.warnings.append(
                    f"{self.path.name}: skipped messages of channel {channel_id}, which no "
                    "Channel record defines"
                )
        return channel

    # -- public API ---------------------------------------------------------

    def _schema_name(self, channel: _Channel) -> str:
        schema = self._schemas.get(channel.schema_id)
        return "" if schema is None else schema.name

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[tuple[str, int, ArchiveMessage]]:
        """Decoded messages as (topic, log_time_ns, message), in log-time order.

        `topics` limits the topics (None: all); `start_ns` (inclusive) and
        `end_ns` (exclusive) limit the log time, ns since epoch. Channels whose
        type is not an archive type are skipped with a line in `warnings`.
        """
        decoders: dict[int, tuple[Decoder, str] | None] = {}
        for channel, log_time, data in self._iter_raw(topics, start_ns, end_ns):
            channel_id = channel.channel_id
            if channel_id not in decoders:
                schema_name = self._schema_name(channel)
                decoder = DECODERS.get(schema_name)
                if decoder is None or channel.message_encoding != "cdr":
                    decoders[channel_id] = None
                    self.warnings.append(
                        f"{self.path.name}: topic {channel.topic!r} skipped (type "
                        f"{schema_name!r}, encoding {channel.message_encoding!r} not supported)"
                    )
                else:
                    decoders[channel_id] = (decoder, f"{self.path.name} {channel.topic}")
            entry = decoders[channel_id]
            if entry is None:
                continue
            try:
                message = entry[0](data, entry[1])
            except InputError as error:
                if not self.salvage:
                    raise
                # Salvage gives back everything valid: a damaged message is skipped, and said.
                self.warnings.append(f"skipped a message at log time {log_time} ns: {error}")
                continue
            yield channel.topic, log_time, message

    def raw_messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawRecord]:
        """Undecoded messages (topic, log time, type name, CDR bytes) in log-time order."""
        for channel, log_time, data in self._iter_raw(topics, start_ns, end_ns):
            yield RawRecord(channel.topic, log_time, self._schema_name(channel), bytes(data))

    def topics(self) -> dict[str, TopicInfo]:
        """Every topic with its type, message count and first/last log time (ns since epoch)."""
        if self._topic_info is None:
            self._topic_info = (
                self._topics_from_indexes() if self.indexed else self._topics_from_scan()
            )
        return dict(self._topic_info)

    def _topics_from_indexes(self) -> dict[str, TopicInfo]:
        times: dict[int, list[NDArray[np.uint64]]] = {}
        seen_at: dict[int, int] = {}  # channel id -> offset of a message index naming it
        for segment in self._segments:
            if segment.message_index_length == 0:
                return self._topics_from_scan()
            try:
                data = self._read_at(segment.message_index_offset, segment.message_index_length)
                pos = 0
                while pos < len(data):
                    opcode, length = _RECORD_HEAD.unpack_from(data, pos)
                    if pos + 9 + length > len(data):
                        raise ValueError("record runs past the message index block")
                    if opcode == rec.OP_MESSAGE_INDEX:
                        channel_id, size = struct.unpack_from("<HI", data, pos + 9)
                        entries = np.frombuffer(data, "<u8", size // 8, pos + 15)
                        times.setdefault(channel_id, []).append(entries[0::2])
                        seen_at.setdefault(channel_id, segment.message_index_offset + pos)
                    pos += 9 + length
            except (ValueError, struct.error) as error:
                where = f"message index at offset {segment.message_index_offset}"
                if not self.salvage:
                    raise self._error(f"damaged {where} ({error})") from None
                self.warnings.append(f"{self.path.name}: damaged {where} ({error}); scanning")
                return self._topics_from_scan()
        info: dict[str, TopicInfo] = {}
        for channel_id, parts in times.items():
            channel = self._channels.get(channel_id)
            if channel is None:
                what = (
                    f"the message index at offset {seen_at[channel_id]} names unknown "
                    f"channel {channel_id}"
                )
                if not self.salvage:
                    raise self._error(what)
                self.warnings.append(f"{self.path.name}: {what}; scanning")
                return self._topics_from_scan()
            all_times = np.concatenate(parts)
            if all_times.size:
                info[channel.topic] = TopicInfo(
                    topic=channel.topic,
                    schema_name=self._schema_name(channel),
                    message_count=int(all_times.size),
                    first_log_time_ns=int(all_times.min()),
                    last_log_time_ns=int(all_times.max()),
                )
        return dict(sorted(info.items()))

    def _topics_from_scan(self) -> dict[str, TopicInfo]:
        counts: dict[int, list[int]] = {}  # channel -> [count, first, last]
        for channel, log_time, _ in self._iter_raw(None, None, None):
            entry = counts.get(channel.channel_id)
            if entry is None:
                counts[channel.channel_id] = [1, log_time, log_time]
            else:
                entry[0] += 1
                entry[2] = log_time
        info = {
            self._channels[cid].topic: TopicInfo(
                topic=self._channels[cid].topic,
                schema_name=self._schema_name(self._channels[cid]),
                message_count=count,
                first_log_time_ns=first,
                last_log_time_ns=last,
            )
            for cid, (count, first, last) in counts.items()
        }
        return dict(sorted(info.items()))

    def time_span_ns(self) -> tuple[int, int]:
        """(first, last) log time of all messages, ns since epoch; InputError if there are none."""
        if self.indexed and self._statistics is not None and self._statistics[0] > 0:
            return self._statistics[1], self._statistics[2]
        infos = self.topics().values()
        if not infos:
            raise self._error("no messages")
        return (
            min(i.first_log_time_ns for i in infos),
            max(i.last_log_time_ns for i in infos),
        )

    def metadata(self) -> dict[str, dict[str, str]]:
        """The Metadata records by name (a later record of the same name updates it)."""
        from mcap.records import Metadata
        from mcap.stream_reader import StreamReader

        result: dict[str, dict[str, str]] = {}
        for offset, length in self._metadata_offsets:
            try:
                data = self._read_at(offset, length)
                stream = StreamReader(io.BytesIO(data), skip_magic=True, record_size_limit=length)
                record = next(stream.records)
                if not isinstance(record, Metadata):
                    raise ValueError(f"no Metadata record at offset {offset}")
                result.setdefault(record.name, {}).update(record.metadata)
            except (ValueError, UnicodeDecodeError, struct.error, McapError) as error:
                if not self.salvage:
                    raise self._error(f"damaged metadata at offset {offset} ({error})") from None
                self._skip(offset, length, f"damaged metadata: {error}")
        return result

    def read_imu(self, topic: str = "/imu0") -> ImuSeries:
        """All samples of an IMU topic as numpy arrays (fast bulk decode), in log-time order."""
        known = {c.topic: c for c in self._channels.values()}
        channel = known.get(topic)
        if channel is not None and self._schema_name(channel) != Imu.ROS_TYPE_NAME:
            raise self._error(
                f"topic {topic!r} holds {self._schema_name(channel)}, not {Imu.ROS_TYPE_NAME}"
            )
        log_times: list[int] = []
        payloads: list[memoryview] = []
        for found_channel, log_time, data in self._iter_raw([topic], None, None):
            if self._schema_name(found_channel) != Imu.ROS_TYPE_NAME:
                raise self._error(f"topic {topic!r} does not hold {Imu.ROS_TYPE_NAME}")
            log_times.append(log_time)
            payloads.append(data)
        if not payloads and topic not in {c.topic for c in self._channels.values()}:
            names = ", ".join(sorted({c.topic for c in self._channels.values()})) or "none"
            raise self._error(f"no topic {topic!r} (topics: {names})")
        name = f"{self.path.name} {topic}"
        try:
            arrays = decode_imu_batch(payloads, name)
        except InputError:
            if not self.salvage:
                raise
            good = []
            for index, payload in enumerate(payloads):
                try:
                    decode_imu_batch([payload], name)
                except InputError as error:
                    self.warnings.append(
                        f"skipped a message at log time {log_times[index]} ns: {error}"
                    )
                else:
                    good.append(index)
            log_times = [log_times[i] for i in good]
            arrays = decode_imu_batch([payloads[i] for i in good], name)
        return ImuSeries(
            topic=topic,
            stamps_ns=arrays.stamps_ns,
            log_times_ns=np.asarray(log_times, dtype=np.int64),
            gyro_rad_s=arrays.gyro_rad_s,
            accel_m_s2=arrays.accel_m_s2,
        )

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> ArchiveReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def iter_records_salvage(
    path: Path | str, *, warnings: list[str] | None = None
) -> Iterator[RawRecord]:
    """Every readable message of a possibly damaged archive, undecoded, in log-time order.

    For rebuilding a crashed recording: damaged chunks and a cut tail are
    skipped; a line per skipped part is appended to `warnings` when given.
    Raises InputError only when the file is not MCAP at all.
    """
    with ArchiveReader(path, salvage=True) as reader:
        try:
            yield from reader.raw_messages()
        finally:
            if warnings is not None:
                warnings.extend(reader.warnings)
