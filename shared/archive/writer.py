"""ArchiveWriter: record archive messages into a chunked, compressed, indexed MCAP file.

The records are written by the `mcap` package (`mcap.writer.Writer`, the
reference Python writer) by default; what wreckmap adds around it is the
archive's contract:

- the topic registry and the CDR encoding (`shared.archive.topics`, `cdr`);
- the file is written as `<path>.part` and renamed to `<path>` only by a clean
  `close()` after an fsync, so a file named `*.mcap` is always complete and
  indexed; a `.part` left behind is a crashed or aborted recording that
  `shared.archive.reader.iter_records_salvage` can still read;
- `flush(fsync=True)`: what was written before it survives a power cut;
- one writer shared by threads (a lock), `bytes_written` for size rotation;
- self-contained chunks: each chunk repeats the Schema and Channel records of
  the channels it holds, so every chunk decodes on its own and a damaged chunk
  loses only its own messages (a salvage read of a `.part` has no summary to
  find the channels in). `mcap.writer.Writer` writes each channel once, into
  the chunk open when it is registered, and has no public way to repeat it;
  `_self_contained_chunks()` (a subclass of mcap's own ChunkBuilder, put in
  place of the writer's) adds the records. It relies on mcap 1.6's private
  attribute `_Writer__chunk_builder`, hence the exact pin in pyproject.toml
  and the check in `_McapRecords`.

Our own record writer (`engine="wreckmap"`, `_OwnRecords` on
`shared.archive.mcap_records`) is kept beside it because it is measurably
cheaper: it packs each message straight into one bytearray per chunk, where
mcap builds a Message object per message and copies each byte through two
BytesIO buffers. bench/bench_archive.py measures both in one run (two runs
at load average 10-12 on 2 cores, so the absolute rates are low, the ratios
hold): IMU messages 2.0x faster with ours; 200 kB video packets about even
with zstd (0.88x and 1.14x), 1.21x faster with ours uncompressed; on the
recorder's own stream (two 8 Mb/s cameras, 400 Hz IMU, 1 MiB chunks, fsync
every 0.5 s) the writer costs 1.8 % of one core with ours and 2.1-2.4 % with
mcap, a small part of the recorder's 10 % budget (bench_record.py, both
recorders side by side at load 9-12, two runs: 13.9 and 13.3 % of a core on
mcap, 12.0 and 12.0 % on ours; the same record writer as before this change
gives the 12.0 %, so that load lifts the whole figure past 10 % whichever
writer is used). So, per use:
the recorder, recover, simulation and export use the default, the mcap
package; the GoPro importer, a bulk copy whose goal is a speed relative to a
plain file copy, asks for "wreckmap" (its import ran 1.30x longer on mcap:
import/copy speed 0.52 against 0.67, goal >= 0.5).
"""

from __future__ import annotations

import operator
import os
import struct
import threading
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal, Protocol

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
Engine = Literal["mcap", "wreckmap"]
"""Who writes the MCAP records: the `mcap` package (default) or our own record writer."""

_UINT64_LIMIT = 1 << 64


def part_path(path: Path | str) -> Path:
    """The temporary name `<path>.part` under which an open archive is written."""
    final = Path(path)
    return final.with_name(final.name + ".part")


def _check_compression(compression: str) -> None:
    if compression == "lz4":
        try:
            import lz4.frame  # type: ignore[import-untyped, import-not-found, unused-ignore]  # noqa: F401
        except ImportError:
            raise InputError("compression 'lz4': the lz4 package is not installed") from None
    elif compression not in ("zstd", "none"):
        raise InputError(f"compression {compression!r}: expected 'zstd', 'lz4' or 'none'")


class _Records(Protocol):
    """The record layer under ArchiveWriter: one MCAP file, chunked and indexed.

    Channel ids are handed out by `register`, from 1. The caller serializes calls.
    """

    def register(self, schema_name: str, schema_data: bytes, topic: str) -> int: ...

    def add_message(self, channel_id: int, sequence: int, log_time: int, data: bytes) -> None: ...

    def add_metadata(self, name: str, values: dict[str, str]) -> None: ...

    def flush(self) -> None:
        """Write the chunk in progress (if any) and everything buffered to the file."""

    def finish(self) -> None:
        """Write the last chunk, the summary, the footer and the closing magic."""

    @property
    def pending_bytes(self) -> int:
        """Uncompressed bytes of the chunk in progress."""
        ...


# -- the mcap package ---------------------------------------------------------


def _mcap_records(
    stream: IO[bytes], *, compression: str, chunk_size: int, library: str
) -> _Records:
    from mcap.writer import CompressionType, IndexType, Writer

    kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    writer = Writer(
        stream,
        chunk_size=chunk_size,
        compression=kind[compression],
        # No attachments: leave out their (empty) index group.
        index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA,
    )
    return _McapRecords(writer, library)


