"""Both record writers of ArchiveWriter (the mcap package and our own), what the mcap
package's reader and mcap-ros2-support make of their files, and why salvage stays ours."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap_ros2.decoder import DecoderFactory
from zstandard import ZstdError

from shared.archive import (
    HEALTH_TOPIC,
    SESSION_TOPIC,
    ArchiveReader,
    ArchiveWriter,
    CompressedImage,
    CompressedVideo,
    DepthSample,
    Imu,
    RecorderEvent,
    SessionInfo,
    cdr,
    depth_topic,
    image_topic,
    imu_topic,
    part_path,
    video_topic,
)
from shared.archive.messages import ArchiveMessage
from shared.archive.writer import Engine
from shared.errors import InputError

T0 = 1_700_000_000_555_000_111
ENGINES: list[Engine] = ["mcap", "wreckmap"]


def session(seed: int, imu_count: int = 300) -> list[tuple[str, ArchiveMessage]]:
    """Every message type, IMU at 200 Hz, shuffled a little (out-of-order host times)."""
    rng = np.random.default_rng(seed)
    out: list[tuple[str, ArchiveMessage]] = [
        (SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="id: s1\nsite: wreck\n"))
    ]
    for i in range(imu_count):
        out.append(
            (
                imu_topic(0),
                Imu(
                    stamp_ns=T0 + i * 5_000_000 + int(rng.integers(0, 1000)),
                    frame_id="imu0",
                    angular_velocity_rad_s=rng.normal(size=3),
                    linear_acceleration_m_s2=rng.normal(size=3) * 9.81,
                ),
            )
        )
        if i % 6 == 0:
            out.append(
                (
                    video_topic(0),
                    CompressedVideo(
                        stamp_ns=T0 + i * 5_000_000 + 1,
                        frame_id="cam0",
                        format="h264",
                        data=b"\x00\x00\x00\x01\x65" + rng.bytes(int(rng.integers(50, 900))),
                    ),
                )
            )
        if i % 40 == 0:
            out.append(
                (
                    image_topic(1),
                    CompressedImage(
                        stamp_ns=T0 + i * 5_000_000 + 2,
                        frame_id="cam1",
                        format="jpeg",
                        data=b"\xff\xd8" + rng.bytes(200),
                    ),
                )
            )
            out.append(
                (
                    depth_topic(0),
                    DepthSample(
                        stamp_ns=T0 + i * 5_000_000 + 3,
                        frame_id="perdix",
                        depth_m=10.0 + i / 100,
                        pressure_pa=2.0e5 + i,
                        temperature_c=19.5,
                    ),
                )
            )
    out.append(
        (
            HEALTH_TOPIC,
            RecorderEvent(stamp_ns=T0 + 7, frame_id="sim", kind="disk", yaml_text="free_mb: 9\n"),
        )
    )
    # Shuffled within blocks of 17: chunks overlap in time, as threads make them.
    shuffled: list[tuple[str, ArchiveMessage]] = []
    for start in range(0, len(out), 17):
        block = out[start : start + 17]
        shuffled += [block[k] for k in rng.permutation(len(block))]
    return shuffled


def write(
    path: Path, messages: list[tuple[str, ArchiveMessage]], engine: Engine, **options: Any
) -> None:
    with ArchiveWriter(path, engine=engine, metadata={"site": "wreck"}, **options) as writer:
        writer.add_metadata("clocks", {"imu": "device"})
        for topic, message in messages:
            writer.write(topic, message)


def by_time(
    messages: list[tuple[str, ArchiveMessage]],
) -> list[tuple[str, int, bytes]]:
    return sorted(((t, m.stamp_ns, cdr.encode(m)) for t, m in messages), key=lambda x: x[1])


def chunk_records(path: Path) -> list[list[Any]]:
    """The records inside each chunk, in file order, parsed by the mcap package."""
    with path.open("rb") as stream:
        records = list(StreamReader(stream, emit_chunks=True).records)
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk

    return [breakup_chunk(r, validate_crc=True) for r in records if isinstance(r, Chunk)]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_each_engine_round_trips_through_both_readers(
    tmp_path: Path, engine: Engine, compression: str
) -> None:
    messages = session(1)
    path = tmp_path / "rec.mcap"
    write(path, messages, engine, chunk_size=3000, compression=compression)
    expected = by_time(messages)
    with ArchiveReader(path) as reader:
        assert reader.indexed and reader.warnings == []
        ours = [(t, lt, cdr.encode(m)) for t, lt, m in reader.messages()]
        assert reader.metadata() == {
            "wreckmap_session": {"site": "wreck"},
            "clocks": {"imu": "device"},
        }
        assert reader.topics()[imu_topic(0)].message_count == 300
        library = reader.library
    with path.open("rb") as stream:
        mcap_reader = make_reader(stream, validate_crcs=True)
        summary = mcap_reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(messages)
        assert summary.statistics.chunk_count == len(summary.chunk_indexes) > 5
        assert {c.compression for c in summary.chunk_indexes} == {
            "" if compression == "none" else compression
        }
        theirs = [
            (channel.topic, message.log_time, message.data)
            for _, channel, message in mcap_reader.iter_messages(log_time_order=True)
        ]
    # Log-time order: equal times may come in either order, so compare the times, then sets.
    assert [lt for _, lt, _ in ours] == [lt for _, lt, _ in expected] == [lt for _, lt, _ in theirs]
    assert sorted(ours) == sorted(expected) == sorted(theirs)
    assert library.startswith("wreckmap-archive/1")
    assert ("mcap-python/" in library) == (engine == "mcap")


def test_both_engines_store_the_same_records(tmp_path: Path) -> None:
    messages = session(2)
    files = {}
    for engine in ENGINES:
        files[engine] = tmp_path / f"{engine}.mcap"
        write(files[engine], messages, engine, chunk_size=5000)
    read = {}
    for engine, path in files.items():
        with ArchiveReader(path) as reader:
            read[engine] = (
                sorted(
                    (r.topic, r.log_time_ns, r.schema_name, r.data) for r in reader.raw_messages()
                ),
                reader.topics(),
                reader.time_span_ns(),
                reader.metadata(),
            )
    assert read["mcap"] == read["wreckmap"]
    # Same chunking rule (uncompressed bytes), so about the same number of chunks.
    counts = [len(chunk_records(path)) for path in files.values()]
    assert abs(counts[0] - counts[1]) <= 1


@pytest.mark.parametrize("engine", ENGINES)
def test_every_chunk_defines_the_channels_it_uses(tmp_path: Path, engine: Engine) -> None:
    path = tmp_path / "rec.mcap"
    write(path, session(3), engine, chunk_size=2000)
    chunks = chunk_records(path)
    assert len(chunks) > 10
    for records in chunks:
        schemas = {r.id for r in records if isinstance(r, Schema)}
        channels = {r.id: r.schema_id for r in records if isinstance(r, Channel)}
        used = {r.channel_id for r in records if isinstance(r, Message)}
        assert used and used <= set(channels)
        assert {channels[c] for c in used} <= schemas
        # Each definition once per chunk, and before the first message that needs it.
        assert sum(isinstance(r, Channel) for r in records) == len(channels)
        assert sum(isinstance(r, Schema) for r in records) == len(schemas)
        defined: set[tuple[str, int]] = set()
        for r in records:
            if isinstance(r, Schema):
                defined.add(("schema", r.id))
            elif isinstance(r, Channel):
                assert ("schema", r.schema_id) in defined
                defined.add(("channel", r.id))
            elif isinstance(r, Message):
                assert ("channel", r.channel_id) in defined


@pytest.mark.parametrize("engine", ENGINES)
def test_a_crashed_recording_with_its_first_chunk_lost_keeps_the_rest(
    tmp_path: Path, engine: Engine
) -> None:
    """No summary (crash) and the chunk that first defined the channels is damaged: the
    later chunks still decode, because each one repeats its schemas and channels."""
    messages = session(4)
    path = tmp_path / "recording.mcap"
    crashed = tmp_path / "crashed.mcap.part"
    with ArchiveWriter(path, engine=engine, chunk_size=3000) as writer:
        for topic, message in messages:
            writer.write(topic, message)
        writer.flush(fsync=True)
        shutil.copy(part_path(path), crashed)
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    first = summary.chunk_indexes[0]
    data = bytearray(crashed.read_bytes())
    middle = first.chunk_start_offset + first.chunk_length // 2
    data[middle : middle + 8] = bytes(8)
    crashed.write_bytes(bytes(data))
    with ArchiveReader(crashed, salvage=True) as reader:
        got = [(t, lt, cdr.encode(m)) for t, lt, m in reader.messages()]
        assert reader.skipped_bytes == first.chunk_length
    expected = by_time(messages)
    lost = sum(summary.statistics.channel_message_counts.values()) - len(got)  # type: ignore[union-attr]
    assert 0 < lost < len(expected) // 5
    assert set(got) < set(expected)
    assert got[-1] == expected[-1]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("bad", [-1, 2**64, "12", 1.5])
def test_a_bad_log_time_is_refused_before_anything_is_written(
    tmp_path: Path, engine: Engine, bad: object
) -> None:
    path = tmp_path / "rec.mcap"
    with ArchiveWriter(path, engine=engine) as writer:
        writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="a"))
        with pytest.raises(InputError, match=r"log time .* ns is not a uint64"):
            writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="b"), log_time_ns=bad)  # type: ignore[arg-type]
        writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0 + 1, yaml_text="c"))
        assert writer.messages_written == {SESSION_TOPIC: 2}
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 2
    assert (summary.statistics.message_start_time, summary.statistics.message_end_time) == (
        T0,
        T0 + 1,
    )
    with ArchiveReader(path) as reader:
        assert [m.yaml_text for _, _, m in reader.messages()] == ["a", "c"]  # type: ignore[union-attr]


def test_numpy_integer_log_times_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    log_time: Any = np.int64(T0 + 5)  # what a caller holding numpy stamps passes
    with ArchiveWriter(path) as writer:
        writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="a"), log_time_ns=log_time)
    with ArchiveReader(path) as reader:
        assert [lt for _, lt, _ in reader.messages()] == [T0 + 5]


@pytest.mark.parametrize("engine", ENGINES)
def test_bytes_written_follows_the_file(tmp_path: Path, engine: Engine) -> None:
    path = tmp_path / "rec.mcap"
    writer = ArchiveWriter(path, engine=engine, chunk_size=2000)
    sizes = []
    for topic, message in session(7, imu_count=100):
        writer.write(topic, message)
        sizes.append(writer.bytes_written)
    writer.flush()
    on_disk = part_path(path).stat().st_size
    assert writer.bytes_written == on_disk  # nothing pending after a flush
    assert sizes[0] < sizes[len(sizes) // 2] < sizes[-1] <= on_disk + 2000
    writer.close()
    assert writer.bytes_written == path.stat().st_size > on_disk  # summary on top


def test_unknown_engine(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="engine 'rosbag': expected 'mcap' or 'wreckmap'"):
        ArchiveWriter(tmp_path / "a.mcap", engine="rosbag")  # type: ignore[arg-type]
    assert not part_path(tmp_path / "a.mcap").exists()


def ros2_fields(message: ArchiveMessage) -> dict[str, Any]:
    """What mcap-ros2-support should decode from `message`, field by field."""
    sec, nanosec = divmod(message.stamp_ns, 1_000_000_000)
    if isinstance(message, CompressedVideo):
        return {
            "timestamp": (sec, nanosec),
            "frame_id": message.frame_id,
            "format": message.format,
            "data": message.data,
        }
    fields: dict[str, Any] = {"header": (sec, nanosec, getattr(message, "frame_id", ""))}
    if isinstance(message, Imu):
        fields["angular_velocity"] = tuple(message.angular_velocity_rad_s.tolist())
        fields["linear_acceleration"] = tuple(message.linear_acceleration_m_s2.tolist())
    elif isinstance(message, CompressedImage):
        fields.update(format=message.format, data=message.data)
    elif isinstance(message, DepthSample):
        fields.update(
            depth_m=message.depth_m,
            pressure_pa=message.pressure_pa,
            temperature_c=message.temperature_c,
        )
    elif isinstance(message, RecorderEvent):
        fields.update(kind=message.kind, yaml_text=message.yaml_text)
    else:
        assert isinstance(message, SessionInfo)
        fields["yaml_text"] = message.yaml_text
    return fields


def decoded_fields(message: Any, like: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in like:
        if name == "header":
            h = message.header
            out[name] = (h.stamp.sec, h.stamp.nanosec, h.frame_id)
        elif name == "timestamp":
            out[name] = (message.timestamp.sec, message.timestamp.nanosec)
        elif name in ("angular_velocity", "linear_acceleration"):
            v = getattr(message, name)
            out[name] = (v.x, v.y, v.z)
        elif name == "data":
            out[name] = bytes(message.data)
        else:
            out[name] = getattr(message, name)
    return out


@pytest.mark.parametrize("engine", ENGINES)
def test_mcap_ros2_support_decodes_our_archive_from_its_own_schemas(
    tmp_path: Path, engine: Engine
) -> None:
    """An independent CDR decoder, built from the .msg text stored in the file."""
    messages = session(5, imu_count=60)
    path = tmp_path / "rec.mcap"
    write(path, messages, engine, chunk_size=4000)
    expected = {(t, m.stamp_ns): ros2_fields(m) for t, m in messages}
    seen = set()
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages():
            key = (channel.topic, message.log_time)
            assert decoded_fields(decoded, expected[key]) == expected[key]
            seen.add(key)
    assert seen == set(expected)


def test_the_mcap_package_cannot_salvage_a_truncated_recording(tmp_path: Path) -> None:
    """Why the salvage path stays ours: with the footer and summary missing, mcap 1.6's
    readers give back nothing (in log-time order) or stop at the cut with an error, and a
    damaged chunk ends the read; ours returns every complete chunk and goes past it.
    When an mcap release can do this, this test fails: then our salvage path can go."""
    messages = session(6)
    path = tmp_path / "rec.mcap"
    write(path, messages, "mcap", chunk_size=3000)
    data = path.read_bytes()
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    cut = tmp_path / "cut.mcap.part"
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    cut.write_bytes(data[: chunk.chunk_start_offset + chunk.chunk_length // 2])

    with cut.open("rb") as stream, pytest.raises((McapError, struct.error)):
        list(make_reader(stream).iter_messages())
    with cut.open("rb") as stream, pytest.raises(McapError):
        list(NonSeekingReader(stream).iter_messages(log_time_order=True))
    in_file_order = 0
    with cut.open("rb") as stream, pytest.raises(McapError):
        for _ in NonSeekingReader(stream).iter_messages(log_time_order=False):
            in_file_order += 1

    with ArchiveReader(cut, salvage=True) as reader:
        salvaged = list(reader.messages())
    assert in_file_order == len(salvaged) > len(messages) // 3

    # A damaged chunk in the middle of a file without summary: mcap stops there.
    damaged = tmp_path / "damaged.mcap.part"
    second = summary.chunk_indexes[1]
    broken = bytearray(data[: chunk.chunk_start_offset + chunk.chunk_length // 2])
    middle = second.chunk_start_offset + second.chunk_length // 2
    broken[middle : middle + 8] = bytes(8)
    damaged.write_bytes(bytes(broken))
    before_damage = 0
    with damaged.open("rb") as stream, pytest.raises((McapError, CRCValidationError, ZstdError)):
        for _ in NonSeekingReader(stream, validate_crcs=True).iter_messages(log_time_order=False):
            before_damage += 1
    with ArchiveReader(damaged, salvage=True) as reader:
        past_damage = list(reader.messages())
    assert before_damage < len(past_damage) < len(salvaged)
