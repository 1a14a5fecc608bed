"""Damaged archives: refused by default (InputError), read as far as they go on salvage."""

from __future__ import annotations

import shutil
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from shared.archive import (
    SESSION_TOPIC,
    ArchiveReader,
    ArchiveWriter,
    DepthSample,
    Imu,
    SessionInfo,
    cdr,
    depth_topic,
    imu_topic,
    iter_records_salvage,
    part_path,
)
from shared.archive.messages import ArchiveMessage
from shared.errors import InputError

T0 = 1_650_000_000_000_000_000


def stream(count: int, seed: int = 0) -> list[tuple[str, ArchiveMessage]]:
    rng = np.random.default_rng(seed)
    out: list[tuple[str, ArchiveMessage]] = []
    for i in range(count):
        out.append(
            (
                imu_topic(0),
                Imu(
                    stamp_ns=T0 + i * 2_500_000,
                    frame_id="imu0",
                    angular_velocity_rad_s=rng.normal(size=3),
                    linear_acceleration_m_s2=rng.normal(size=3),
                ),
            )
        )
        if i % 20 == 0:
            out.append(
                (depth_topic(0), DepthSample(stamp_ns=T0 + i * 2_500_000, frame_id="d", depth_m=i))
            )
    return out


def encoded(messages: list[tuple[str, ArchiveMessage]]) -> list[tuple[str, int, bytes]]:
    return [(t, m.stamp_ns, cdr.encode(m)) for t, m in messages]


def write(path: Path, messages: list[tuple[str, ArchiveMessage]], chunk_size: int = 8000) -> None:
    with ArchiveWriter(path, chunk_size=chunk_size, metadata={"site": "wreck"}) as writer:
        for topic, message in messages:
            writer.write(topic, message)