def _self_contained_chunks() -> Any:
    """A ChunkBuilder that puts the Schema and Channel records of a channel into every
    chunk holding one of its messages (mcap's own builder writes them once)."""
    from mcap._chunk_builder import ChunkBuilder
    from mcap.records import Channel, Message, Schema

    class SelfContainedChunks(ChunkBuilder):
        def __init__(self) -> None:
            super().__init__()
            self.schemas: dict[int, Schema] = {}
            self.channels: dict[int, Channel] = {}
            self._present: set[int] = set()  # channel ids (and -schema ids) in this chunk

        # Registration only records them: they are written with each chunk's first
        # message of the channel (a channel without messages is in the summary only).
        def add_schema(self, schema: Schema) -> None:
            self.schemas[schema.id] = schema

        def add_channel(self, channel: Channel) -> None:
            self.channels[channel.id] = channel

        def add_message(self, message: Message) -> None:
            channel_id = message.channel_id
            if channel_id not in self._present:
                channel = self.channels[channel_id]
                if channel.schema_id and -channel.schema_id not in self._present:
                    self.schemas[channel.schema_id].write(self.record_writer)
                    self._present.add(-channel.schema_id)
                channel.write(self.record_writer)
                self._present.add(channel_id)
            super().add_message(message)

        def reset(self) -> None:
            super().reset()  # type: ignore[no-untyped-call]
            self._present.clear()

    return SelfContainedChunks()


class _McapRecords:
    def __init__(self, writer: Any, library: str) -> None:
        builder = getattr(writer, "_Writer__chunk_builder", None)
        from mcap._chunk_builder import ChunkBuilder

        if not isinstance(builder, ChunkBuilder):
            raise WreckmapError(
                "mcap.writer.Writer: no chunk builder where mcap 1.6 keeps it "
                "(pyproject.toml pins the mcap version this writer was built for)"
            )
        self._builder = _self_contained_chunks()
        writer._Writer__chunk_builder = self._builder
        self._writer = writer
        writer.start(profile=PROFILE, library=library)

    def register(self, schema_name: str, schema_data: bytes, topic: str) -> int:
        schema_id = next(
            (
                s.id
                for s in self._builder.schemas.values()
                if (s.name, s.data) == (schema_name, schema_data)
            ),
            None,
        )
        if schema_id is None:
            schema_id = self._writer.register_schema(schema_name, SCHEMA_ENCODING, schema_data)
        return int(self._writer.register_channel(topic, MESSAGE_ENCODING, schema_id, {}))

    def add_message(self, channel_id: int, sequence: int, log_time: int, data: bytes) -> None:
        self._writer.add_message(channel_id, log_time, data, log_time, sequence)

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        self._writer.add_metadata(name, values)

    def flush(self) -> None:
        self._writer.flush()

    def finish(self) -> None:
        self._writer.finish()

    @property
    def pending_bytes(self) -> int:
        return int(self._builder.count)


# -- our own record writer ----------------------------------------------------


def _keep(data: bytearray) -> bytearray:
    return data


def _compressor(compression: str) -> tuple[str, Callable[[bytearray], bytes | bytearray]]:
    if compression == "zstd":
        import zstandard

        return "zstd", zstandard.ZstdCompressor(level=3).compress
    if compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped, import-not-found, unused-ignore]

        compress: Callable[[bytearray], bytes] = lz4.frame.compress
        return "lz4", compress
    return "", _keep


@dataclass
class _OwnChannel:
    schema_id: int
    record: bytes


class _OwnRecords:
    """The same file layout as `_McapRecords`, written with `mcap_records` and a bytearray
    chunk buffer: no record objects per message (what makes it faster)."""

    def __init__(self, stream: IO[bytes], *, compression: str, chunk_size: int, library: str):
        self._file = stream
        self._compression_name, self._compress = _compressor(compression)
        self._chunk_size = chunk_size
        self._pos = 0
        self._schemas: dict[tuple[str, bytes], tuple[int, bytes]] = {}
        self._schema_records: dict[int, bytes] = {}
        self._channels: dict[int, _OwnChannel] = {}
        self._channel_counts: dict[int, int] = {}
        self._chunk_indexes: list[rec.ChunkIndexEntry] = []
        self._metadata_indexes: list[tuple[int, int, str]] = []
        self._message_count = 0
        self._start_time = 0
        self._end_time = 0
        self._new_chunk()
        self._emit(rec.MAGIC + rec.header_record(PROFILE, library))

    @property
    def pending_bytes(self) -> int:
        return len(self._chunk)

    def _emit(self, data: bytes | bytearray) -> None:
        self._file.write(data)
        self._pos += len(data)

    def register(self, schema_name: str, schema_data: bytes, topic: str) -> int:
        schema = self._schemas.get((schema_name, schema_data))
        if schema is None:
            schema_id = len(self._schemas) + 1
            record = rec.schema_record(schema_id, schema_name, SCHEMA_ENCODING, schema_data)
            schema = self._schemas[(schema_name, schema_data)] = (schema_id, record)
            self._schema_records[schema_id] = record
        channel_id = len(self._channels) + 1
        self._channels[channel_id] = _OwnChannel(
            schema_id=schema[0],
            record=rec.channel_record(channel_id, schema[0], topic, MESSAGE_ENCODING, {}),
        )
        return channel_id

    def add_message(self, channel_id: int, sequence: int, log_time: int, data: bytes) -> None:
        buffer = self._chunk
        if channel_id not in self._chunk_entries:
            self._add_channel_to_chunk(channel_id)
        offset = len(buffer)
        buffer += rec.MESSAGE_HEAD.pack(
            rec.OP_MESSAGE,
            rec.MESSAGE_FIELDS_SIZE + len(data),
            channel_id,
            sequence,
            log_time,
            log_time,
        )
        buffer += data
        entries = self._chunk_entries[channel_id]
        entries.append(log_time)
        entries.append(offset)
        self._channel_counts[channel_id] = self._channel_counts.get(channel_id, 0) + 1
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
        record = rec.metadata_record(name, values)
        self._metadata_indexes.append((self._pos, len(record), name))
        self._emit(record)

    def flush(self) -> None:
        self._finish_chunk()
        self._file.flush()

    def _new_chunk(self) -> None:
        self._chunk = bytearray()
        self._chunk_entries: dict[int, list[int]] = {}
        self._chunk_schemas: set[int] = set()
        self._chunk_messages = 0
        self._chunk_start = 0
        self._chunk_end = 0

    def _add_channel_to_chunk(self, channel_id: int) -> None:
        # Repeat schema + channel in every chunk that uses them: chunks stay self-contained.
        channel = self._channels[channel_id]
        if channel.schema_id not in self._chunk_schemas:
            self._chunk += self._schema_records[channel.schema_id]
            self._chunk_schemas.add(channel.schema_id)
        self._chunk += channel.record
        self._chunk_entries[channel_id] = []

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
                    channel_message_counts=self._channel_counts,
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

    def finish(self) -> None:
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


