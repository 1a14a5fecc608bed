"""MCAP record layouts (opcodes, byte packing) for our own record writer and the reader.

Only what wreckmap's archives use: Header, Footer, Schema, Channel, Message,
Chunk, MessageIndex, ChunkIndex, Statistics, Metadata, MetadataIndex,
SummaryOffset and DataEnd, all little-endian as the MCAP specification
defines them (strings and maps carry a uint32 byte-length prefix, every
record is opcode uint8 + length uint64 + body).

The mcap package has these records too (`mcap.records`), as one object per
record. They stay here for the two places where that cost shows: the
`engine="wreckmap"` writer packs messages straight into a chunk buffer
(`MESSAGE_HEAD`, 2x the mcap writer's IMU rate), and the reader walks chunks
and salvages files with `struct` on memoryviews (shared/archive/reader.py
says what it reads through mcap instead).
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass, field

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_ATTACHMENT = 0x09
OP_ATTACHMENT_INDEX = 0x0A
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

RECORD_HEAD = struct.Struct("<BQ")
"""opcode, body length."""
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
"""A whole Message record head: opcode, length, channel_id, sequence, log_time, publish_time."""
MESSAGE_FIELDS = struct.Struct("<HIQQ")
MESSAGE_FIELDS_SIZE = MESSAGE_FIELDS.size  # 22
CHUNK_FIXED = struct.Struct("<QQQI")
"""message_start_time, message_end_time, uncompressed_size, uncompressed_crc."""
FOOTER_BODY = struct.Struct("<QQI")
FOOTER_RECORD_SIZE = RECORD_HEAD.size + FOOTER_BODY.size  # 29


def pack_str(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack("<I", len(raw)) + raw


def pack_bytes(data: bytes) -> bytes:
    return struct.pack("<I", len(data)) + data


def pack_str_map(values: Mapping[str, str]) -> bytes:
    body = b"".join(pack_str(k) + pack_str(v) for k, v in values.items())
    return struct.pack("<I", len(body)) + body


def record(opcode: int, body: bytes) -> bytes:
    return RECORD_HEAD.pack(opcode, len(body)) + body


def header_record(profile: str, library: str) -> bytes:
    return record(OP_HEADER, pack_str(profile) + pack_str(library))


def schema_record(schema_id: int, name: str, encoding: str, data: bytes) -> bytes:
    return record(
        OP_SCHEMA,
        struct.pack("<H", schema_id) + pack_str(name) + pack_str(encoding) + pack_bytes(data),
    )


def channel_record(
    channel_id: int, schema_id: int, topic: str, message_encoding: str, metadata: Mapping[str, str]
) -> bytes:
    return record(
        OP_CHANNEL,
        struct.pack("<HH", channel_id, schema_id)
        + pack_str(topic)
        + pack_str(message_encoding)
        + pack_str_map(metadata),
    )


def metadata_record(name: str, values: Mapping[str, str]) -> bytes:
    return record(OP_METADATA, pack_str(name) + pack_str_map(values))


def metadata_index_record(offset: int, length: int, name: str) -> bytes:
    return record(OP_METADATA_INDEX, struct.pack("<QQ", offset, length) + pack_str(name))


def message_index_record(channel_id: int, entries: list[int]) -> bytes:
    """`entries` is flat: log_time, offset, log_time, offset, ..."""
    body = struct.pack(f"<HI{len(entries)}Q", channel_id, 8 * len(entries), *entries)
    return record(OP_MESSAGE_INDEX, body)


@dataclass
class ChunkIndexEntry:
    """What a ChunkIndex record says about one chunk (offsets are absolute file offsets)."""

    message_start_time: int
    message_end_time: int
    chunk_start_offset: int
    chunk_length: int
    message_index_offsets: dict[int, int] = field(default_factory=dict)
    message_index_length: int = 0
    compression: str = ""
    compressed_size: int = 0
    uncompressed_size: int = 0

    def to_record(self) -> bytes:
        offsets = b"".join(struct.pack("<HQ", k, v) for k, v in self.message_index_offsets.items())
        return record(
            OP_CHUNK_INDEX,
            struct.pack(
                "<QQQQI",
                self.message_start_time,
                self.message_end_time,
                self.chunk_start_offset,
                self.chunk_length,
                len(offsets),
            )
            + offsets
            + struct.pack("<Q", self.message_index_length)
            + pack_str(self.compression)
            + struct.pack("<QQ", self.compressed_size, self.uncompressed_size),
        )


def statistics_record(
    *,
    message_count: int,
    schema_count: int,
    channel_count: int,
    metadata_count: int,
    chunk_count: int,
    message_start_time: int,
    message_end_time: int,
    channel_message_counts: Mapping[int, int],
) -> bytes:
    counts = b"".join(struct.pack("<HQ", k, v) for k, v in channel_message_counts.items())
    return record(
        OP_STATISTICS,
        struct.pack(
            "<QHIIIIQQI",
            message_count,
            schema_count,
            channel_count,
            0,  # attachments: none
            metadata_count,
            chunk_count,
            message_start_time,
            message_end_time,
            len(counts),
        )
        + counts,
    )


def summary_offset_record(group_opcode: int, group_start: int, group_length: int) -> bytes:
    return record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", group_opcode, group_start, group_length))


def data_end_record(data_section_crc: int = 0) -> bytes:
    return record(OP_DATA_END, struct.pack("<I", data_section_crc))
