"""Archives read by independent readers: mcap's reader, rosbags (bare MCAP and rosbag2 bag)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

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
    video_topic,
    write_rosbag2_metadata,
)
from shared.archive.messages import ArchiveMessage
from shared.archive.writer import Engine
from shared.errors import InputError, OutputExistsError

T0 = 1_700_000_000_987_654_321


def session_messages(rng: np.random.Generator, t0: int = T0) -> list[tuple[str, ArchiveMessage]]:
    out: list[tuple[str, ArchiveMessage]] = []
    for i in range(50):
        out.append(
            (
                imu_topic(0),
                Imu(
                    stamp_ns=t0 + i * 5_000_000,
                    frame_id="imu0",
                    angular_velocity_rad_s=rng.normal(size=3),
                    linear_acceleration_m_s2=rng.normal(size=3),
                    angular_velocity_covariance=np.diag(rng.random(3)).reshape(-1),
                ),
            )
        )
    for i in range(5):
        out.append(
            (
                video_topic(0),
                CompressedVideo(
                    stamp_ns=t0 + i * 33_333_333 + 1,
                    frame_id="cam0",
                    format="h264",
                    data=b"\x00\x00\x00\x01\x67" + rng.bytes(100 + 7 * i),
                ),
            )
        )
        out.append(
            (
                image_topic(0),
                CompressedImage(
                    stamp_ns=t0 + i * 40_000_000 + 2,
                    frame_id="cam0",
                    format="jpeg",
                    data=b"\xff\xd8" + rng.bytes(50 + i),
                ),
            )
        )
        out.append(
            (
                depth_topic(0),
                DepthSample(
                    stamp_ns=t0 + i * 1_000_000_000 + 3,
                    frame_id="perdix",
                    depth_m=12.3 + i / 7,
                    pressure_pa=float("nan") if i % 2 else 2.2e5 + i,
                    temperature_c=18.0 - i / 3,
                ),
            )
        )
    out.append((SESSION_TOPIC, SessionInfo(stamp_ns=t0 + 4, yaml_text="id: abc\nsite: x\n")))
    out.append(
        (
            HEALTH_TOPIC,
            RecorderEvent(
                stamp_ns=t0 + 5, frame_id="sim", kind="clock_step", yaml_text="step_s: 3\n"
            ),
        )
    )
    return out


def write(path: Path, messages: list[tuple[str, ArchiveMessage]], engine: Engine = "mcap") -> None:
    with ArchiveWriter(
        path, chunk_size=4000, metadata={"session_id": "abc"}, engine=engine
    ) as writer:
        for topic, message in messages:
            writer.write(topic, message)


def f64(value: float) -> bytes:
    return np.float64(value).tobytes()


@pytest.mark.parametrize("engine", ["mcap", "wreckmap"])
def test_mcap_library_reads_our_archive(tmp_path: Path, engine: Engine) -> None:
    messages = session_messages(np.random.default_rng(1))
    path = tmp_path / "rec.mcap"
    write(path, messages, engine)
    with path.open("rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(messages)
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count > 1
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert (channel.message_encoding, schema.encoding) == ("cdr", "ros2msg")
            assert schema.data.decode() == cdr.schema_text(
                next(type(m) for t, m in messages if t == channel.topic)
            )
        got = [
            (channel.topic, message.log_time, cdr.decode(schema.name, message.data))
            for schema, channel, message in reader.iter_messages(log_time_order=True)
            if schema is not None
        ]
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {
            "wreckmap_session": {"session_id": "abc"}
        }
    with ArchiveReader(path) as ours:
        mine = list(ours.messages())
    # Both in log-time order; messages with equal log times may come in either order.
    assert [lt for _, lt, _ in got] == [lt for _, lt, _ in mine]
    assert sorted((lt, t, cdr.encode(m)) for t, lt, m in got) == sorted(
        (lt, t, cdr.encode(m)) for t, lt, m in mine
    )


def check_rosbags_message(msg: Any, expected: ArchiveMessage) -> None:
    """Compare a rosbags-deserialized message with the dataclass written, bit for bit."""
    stamp = msg.timestamp if isinstance(expected, CompressedVideo) else msg.header.stamp
    assert stamp.sec * 1_000_000_000 + stamp.nanosec == expected.stamp_ns
    if isinstance(expected, Imu):
        assert msg.header.frame_id == expected.frame_id
        av, la = msg.angular_velocity, msg.linear_acceleration
        assert np.array([av.x, av.y, av.z]).tobytes() == expected.angular_velocity_rad_s.tobytes()
        assert np.array([la.x, la.y, la.z]).tobytes() == expected.linear_acceleration_m_s2.tobytes()
        assert msg.orientation_covariance[0] == -1.0  # ROS: orientation not estimated
        assert expected.angular_velocity_covariance is not None
        assert (
            msg.angular_velocity_covariance.tobytes()
            == expected.angular_velocity_covariance.tobytes()
        )
        assert not msg.linear_acceleration_covariance.any()
    elif isinstance(expected, CompressedImage):
        assert (msg.header.frame_id, msg.format) == (expected.frame_id, expected.format)
        assert msg.data.tobytes() == expected.data
    elif isinstance(expected, CompressedVideo):
        assert (msg.frame_id, msg.format) == (expected.frame_id, expected.format)
        assert msg.data.tobytes() == expected.data
    elif isinstance(expected, DepthSample):
        assert msg.header.frame_id == expected.frame_id
        for name in ("depth_m", "pressure_pa", "temperature_c"):
            assert f64(getattr(msg, name)) == f64(getattr(expected, name))
        assert math.isnan(msg.pressure_pa) == math.isnan(expected.pressure_pa)
    elif isinstance(expected, RecorderEvent):
        assert (msg.header.frame_id, msg.kind) == (expected.frame_id, expected.kind)
        assert msg.yaml_text == expected.yaml_text
    else:
        assert msg.header.frame_id == ""
        assert msg.yaml_text == expected.yaml_text


def read_with_rosbags(paths: list[Path]) -> list[tuple[str, int, Any]]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # An empty type store: every type (standard and custom) comes from the file's schemas.
    with AnyReader(paths, default_typestore=get_typestore(Stores.EMPTY)) as reader:
        return [
            (conn.topic, log_time, reader.deserialize(raw, conn.msgtype))
            for conn, log_time, raw in reader.messages()
        ]


@pytest.mark.parametrize("engine", ["mcap", "wreckmap"])
def test_rosbags_reads_bare_mcap(tmp_path: Path, engine: Engine) -> None:
    messages = session_messages(np.random.default_rng(2))
    path = tmp_path / "rec.mcap"
    write(path, messages, engine)
    got = read_with_rosbags([path])
    expected = sorted(messages, key=lambda tm: tm[1].stamp_ns)
    assert sorted((t, lt) for t, lt, _ in got) == sorted((t, m.stamp_ns) for t, m in messages)
    by_key = {(t, m.stamp_ns): m for t, m in expected}
    for topic, log_time, msg in got:
        check_rosbags_message(msg, by_key[(topic, log_time)])


def test_rosbags_types_from_our_msg_text() -> None:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    for kind in (DepthSample, SessionInfo, RecorderEvent):
        store.register(get_types_from_msg(cdr.schema_text(kind), kind.ROS_TYPE_NAME))
    sample = DepthSample(stamp_ns=T0, frame_id="d", depth_m=1.25, pressure_pa=1.5e5)
    msg: Any = store.deserialize_cdr(cdr.encode(sample), DepthSample.ROS_TYPE_NAME)
    check_rosbags_message(msg, sample)
    # ...and the other way: rosbags serializes the same bytes as we do.
    assert store.serialize_cdr(msg, msg.__msgtype__) == cdr.encode(sample)


def test_session_folder_is_a_rosbag2_bag(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader

    rng = np.random.default_rng(3)
    folder = tmp_path / "session"
    first = session_messages(rng)
    second = session_messages(rng, t0=T0 + 10_000_000_000)
    write(folder / "recording_000.mcap", first)
    write(folder / "recording_001.mcap", second)
    (folder / "recording_002.mcap.part").write_bytes(b"crashed")
    metadata_path = write_rosbag2_metadata(folder)
    info = yaml.safe_load(metadata_path.read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == ["recording_000.mcap", "recording_001.mcap"]
    assert info["message_count"] == len(first) + len(second)
    with Reader(folder) as bag:
        assert bag.message_count == len(first) + len(second)
        assert bag.start_time == T0
        topics = {c.topic: (c.msgtype, c.msgcount) for c in bag.connections}
        assert topics[imu_topic(0)] == ("sensor_msgs/msg/Imu", 100)
        assert topics[SESSION_TOPIC] == ("wreckmap_msgs/msg/SessionInfo", 2)
    got = read_with_rosbags([folder])
    everything = first + second
    assert len(got) == len(everything)
    by_key = {(t, m.stamp_ns): m for t, m in everything}
    for topic, log_time, msg in got:
        check_rosbags_message(msg, by_key[(topic, log_time)])

    with pytest.raises(OutputExistsError, match=r"metadata\.yaml: already exists"):
        write_rosbag2_metadata(folder)
    write_rosbag2_metadata(folder, files=[folder / "recording_001.mcap"], overwrite=True)
    with Reader(folder) as bag:
        assert bag.message_count == len(second)


def test_rosbag2_metadata_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"no \.mcap file"):
        write_rosbag2_metadata(tmp_path)
    elsewhere = tmp_path / "other" / "x.mcap"
    write(elsewhere, session_messages(np.random.default_rng(4))[:3])
    with pytest.raises(InputError, match="not inside"):
        write_rosbag2_metadata(tmp_path, files=[elsewhere])
    # A topic that changes type between files (not something ArchiveWriter can write).
    folder = tmp_path / "mixed"
    write(folder / "a.mcap", session_messages(np.random.default_rng(5))[:2])
    with (folder / "b.mcap").open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2")
        schema = writer.register_schema(
            "sensor_msgs/msg/CompressedImage", "ros2msg", cdr.schema_text(CompressedImage).encode()
        )
        channel = writer.register_channel(imu_topic(0), "cdr", schema)
        data = cdr.encode(CompressedImage(stamp_ns=T0, frame_id="c", format="jpeg", data=b"x"))
        writer.add_message(channel, T0, data, T0)
        writer.finish()
    with pytest.raises(InputError, match="holds sensor_msgs/msg/CompressedImage"):
        write_rosbag2_metadata(folder)


@pytest.mark.parametrize(
    "options",
    [
        {"use_chunking": False},  # top-level messages, no chunk index
        {
            "index_types": IndexType.NONE,
            "repeat_channels": False,
            "repeat_schemas": False,
            "use_statistics": False,
            "use_summary_offsets": False,
        },  # chunks but no summary at all
        {"compression": CompressionType.LZ4, "chunk_size": 500},
        {"index_types": IndexType.NONE, "use_statistics": False},  # summary without chunk index
    ],
)
def test_reads_files_written_by_the_mcap_library(tmp_path: Path, options: dict[str, Any]) -> None:
    messages = session_messages(np.random.default_rng(6))
    path = tmp_path / "theirs.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream, **options)
        writer.start(profile="ros2")
        channels: dict[str, int] = {}
        for topic, message in messages:
            if topic not in channels:
                schema = writer.register_schema(
                    message.ROS_TYPE_NAME, "ros2msg", cdr.schema_text(type(message)).encode()
                )
                channels[topic] = writer.register_channel(topic, "cdr", schema)
            writer.add_message(channels[topic], message.stamp_ns, cdr.encode(message), 0)
        writer.add_metadata("m", {"k": "v"})
        writer.finish()
    with ArchiveReader(path) as reader:
        got = list(reader.messages())
        assert reader.metadata() == {"m": {"k": "v"}}
        assert reader.topics()[imu_topic(0)].message_count == 50
        assert reader.read_imu().stamps_ns.tolist() == [
            m.stamp_ns for t, m in messages if t == imu_topic(0)
        ]
        assert reader.warnings == []
    expected = sorted(messages, key=lambda tm: tm[1].stamp_ns)
    assert [lt for _, lt, _ in got] == [m.stamp_ns for _, m in expected]
    assert sorted(cdr.encode(m) for _, _, m in got) == sorted(cdr.encode(m) for _, m in messages)


def test_foreign_types_are_skipped_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "foreign.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2")
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
        channel = writer.register_channel("/chatter", "cdr", schema)
        writer.add_message(channel, T0, b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00", T0)
        session = writer.register_schema(
            SessionInfo.ROS_TYPE_NAME, "ros2msg", cdr.schema_text(SessionInfo).encode()
        )
        session_channel = writer.register_channel(SESSION_TOPIC, "cdr", session)
        writer.add_message(
            session_channel, T0, cdr.encode(SessionInfo(stamp_ns=T0, yaml_text="a")), T0
        )
        writer.finish()
    with ArchiveReader(path) as reader:
        assert [t for t, _, _ in reader.messages()] == [SESSION_TOPIC]
        assert any("'/chatter' skipped" in w for w in reader.warnings)
        assert [r.schema_name for r in reader.raw_messages()] == [
            "std_msgs/msg/String",
            SessionInfo.ROS_TYPE_NAME,
        ]