# -- the archive writer -------------------------------------------------------


@dataclass
class _Channel:
    channel_id: int
    topic: str
    message_type: type[Any]
    encoder: Callable[[Any], bytes]
    count: int = 0


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
        engine: who writes the records: "mcap" (the mcap package, default) or
            "wreckmap" (our own record writer, the same layout at a lower CPU cost).

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
        engine: Engine = "mcap",
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
        _check_compression(compression)
        if engine == "mcap":
            make: Callable[..., _Records] = _mcap_records
            from mcap.writer import LIBRARY_IDENTIFIER

            library = f"{LIBRARY}; {LIBRARY_IDENTIFIER}"
        elif engine == "wreckmap":
            make, library = _OwnRecords, LIBRARY
        else:
            raise InputError(f"engine {engine!r}: expected 'mcap' or 'wreckmap'")
        self.engine = engine
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.part_path.open("wb" if overwrite else "xb")
        try:
            self._records = make(
                self._file, compression=compression, chunk_size=chunk_size, library=library
            )
        except BaseException:
            self._file.close()
            raise
        self._lock = threading.Lock()
        self._closed = False
        self._final_size = 0
        self._schema_texts: dict[type[Any], bytes] = {}
        self._channels: dict[str, _Channel] = {}
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
        if self._closed:
            return self._final_size
        return self._file.tell() + self._records.pending_bytes

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
        # Checked before the record layer sees it: a bad time must not leave a half-written
        # message (mcap counts the message in its statistics before packing it).
        try:
            log_time = operator.index(log_time)
            if not 0 <= log_time < _UINT64_LIMIT:
                raise struct.error("out of range")
        except (TypeError, struct.error) as error:
            raise InputError(
                f"topic {channel.topic!r}: log time {log_time!r} ns is not a uint64 ({error})"
            ) from None
        with self._lock:
            self._check_open()
            self._records.add_message(
                channel.channel_id, channel.count & 0xFFFFFFFF, log_time, data
            )
            channel.count += 1

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """Store a named string-to-string Metadata record (indexed in the summary)."""
        bad = [k for k, v in values.items() if not isinstance(k, str) or not isinstance(v, str)]
        if bad:
            raise InputError(f"metadata {name!r}: keys and values must be strings (bad: {bad})")
        with self._lock:
            self._check_open()
            self._records.add_metadata(name, dict(values))

    def flush(self, *, fsync: bool = False) -> None:
        """Write the chunk in progress to the file (and fsync it when asked).

        A crash after `flush` loses nothing written before it: the `.part`
        file can be salvaged. Flushing often makes chunks smaller.
        """
        with self._lock:
            self._check_open()
            self._records.flush()
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

    def _register(self, topic: str) -> _Channel:
        message_type = message_type_for_topic(topic)
        with self._lock:
            self._check_open()
            existing = self._channels.get(topic)
            if existing is not None:
                return existing
            text = self._schema_texts.get(message_type)
            if text is None:
                text = self._schema_texts[message_type] = schema_text(message_type).encode()
            channel_id = self._records.register(message_type.ROS_TYPE_NAME, text, topic)
            channel = _Channel(
                channel_id=channel_id,
                topic=topic,
                message_type=message_type,
                encoder=ENCODERS[message_type],
            )
            self._channels[topic] = channel
            return channel

    def _finish(self, *, rename: bool) -> Path:
        with self._lock:
            if self._closed:
                return self.path if rename else self.part_path
            self._closed = True
            try:
                self._records.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
                self._final_size = self._file.tell()
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
