"""ArchiveWriter: record archive messages into a chunked, compressed, indexed MCAP file.

The file is written as `<path>.part` and renamed to `<path>` only by a clean
`close()` after an fsync, so a file named `*.mcap` is always complete and
indexed; a `.part` left behind is a crashed or aborted recording that
`shared.archive.reader.iter_records_salvage` can still read.

Each chunk repeats the Schema and Channel records of the channels it holds,
so every chunk can be decoded on its own (a damaged chunk loses only its own
messages). The summary section carries the schemas, channels, statistics,
chunk indexes and metadata indexes; each chunk is followed by one
MessageIndex record per channel.
"""

from __future__ import annotations

import os
import struct
import threading
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from shared.archive import mcap_records as rec
from shared.archive.cdr import ENCODERS, schema_text
from shared.archive.messages import ArchiveMessage
from shared.archive.topics import message_type_for_topic
from shared.errors import InputError, OutputExistsError, WreckmapError
from shared.fsutil import fsync_dir

PROFILE = "ros2"
MESSAGE_ENCODING = "cdr"
SCHEMA_ENCODING = "ros2msg"
LIBRARY = "wreckmap-archive/1"
SESSION_METADATA_NAME = "wreckmap_session"
"""Name of the Metadata record written from the `metadata` argument of ArchiveWriter."""

Compression = Literal["zstd", "lz4", "none"]


def part_path(path: Path | str) -> Path:
    """The temporary name `<path>.part` under which an open archive is written."""
    final = Path(path)
    return final.with_name(final.name + ".part")


@dataclass
class _Channel:
    channel_id: int
    schema_id: int
    topic: str
    message_type: type[Any]
    encoder: Callable[[Any], bytes]
    record: bytes
    count: int = 0


def _keep(data: bytearray) -> bytearray:
    return data


def _compressor(compression: str) -> tuple[str, Callable[[bytearray], bytes | bytearray]]:
    if compression == "zstd":
        import zstandard

        return "zstd", zstandard.ZstdCompressor(level=3).compress
    if compression == "lz4":
        try:
            import lz4.frame  # type: ignore[import-untyped, import-not-found, unused-ignore]
        except ImportError:
            raise InputError("compression 'lz4': the lz4 package is not installed") from None
        compress: Callable[[bytearray], bytes] = lz4.frame.compress
        return "lz4", compress
    if compression == "none":
        return "", _keep
    raise InputError(f"compression {compression!r}: expected 'zstd', 'lz4' or 'none'")


