"""A truncated or corrupt MCAP gives back everything valid and says what it skipped."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from shared.archive import ArchiveReader, ArchiveWriter, DepthSample, Imu, cdr
from shared.archive import mcap_records as rec
from shared.archive.messages import ArchiveMessage
from shared.errors import InputError

pytestmark = pytest.mark.timeout(60)

T0 = 1_700_000_000_000_000_000


def _messages(count: int) -> list[tuple[str, ArchiveMessage]]:
    rng = np.random.default_rng(11)
    out: list[tuple[str, ArchiveMessage]] = []
    for i in range(count):
        out.append(("/imu0", Imu(stamp_ns=T0 + i * 5_000_000, frame_id="imu0",
                                 angular_velocity_rad_s=rng.normal(size=3),
                                 linear_acceleration_m_s2=rng.normal(size=3))))  # fmt: skip
        if i % 7 == 0:
            out.append(("/depth0", DepthSample(stamp_ns=T0 + i * 5_000_000, frame_id="d",
                                               depth_m=float(i))))  # fmt: skip
    return out


def _write(path: Path, compression: str) -> list[tuple[int, int, int, int]]:
    """Write the archive; (offset, length, first log time, last log time) of each chunk."""
    with ArchiveWriter(path, chunk_size=2500, compression=compression) as writer:  # type: ignore[arg-type]
        for topic, message in _messages(300):
            writer.write(topic, message)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 5
    return [
        (c.chunk_start_offset, c.chunk_length, c.message_start_time, c.message_end_time)
        for c in summary.chunk_indexes
    ]


def _salvaged(path: Path, end: int) -> set[tuple[str, int]]:
    """(topic, stamp) of what a salvage read of the file's first `end` bytes gives."""
    part = path.with_name(f"part-{end}.mcap")
    part.write_bytes(path.read_bytes()[:end])
    with ArchiveReader(part, salvage=True) as reader:
        return {(topic, message.stamp_ns) for topic, _, message in reader.messages()}


def _expected(
    path: Path, chunks: list[tuple[int, int, int, int]], lost: set[int]
) -> list[tuple[str, int]]:
    """(topic, stamp) of every message outside the lost chunks, in log-time order (found by
    salvaging copies of the intact file cut at chunk ends)."""
    everything = {(topic, m.stamp_ns) for topic, m in _messages(300)}
    for index in lost:
        before = _salvaged(path, chunks[index][0]) if index else set()
        upto = _salvaged(path, chunks[index][0] + chunks[index][1])
        everything -= upto - before
    return sorted(everything, key=lambda item: (item[1], item[0]))


def _got(reader: ArchiveReader) -> list[tuple[str, int]]:
    return sorted(((topic, message.stamp_ns) for topic, _, message in reader.messages()),
                  key=lambda item: (item[1], item[0]))  # fmt: skip


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_corrupt_chunk_is_skipped_and_named(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "rec.mcap"
    chunks = _write(path, compression)
    offset, length, _, _ = chunks[2]
    expected = _expected(path, chunks, {2})
    data = bytearray(path.read_bytes())
    data[offset + length - 40] ^= 0x5A  # inside the chunk's (compressed) records
    path.write_bytes(bytes(data))
    with (
        ArchiveReader(path) as reader,
        pytest.raises(InputError, match=rf"rec\.mcap: damaged chunk at offset {offset} "),
    ):
        list(reader.messages())
    with ArchiveReader(path, salvage=True) as reader:
        got = _got(reader)
        assert got == expected
        assert len(got) < len(_messages(300))
        assert reader.skipped_bytes == length
        assert any(f"skipped {length} bytes at offset {offset}" in w for w in reader.warnings)


def test_file_cut_inside_a_chunk_keeps_the_chunks_before(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    chunks = _write(path, "zstd")
    offset, length, _, _ = chunks[3]
    expected = _expected(path, chunks, set(range(3, len(chunks))))
    cut = offset + length // 2
    path.write_bytes(path.read_bytes()[:cut])
    with pytest.raises(InputError, match=rf"rec\.mcap: truncated MCAP file .*ends at byte {cut}"):
        ArchiveReader(path)
    with ArchiveReader(path, salvage=True) as reader:
        got = _got(reader)
        assert got == expected and got
        assert any(f"skipped {cut - offset} bytes at offset {offset}" in w for w in reader.warnings)
        assert reader.skipped_bytes == cut - offset


def test_message_of_an_undefined_channel_is_skipped_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    chunks = _write(path, "none")
    offset, _, _, _ = chunks[1]
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, offset + 9 + 24, 0)  # chunk CRC 0: not checked
    records_at = offset + 9 + 8 + 8 + 8 + 4 + 4 + 8  # times, size, crc, "" compression, length
    opcode, length = rec.RECORD_HEAD.unpack_from(data, records_at)
    while opcode != rec.OP_MESSAGE:
        records_at += 9 + length
        opcode, length = rec.RECORD_HEAD.unpack_from(data, records_at)
    struct.pack_into("<H", data, records_at + 9, 999)  # its channel id
    victim_time = struct.unpack_from("<Q", data, records_at + 9 + 6)[0]
    path.write_bytes(bytes(data))
    expected = _expected(path, chunks, set())
    with ArchiveReader(path, salvage=True) as reader:
        got = _got(reader)
        assert len(got) == len(expected) - 1
        assert {s for _, s in expected} - {s for _, s in got} <= {victim_time}
        assert any("channel 999" in w for w in reader.warnings)


def test_damaged_message_index_falls_back_to_scanning_on_salvage(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write(path, "zstd")
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    first_index = min(summary.chunk_indexes[0].message_index_offsets.values())
    data = bytearray(path.read_bytes())
    struct.pack_into("<Q", data, first_index + 1, 1 << 40)  # its record length
    path.write_bytes(bytes(data))
    with (
        ArchiveReader(path) as reader,
        pytest.raises(
            InputError, match=rf"rec\.mcap: damaged message index at offset {first_index}"
        ),
    ):
        reader.topics()
    with ArchiveReader(path, salvage=True) as reader:
        topics = reader.topics()
        assert topics["/imu0"].message_count == 300
        assert topics["/depth0"].message_count == len(range(0, 300, 7))
        assert any("damaged message index" in w and "scanning" in w for w in reader.warnings)
        assert len(_got(reader)) == len(_messages(300))


def test_encoded_messages_round_trip_after_salvage(tmp_path: Path) -> None:
    """What salvage gives back is byte-identical to what was written."""
    path = tmp_path / "rec.mcap"
    _write(path, "zstd")
    with ArchiveReader(path, salvage=True) as reader:
        raw = [(r.topic, r.data) for r in reader.raw_messages()]
    written = sorted(((t, cdr.encode(m)) for t, m in _messages(300)), key=lambda x: x[0])
    assert sorted(raw, key=lambda x: x[0]) == written