def chunk_layout(path: Path) -> list[tuple[int, int, dict[int, int]]]:
    """(offset, length, message index offsets) of every chunk, from mcap's own reader."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return [
        (c.chunk_start_offset, c.chunk_length, dict(c.message_index_offsets))
        for c in summary.chunk_indexes
    ]


def test_crashed_writer_is_salvaged_up_to_the_last_flush(tmp_path: Path) -> None:
    messages = stream(600)
    path = tmp_path / "recording.mcap"
    crashed = tmp_path / "crashed" / "recording.mcap.part"
    crashed.parent.mkdir()
    with ArchiveWriter(path, chunk_size=6000, metadata={"site": "wreck"}) as writer:
        for topic, message in messages[:400]:
            writer.write(topic, message)
        writer.flush(fsync=True)
        shutil.copy(part_path(path), crashed)  # what a power cut would leave on disk
        for topic, message in messages[400:]:
            writer.write(topic, message)
    with pytest.raises(InputError, match=r"recording\.mcap\.part: truncated MCAP file \(no footer"):
        ArchiveReader(crashed)
    with ArchiveReader(crashed, salvage=True) as reader:
        assert not reader.indexed
        got = [(t, lt, cdr.encode(m)) for t, lt, m in reader.messages()]
        assert got == encoded(messages[:400])
        assert reader.skipped_bytes == 0
        assert any("no footer" in w for w in reader.warnings)
        assert reader.metadata() == {"wreckmap_session": {"site": "wreck"}}
        assert reader.topics()[imu_topic(0)].message_count == sum(
            1 for t, _ in messages[:400] if t == imu_topic(0)
        )
        assert reader.time_span_ns() == (T0, messages[399][1].stamp_ns)
        assert len(reader.read_imu().stamps_ns) == reader.topics()[imu_topic(0)].message_count
    warnings: list[str] = []
    raw = list(iter_records_salvage(crashed, warnings=warnings))
    assert [(r.topic, r.log_time_ns, r.data) for r in raw] == encoded(messages[:400])
    assert raw[0].schema_name == Imu.ROS_TYPE_NAME
    assert warnings and "no footer" in warnings[0]


def test_truncated_anywhere_yields_a_prefix_of_whole_chunks(tmp_path: Path) -> None:
    messages = stream(300, seed=1)
    path = tmp_path / "full.mcap"
    write(path, messages, chunk_size=3000)
    data = path.read_bytes()
    expected = encoded(messages)
    previous = -1
    header_end = 8 + 9 + struct.unpack_from("<Q", data, 9)[0]
    boundaries = {header_end}
    position = header_end
    while data[position] != 0x0F:  # up to DataEnd; a cut summary loses no message
        position += 9 + struct.unpack_from("<Q", data, position + 1)[0]
        boundaries.add(position)
    boundaries.update(range(position, len(data)))
    for cut in np.linspace(header_end, len(data) - 1, 37).astype(int):
        cut_path = tmp_path / f"cut_{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        with pytest.raises(InputError, match="truncated"):
            ArchiveReader(cut_path)
        with ArchiveReader(cut_path, salvage=True) as reader:
            got = [(t, lt, cdr.encode(m)) for t, lt, m in reader.messages()]
            assert got == expected[: len(got)]  # whole chunks, never a damaged message
            assert len(got) >= previous
            previous = len(got)
            read = reader.skipped_bytes
            assert read < cut
            # Nothing skipped only when the cut falls between two records.
            assert (read == 0) == (cut in boundaries)
    assert previous == len(expected)  # a cut in the summary loses no message


def test_damaged_chunk_is_skipped_only_on_salvage(tmp_path: Path) -> None:
    messages = stream(400, seed=2)
    path = tmp_path / "rec.mcap"
    write(path, messages, chunk_size=4000)
    chunks = chunk_layout(path)
    assert len(chunks) >= 4
    offset, length, _ = chunks[1]
    data = bytearray(path.read_bytes())
    middle = offset + length // 2
    data[middle : middle + 16] = bytes(16)  # zeroed compressed bytes: bad zstd or bad CRC
    path.write_bytes(bytes(data))
    with (
        ArchiveReader(path) as reader,
        pytest.raises(InputError, match=r"rec\.mcap: damaged chunk at offset"),
    ):
        list(reader.messages())
    with ArchiveReader(path, salvage=True) as reader:
        got = [(t, lt, cdr.encode(m)) for t, lt, m in reader.messages()]
        assert reader.skipped_bytes == length
        assert any("damaged chunk" in w for w in reader.warnings)
    expected = encoded(messages)
    assert 0 < len(got) < len(expected)
    assert set(got) <= set(expected)
    assert got[0] == expected[0] and got[-1] == expected[-1]


def test_damaged_summary(tmp_path: Path) -> None:
    messages = stream(100, seed=3)
    path = tmp_path / "rec.mcap"
    write(path, messages)
    data = bytearray(path.read_bytes())
    # Point the footer's summary_start past the end of the file.
    footer = len(data) - 8 - 29
    struct.pack_into("<Q", data, footer + 9, len(data) - 10)
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"rec\.mcap: damaged MCAP summary"):
        ArchiveReader(path)
    with ArchiveReader(path, salvage=True) as reader:
        assert [(t, lt, cdr.encode(m)) for t, lt, m in reader.messages()] == encoded(messages)
        assert any("damaged summary" in w for w in reader.warnings)


def test_damaged_indexes_and_metadata(tmp_path: Path) -> None:
    messages = stream(100, seed=4)
    path = tmp_path / "rec.mcap"
    write(path, messages)
    good = path.read_bytes()
    (_, _, index_offsets), *_ = chunk_layout(path)
    with path.open("rb") as f:
        (metadata_index,) = make_reader(f).get_summary().metadata_indexes  # type: ignore[union-attr]

    data = bytearray(good)
    first_index = min(index_offsets.values())
    struct.pack_into("<H", data, first_index + 9, 99)  # a channel that does not exist
    path.write_bytes(bytes(data))
    with ArchiveReader(path) as reader, pytest.raises(InputError, match="unknown channel 99"):
        reader.topics()

    data = bytearray(good)
    struct.pack_into("<Q", data, first_index + 1, 2**40)  # index record length past the end
    path.write_bytes(bytes(data))
    with ArchiveReader(path) as reader, pytest.raises(InputError, match="damaged message index"):
        reader.topics()

    data = bytearray(good)
    data[metadata_index.offset] = 0x55  # no longer a Metadata record
    path.write_bytes(bytes(data))
    with ArchiveReader(path) as reader, pytest.raises(InputError, match="damaged metadata"):
        reader.metadata()
    with ArchiveReader(path, salvage=True) as reader:
        assert reader.metadata() == {}
        assert reader.skipped_bytes == metadata_index.length


def test_not_an_archive(tmp_path: Path) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("dive log\n")
    with pytest.raises(InputError, match=r"notes\.mcap: not an MCAP file \(expected magic"):
        ArchiveReader(text)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match=r"empty\.mcap: not an MCAP file .*an empty file"):
        ArchiveReader(empty)
    magic_only = tmp_path / "magic.mcap"
    magic_only.write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(InputError, match=r"magic\.mcap: truncated MCAP file \(no Header"):
        ArchiveReader(magic_only, salvage=True)
    cut_header = tmp_path / "cut_header.mcap"
    cut_header.write_bytes(b"\x89MCAP0\r\n\x01" + struct.pack("<Q", 100) + b"\x04\x00")
    with pytest.raises(InputError, match="Header record cut short"):
        ArchiveReader(cut_header, salvage=True)
    with pytest.raises(InputError, match=r"missing\.mcap: cannot open archive"):
        ArchiveReader(tmp_path / "missing.mcap")
    with pytest.raises(InputError, match="not an MCAP file"):
        list(iter_records_salvage(text))


def test_without_lz4_installed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "lz4.mcap"
    with ArchiveWriter(path, compression="lz4") as writer:
        writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="x"))
    monkeypatch.setitem(sys.modules, "lz4.frame", None)  # makes `import lz4.frame` fail
    with pytest.raises(InputError, match="lz4 package is not installed"):
        ArchiveWriter(tmp_path / "other.mcap", compression="lz4")
    with ArchiveReader(path) as reader, pytest.raises(InputError, match="lz4, which is not"):
        list(reader.messages())


def test_damaged_message_is_skipped_only_on_salvage(tmp_path: Path) -> None:
    """A message whose CDR is damaged (chunk intact) is skipped and reported on salvage."""
    path = tmp_path / "rec.mcap"
    messages = stream(40)
    bad_stamp = messages[5][1].stamp_ns
    with ArchiveWriter(path, metadata={"site": "wreck"}) as writer:
        for topic, message in messages:
            if message.stamp_ns == bad_stamp and topic == imu_topic(0):
                damaged = cdr.encode(message)[:20]  # cut short: the chunk itself is intact
                writer.write_cdr(topic, damaged, log_time_ns=bad_stamp)
            else:
                writer.write(topic, message)
    imu_count = sum(1 for topic, _ in messages if topic == imu_topic(0))
    with ArchiveReader(path) as reader, pytest.raises(InputError, match="truncated"):
        list(reader.messages())
    with ArchiveReader(path, salvage=True) as reader:
        kept = [m for t, _, m in reader.messages() if t == imu_topic(0)]
        series = reader.read_imu(imu_topic(0))
        assert len(kept) == imu_count - 1
        assert len(series.stamps_ns) == imu_count - 1
        assert bad_stamp not in set(series.stamps_ns.tolist())
        assert any("skipped a message" in w for w in reader.warnings)