class ArchiveWriter:
    """Write archive messages to an MCAP file (ROS 2 profile, CDR messages).

    Use as a context manager. `write(topic, message)` checks the message class
    against the topic registry (`shared.archive.topics`) and stores the
    message with log time = `log_time_ns` (host receive time, ns since epoch)
    or, when omitted, the message's own `stamp_ns`.

    Args:
        path: the final file name (`*.mcap`); written as `<path>.part` until closed.
        overwrite: replace an existing `path` or `.part`; otherwise OutputExistsError.
        chunk_size: uncompressed bytes per chunk before it is compressed and written.
        compression: chunk compression, "zstd" (default), "lz4" or "none".
        metadata: key facts stored in a Metadata record named `wreckmap_session`.

    One writer may be shared by threads (writes are serialized by a lock).
    An exception inside the `with` block still writes the summary but leaves
    the file under its `.part` name.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        overwrite: bool = False,
        chunk_size: int = 4 * 2**20,
        compression: Compression = "zstd",
        metadata: dict[str, str] | None = None,
    ) -> None:
        self.path = Path(path)
        self.part_path = part_path(self.path)
        self._overwrite = overwrite
        if not overwrite:
            for existing in (self.path, self.part_path):
                if existing.exists():
                    raise OutputExistsError(
                        f"{existing}: already exists (refusing to overwrite a recording)"
                    )
        if chunk_size <= 0:
            raise InputError(f"chunk_size {chunk_size}: expected a positive number of bytes")
        self._compression_name, self._compress = _compressor(compression)
        self._chunk_size = chunk_size
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.part_path.open("wb" if overwrite else "xb")
        self._lock = threading.Lock()
        self._pos = 0
        self._closed = False
        self._schemas: dict[str, tuple[int, bytes]] = {}
        self._channels: dict[str, _Channel] = {}
        self._chunk_indexes: list[rec.ChunkIndexEntry] = []
        self._metadata_indexes: list[tuple[int, int, str]] = []
        self._message_count = 0
        self._start_time = 0
        self._end_time = 0
        self._new_chunk()
        self._emit(rec.MAGIC + rec.header_record(PROFILE, LIBRARY))
        if metadata:
            self.add_metadata(SESSION_METADATA_NAME, metadata)

    # -- public API ---------------------------------------------------------

    @property
    def messages_written(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return {topic: channel.count for topic, channel in self._channels.items()}

    @property
    def closed(self) -> bool:
        """True once closed or aborted."""
        return self._closed

    @property
    def bytes_written(self) -> int:
        """File bytes so far plus the uncompressed chunk in progress (for size-based rotation)."""
        return self._pos + len(self._chunk)

    def write(self, topic: str, message: ArchiveMessage, *, log_time_ns: int | None = None) -> None:
        """Append `message` on `topic`; `log_time_ns` (ns since epoch) defaults to its stamp."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._register(topic)
        if type(message) is not channel.message_type:
            raise InputError(
                f"topic {topic!r}: expected a {channel.message_type.__name__} message, "
                f"got {type(message).__name__}"
            )
        data = channel.encoder(message)
        self._append(channel, message.stamp_ns if log_time_ns is None else log_time_ns, data)

    def write_cdr(self, topic: str, data: bytes, *, log_time_ns: int) -> None:
        """Append an already encoded message (CDR bytes with their 4-byte header) on `topic`.

        For copying records between archives (recovering a crashed recording)
        without decoding them; the topic must be in the registry.
        """
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._register(topic)
        if data[:2] != b"\x00\x01":
            raise InputError(
                f"topic {topic!r}: not little-endian CDR (expected 00 01 first, "
                f"got {bytes(data[:4]).hex(' ') or 'nothing'})"
            )
        self._append(channel, log_time_ns, data)

    def _append(self, channel: _Channel, log_time: int, data: bytes) -> None:
        with self._lock:
            if self._closed:
                raise WreckmapError(f"{self.path}: archive already closed")
            buffer = self._chunk
            channel_id = channel.channel_id
            if channel_id not in self._chunk_entries:
                self._add_channel_to_chunk(channel)
            offset = len(buffer)
            try:
                buffer += rec.MESSAGE_HEAD.pack(
                    rec.OP_MESSAGE,
                    rec.MESSAGE_FIELDS_SIZE + len(data),
                    channel_id,
                    channel.count & 0xFFFFFFFF,
                    log_time,
                    log_time,
                )
            except struct.error as error:  # a time outside uint64, or not an int
                raise InputError(
                    f"topic {channel.topic!r}: log time {log_time!r} ns is not a uint64 ({error})"
                ) from None
            buffer += data
            entries = self._chunk_entries[channel_id]
            entries.append(log_time)
            entries.append(offset)
            channel.count += 1
            if self._chunk_messages == 0:
                self._chunk_start = log_time
                self._chunk_end = log_time
            elif log_time < self._chunk_start:
                self._chunk_start = log_time
            elif log_time > self._chunk_end:
                self._chunk_end = log_time
            self._chunk_messages += 1
            if len(buffer) >= self._chunk_size:
                self._finish_chunk()

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """Store a named string-to-string Metadata record (indexed in the summary)."""
        bad = [k for k, v in values.items() if not isinstance(k, str) or not isinstance(v, str)]
        if bad:
            raise InputError(f"metadata {name!r}: keys and values must be strings (bad: {bad})")
        with self._lock:
            self._check_open()
            record = rec.metadata_record(name, values)
            self._metadata_indexes.append((self._pos, len(record), name))
            self._emit(record)

    def flush(self, *, fsync: bool = False) -> None:
        """Write the chunk in progress to the file (and fsync it when asked).

        A crash after `flush` loses nothing written before it: the `.part`
        file can be salvaged. Flushing often makes chunks smaller.
        """
        with self._lock:
            self._check_open()
            self._finish_chunk()
            self._file.flush()
            if fsync:
                os.fsync(self._file.fileno())

    def close(self) -> Path:
        """Finish the file (summary, footer), fsync it and rename `.part` to the final path."""
        return self._finish(rename=True)

    def abort(self) -> Path:
        """Finish the file (readable, indexed) but keep it under its `.part` name."""
        return self._finish(rename=False)

    def __enter__(self) -> ArchiveWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if not self._closed:
            self._finish(rename=exc_type is None)

    # -- internals ----------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise WreckmapError(f"{self.path}: archive already closed")

    def _emit(self, data: bytes | bytearray) -> None:
        self._file.write(data)
        self._pos += len(data)

    def _register(self, topic: str) -> _Channel:
        message_type = message_type_for_topic(topic)
        with self._lock:
            self._check_open()
            existing = self._channels.get(topic)
            if existing is not None:
                return existing
            name = message_type.ROS_TYPE_NAME
            schema = self._schemas.get(name)
            if schema is None:
                schema_id = len(self._schemas) + 1
                schema = (
                    schema_id,
                    rec.schema_record(
                        schema_id, name, SCHEMA_ENCODING, schema_text(message_type).encode()
                    ),
                )
                self._schemas[name] = schema
            channel_id = len(self._channels) + 1
            channel = _Channel(
                channel_id=channel_id,
                schema_id=schema[0],
                topic=topic,
                message_type=message_type,
                encoder=ENCODERS[message_type],
                record=rec.channel_record(channel_id, schema[0], topic, MESSAGE_ENCODING, {}),
            )
            self._channels[topic] = channel
            return channel

    def _new_chunk(self) -> None:
        self._chunk = bytearray()
        self._chunk_entries: dict[int, list[int]] = {}
        self._chunk_schemas: set[int] = set()
        self._chunk_messages = 0
        self._chunk_start = 0
        self._chunk_end = 0

    def _add_channel_to_chunk(self, channel: _Channel) -> None:
        # Repeat schema + channel in every chunk that uses them: chunks stay self-contained.
        if channel.schema_id not in self._chunk_schemas:
            for schema_id, record in self._schemas.values():
                if schema_id == channel.schema_id:
                    self._chunk += record
            self._chunk_schemas.add(channel.schema_id)
        self._chunk += channel.record
        self._chunk_entries[channel.channel_id] = []

    def _finish_chunk(self) -> None:
        if self._chunk_messages == 0:
            return
        # The buffer is handed over (a new one starts below): no copy of the chunk.
        raw = self._chunk
        compressed = self._compress(raw)
        chunk_offset = self._pos
        head = rec.CHUNK_FIXED.pack(
            self._chunk_start, self._chunk_end, len(raw), zlib.crc32(raw)
        ) + rec.pack_str(self._compression_name)
        body_length = len(head) + 8 + len(compressed)
        self._emit(rec.RECORD_HEAD.pack(rec.OP_CHUNK, body_length) + head)
        self._emit(len(compressed).to_bytes(8, "little"))
        self._emit(compressed)
        index = rec.ChunkIndexEntry(
            message_start_time=self._chunk_start,
            message_end_time=self._chunk_end,
            chunk_start_offset=chunk_offset,
            chunk_length=self._pos - chunk_offset,
            compression=self._compression_name,
            compressed_size=len(compressed),
            uncompressed_size=len(raw),
        )
        index_start = self._pos
        for channel_id, entries in self._chunk_entries.items():
            index.message_index_offsets[channel_id] = self._pos
            self._emit(rec.message_index_record(channel_id, entries))
        index.message_index_length = self._pos - index_start
        self._chunk_indexes.append(index)
        if self._message_count == 0:
            self._start_time, self._end_time = self._chunk_start, self._chunk_end
        else:
            self._start_time = min(self._start_time, self._chunk_start)
            self._end_time = max(self._end_time, self._chunk_end)
        self._message_count += self._chunk_messages
        self._new_chunk()

    def _summary(self, summary_start: int) -> tuple[bytes, bytes]:
        """(summary groups, summary offset records) for a summary starting at `summary_start`."""
        groups: list[tuple[int, bytes]] = [
            (rec.OP_SCHEMA, b"".join(record for _, record in self._schemas.values())),
            (rec.OP_CHANNEL, b"".join(c.record for c in self._channels.values())),
            (
                rec.OP_STATISTICS,
                rec.statistics_record(
                    message_count=self._message_count,
                    schema_count=len(self._schemas),
                    channel_count=len(self._channels),
                    metadata_count=len(self._metadata_indexes),
                    chunk_count=len(self._chunk_indexes),
                    message_start_time=self._start_time,
                    message_end_time=self._end_time,
                    channel_message_counts={
                        c.channel_id: c.count for c in self._channels.values() if c.count
                    },
                ),
            ),
            (rec.OP_CHUNK_INDEX, b"".join(i.to_record() for i in self._chunk_indexes)),
            (
                rec.OP_METADATA_INDEX,
                b"".join(
                    rec.metadata_index_record(offset, length, name)
                    for offset, length, name in self._metadata_indexes
                ),
            ),
        ]
        body = bytearray()
        offsets = bytearray()
        for opcode, group in groups:
            if group:
                offsets += rec.summary_offset_record(opcode, summary_start + len(body), len(group))
                body += group
        return bytes(body), bytes(offsets)

    def _finish(self, *, rename: bool) -> Path:
        with self._lock:
            if self._closed:
                return self.path if rename else self.part_path
            self._closed = True
            try:
                self._finish_chunk()
                self._emit(rec.data_end_record())
                summary_start = self._pos
                body, offsets = self._summary(summary_start)
                summary = body + offsets
                offset_start = summary_start + len(body)
                # The summary CRC covers the summary and the footer up to its CRC field.
                footer = rec.RECORD_HEAD.pack(rec.OP_FOOTER, rec.FOOTER_BODY.size)
                footer += rec.FOOTER_BODY.pack(summary_start, offset_start, 0)[:16]
                crc = zlib.crc32(footer, zlib.crc32(summary))
                self._emit(summary)
                self._emit(footer + crc.to_bytes(4, "little"))
                self._emit(rec.MAGIC)
                self._file.flush()
                os.fsync(self._file.fileno())
            finally:
                self._file.close()
            if not rename:
                return self.part_path
            if self.path.exists() and not self._overwrite:
                raise OutputExistsError(
                    f"{self.path}: appeared while recording; the recording stays in "
                    f"{self.part_path.name}"
                )
            self.part_path.replace(self.path)
            fsync_dir(self.path.parent)
            return self.path
