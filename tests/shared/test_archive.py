"""Archive messages, CDR codec, topic registry, ArchiveWriter and ArchiveReader round trips."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

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
    message_type_for_topic,
    part_path,
    video_topic,
)
from shared.archive.messages import ArchiveMessage
from shared.errors import InputError, OutputExistsError, WreckmapError

T0 = 1_700_000_000_123_456_789

# Floats that a lossy or text path would change: NaN payload, -0.0, subnormal, inf, pi.
AWKWARD = [float("nan"), -0.0, 5e-324, float("inf"), math.pi, -1.0e300]


def bits(values: object) -> bytes:
    return np.asarray(values, dtype="<f8").tobytes()


def make_imu(i: int, rng: np.random.Generator, frame_id: str = "imu0") -> Imu:
    return Imu(
        stamp_ns=T0 + i * 5_000_000 + int(rng.integers(0, 1000)),
        frame_id=frame_id,
        angular_velocity_rad_s=rng.normal(size=3),
        linear_acceleration_m_s2=rng.normal(size=3) * 9.81,
    )


def same(a: ArchiveMessage, b: ArchiveMessage) -> bool:
    """Bit-exact comparison of two archive messages (floats by their bytes)."""
    if type(a) is not type(b) or a.stamp_ns != b.stamp_ns:
        return False
    if isinstance(a, Imu):
        assert isinstance(b, Imu)
        return (
            a.frame_id == b.frame_id
            and bits(a.angular_velocity_rad_s) == bits(b.angular_velocity_rad_s)
            and bits(a.linear_acceleration_m_s2) == bits(b.linear_acceleration_m_s2)
        )
    if isinstance(a, DepthSample):
        assert isinstance(b, DepthSample)
        return a.frame_id == b.frame_id and bits(
            [a.depth_m, a.pressure_pa, a.temperature_c]
        ) == bits([b.depth_m, b.pressure_pa, b.temperature_c])
    return a == b


def sample_messages(rng: np.random.Generator) -> list[tuple[str, ArchiveMessage]]:
    """A small session: IMU at 200 Hz, video, stills, depth and the session text."""
    out: list[tuple[str, ArchiveMessage]] = []
    for i in range(400):
        out.append((imu_topic(0), make_imu(i, rng)))
    for i in range(12):
        out.append(
            (
                video_topic(0),
                CompressedVideo(
                    stamp_ns=T0 + i * 33_333_333,
                    frame_id="cam0",
                    format="h264" if i % 2 else "h265",
                    data=b"\x00\x00\x00\x01" + rng.bytes(int(rng.integers(0, 3000))),
                ),
            )
        )
    for i in range(3):
        out.append(
            (
                image_topic(1),
                CompressedImage(
                    stamp_ns=T0 + i * 500_000_000,
                    frame_id="cam1_optical",
                    format="jpeg",
                    data=b"\xff\xd8" + rng.bytes(1001 + i),
                ),
            )
        )
    for i, value in enumerate(AWKWARD):
        out.append(
            (
                depth_topic(0),
                DepthSample(
                    stamp_ns=T0 + i * 1_000_000_000,
                    frame_id="petrel",
                    depth_m=value,
                    pressure_pa=101325.0 + i,
                    temperature_c=float("nan"),
                ),
            )
        )
    out.append((SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="id: s1\nsite: Épave ü\n")))
    out.append(
        (
            HEALTH_TOPIC,
            RecorderEvent(
                stamp_ns=T0 + 7, frame_id="oak0", kind="source_back", yaml_text="gap_s: 2.5\n"
            ),
        )
    )
    return out


# -- CDR codec ---------------------------------------------------------------


@pytest.mark.parametrize("index", range(6))
def test_cdr_round_trip_each_type_bit_exact(index: int) -> None:
    rng = np.random.default_rng(index)
    messages = [m for _, m in sample_messages(rng)]
    kinds = [Imu, CompressedVideo, CompressedImage, DepthSample, SessionInfo, RecorderEvent]
    assert any(type(m) is kinds[index] for m in messages)
    for message in (m for m in messages if type(m) is kinds[index]):
        data = cdr.encode(message)
        assert data[:4] == b"\x00\x01\x00\x00"
        assert same(cdr.decode(message.ROS_TYPE_NAME, data), message)


def test_imu_layout_matches_cdr_rules() -> None:
    # Layout derived by hand from the CDR rules: header, Time, string "ab\0",
    # padding to 8 (relative to the payload), then 37 float64.
    message = Imu(
        stamp_ns=-1_500_000_000,  # pre-epoch: sec -2, nanosec 5e8
        frame_id="ab",
        angular_velocity_rad_s=np.array([1.0, 2.0, 3.0]),
        linear_acceleration_m_s2=np.array([4.0, 5.0, 6.0]),
        angular_velocity_covariance=np.arange(9.0),
    )
    payload = struct.pack("<iII", -2, 500_000_000, 3) + b"ab\x00"  # 15 bytes
    payload += b"\x00"  # to 16
    doubles = [0, 0, 0, 1, -1] + [0] * 8 + [1, 2, 3, *range(9), 4, 5, 6] + [0] * 9
    expected = b"\x00\x01\x00\x00" + payload + struct.pack("<37d", *doubles)
    assert cdr.encode(message) == expected
    decoded = cdr.decode_imu(expected)
    assert decoded.stamp_ns == -1_500_000_000
    assert bits(decoded.angular_velocity_covariance) == bits(np.arange(9.0))


def test_strings_and_sequences_align_to_four() -> None:
    message = CompressedVideo(stamp_ns=T0, frame_id="c", format="h264", data=b"\x01\x02\x03")
    sec, nanosec = divmod(T0, 1_000_000_000)
    payload = struct.pack("<iII", sec, nanosec, 2) + b"c\x00"  # 14 -> pad to 16
    payload += b"\x00\x00" + struct.pack("<I", 3) + b"\x01\x02\x03"  # 23 -> pad to 24
    payload += b"\x00" + struct.pack("<I", 5) + b"h264\x00"
    assert cdr.encode(message) == b"\x00\x01\x00\x00" + payload


def test_imu_batch_decode_matches_single_decode() -> None:
    rng = np.random.default_rng(3)
    messages = [make_imu(i, rng, frame_id="imu" + "x" * (i % 3)) for i in range(60)]
    payloads = [cdr.encode(m) for m in messages]
    batch = cdr.decode_imu_batch(payloads)
    for i, message in enumerate(messages):
        assert batch.stamps_ns[i] == message.stamp_ns
        assert bits(batch.gyro_rad_s[i]) == bits(message.angular_velocity_rad_s)
        assert bits(batch.accel_m_s2[i]) == bits(message.linear_acceleration_m_s2)
    with pytest.raises(InputError, match="truncated"):
        cdr.decode_imu_batch([b"\x00\x01\x00\x00abc"])


def test_cdr_errors() -> None:
    with pytest.raises(InputError, match="not little-endian CDR"):
        cdr.decode(Imu.ROS_TYPE_NAME, b"\x00\x00\x00\x00" + bytes(300))
    good = cdr.encode(make_imu(0, np.random.default_rng(0)))
    with pytest.raises(InputError, match="truncated"):
        cdr.decode(Imu.ROS_TYPE_NAME, good[:-8])
    with pytest.raises(InputError, match="unknown schema"):
        cdr.decode("std_msgs/msg/String", good)
    bad_utf8 = cdr.encode(SessionInfo(stamp_ns=0, yaml_text="ab"))[:-3] + b"\xff\xfe\x00"
    with pytest.raises(InputError, match="UTF-8"):
        cdr.decode(SessionInfo.ROS_TYPE_NAME, bad_utf8)
    with pytest.raises(InputError, match="int32 seconds"):
        cdr.encode(SessionInfo(stamp_ns=2**31 * 1_000_000_000, yaml_text=""))
    with pytest.raises(InputError, match="expected 3 values"):
        cdr.encode(
            Imu(
                stamp_ns=0,
                frame_id="i",
                angular_velocity_rad_s=np.zeros(4),
                linear_acceleration_m_s2=np.zeros(3),
            )
        )
    with pytest.raises(InputError, match="expected 9 values"):
        cdr.encode(
            Imu(
                stamp_ns=0,
                frame_id="i",
                angular_velocity_rad_s=np.zeros(3),
                linear_acceleration_m_s2=np.zeros(3),
                linear_acceleration_covariance=np.zeros(3),
            )
        )
    with pytest.raises(InputError, match="not an archive message"):
        cdr.encode("hello")  # type: ignore[arg-type]


def test_schema_text_concatenates_dependencies() -> None:
    text = cdr.schema_text(Imu)
    sections = text.split("=" * 80 + "\n")
    assert sections[0].startswith("std_msgs/Header header\n")
    names = [s.splitlines()[0] for s in sections[1:]]
    assert names == [
        "MSG: std_msgs/Header",
        "MSG: builtin_interfaces/Time",
        "MSG: geometry_msgs/Quaternion",
        "MSG: geometry_msgs/Vector3",
    ]
    assert "MSG: std_msgs/Header" in cdr.schema_text(DepthSample)
    assert cdr.schema_text(CompressedVideo).startswith("builtin_interfaces/Time timestamp\n")


# -- topic registry ----------------------------------------------------------


def test_topic_registry() -> None:
    assert video_topic() == "/cam0/video"
    assert image_topic(2) == "/cam2/image"
    assert imu_topic(1) == "/imu1"
    assert depth_topic(0) == "/depth0"
    assert message_type_for_topic("/cam3/video") is CompressedVideo
    assert message_type_for_topic("/cam0/image") is CompressedImage
    assert message_type_for_topic("/imu12") is Imu
    assert message_type_for_topic("/depth0") is DepthSample
    assert message_type_for_topic(SESSION_TOPIC) is SessionInfo
    assert message_type_for_topic(HEALTH_TOPIC) is RecorderEvent
    for bad in ("/imu", "/cam0", "/cam0/video/x", "imu0", "/gps0", "/sessionx"):
        with pytest.raises(InputError, match="not an archive topic"):
            message_type_for_topic(bad)
    with pytest.raises(InputError, match="expected an integer >= 0"):
        imu_topic(-1)


# -- writer and reader -------------------------------------------------------


def write_all(path: Path, messages: list[tuple[str, ArchiveMessage]], **options: object) -> None:
    with ArchiveWriter(path, **options) as writer:  # type: ignore[arg-type]
        for topic, message in messages:
            writer.write(topic, message)


def in_log_order(
    messages: list[tuple[str, ArchiveMessage]],
) -> list[tuple[str, int, ArchiveMessage]]:
    # Stable: equal log times keep write order, as the reader does within a chunk.
    return sorted(((t, m.stamp_ns, m) for t, m in messages), key=lambda x: x[1])


@pytest.mark.parametrize(
    ("compression", "chunk_size"), [("zstd", 4 * 2**20), ("lz4", 2000), ("none", 1)]
)
def test_round_trip_all_types_in_log_time_order(
    tmp_path: Path, compression: str, chunk_size: int
) -> None:
    rng = np.random.default_rng(10)
    messages = sample_messages(rng)
    rng.shuffle(messages)  # out-of-order writes, overlapping chunks
    path = tmp_path / "rec.mcap"
    write_all(path, messages, compression=compression, chunk_size=chunk_size)
    expected = in_log_order(messages)
    with ArchiveReader(path) as reader:
        assert reader.indexed
        got = list(reader.messages())
    assert [lt for _, lt, _ in got] == [lt for _, lt, _ in expected]  # log-time order
    # Equal log times may come in any topic order across chunks: compare as multisets per time.
    for (_, _, a), (_, _, b) in zip(
        sorted(got, key=lambda x: (x[1], x[0], cdr.encode(x[2]))),
        sorted(expected, key=lambda x: (x[1], x[0], cdr.encode(x[2]))),
        strict=True,
    ):
        assert same(a, b)


def test_topics_span_metadata_and_counts(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    messages = sample_messages(rng)
    path = tmp_path / "rec.mcap"
    with ArchiveWriter(path, chunk_size=5000, metadata={"site": "Thistlegorm"}) as writer:
        writer.add_metadata("clocks", {"gopro": "utc", "dive_computer": "local, no zone"})
        for topic, message in messages:
            writer.write(topic, message)
        counts = writer.messages_written
    assert counts == {t: sum(1 for x, _ in messages if x == t) for t in counts}
    with ArchiveReader(path) as reader:
        topics = reader.topics()
        assert set(topics) == {t for t, _ in messages}
        for name, info in topics.items():
            stamps = [m.stamp_ns for t, m in messages if t == name]
            assert info.message_count == len(stamps) == counts[name]
            assert (info.first_log_time_ns, info.last_log_time_ns) == (min(stamps), max(stamps))
            assert info.schema_name == message_type_for_topic(name).ROS_TYPE_NAME
        stamps = [m.stamp_ns for _, m in messages]
        assert reader.time_span_ns() == (min(stamps), max(stamps))
        assert reader.metadata() == {
            "wreckmap_session": {"site": "Thistlegorm"},
            "clocks": {"gopro": "utc", "dive_computer": "local, no zone"},
        }
        assert reader.profile == "ros2"


def test_time_and_topic_filters(tmp_path: Path) -> None:
    rng = np.random.default_rng(12)
    messages = sample_messages(rng)
    path = tmp_path / "rec.mcap"
    write_all(path, messages, chunk_size=3000)
    expected = in_log_order(messages)
    start, end = T0 + 300_000_000, T0 + 1_200_000_000
    with ArchiveReader(path) as reader:
        got = [(t, lt) for t, lt, _ in reader.messages(start_ns=start, end_ns=end)]
        assert got == [(t, lt) for t, lt, _ in expected if start <= lt < end]
        assert got and got[0][1] >= start
        wanted = {imu_topic(0), depth_topic(0)}
        got = [(t, lt) for t, lt, _ in reader.messages(topics=wanted, end_ns=end)]
        assert got == [(t, lt) for t, lt, _ in expected if t in wanted and lt < end]
        assert list(reader.messages(topics=["/imu7"])) == []
        assert list(reader.messages(start_ns=end, end_ns=end)) == []


def test_explicit_log_time_and_read_imu(tmp_path: Path) -> None:
    rng = np.random.default_rng(13)
    imus = [make_imu(i, rng) for i in range(500)]
    path = tmp_path / "rec.mcap"
    with ArchiveWriter(path, chunk_size=10_000) as writer:
        for i, message in enumerate(imus):
            writer.write(imu_topic(0), message, log_time_ns=T0 + 7 + i * 5_000_000)
        writer.write(depth_topic(0), DepthSample(stamp_ns=T0, frame_id="d"))
    with ArchiveReader(path) as reader:
        series = reader.read_imu()
        assert series.stamps_ns.dtype == np.int64 and series.gyro_rad_s.shape == (500, 3)
        assert series.stamps_ns.tolist() == [m.stamp_ns for m in imus]
        assert series.log_times_ns.tolist() == [T0 + 7 + i * 5_000_000 for i in range(500)]
        assert bits(series.gyro_rad_s) == bits([m.angular_velocity_rad_s for m in imus])
        assert bits(series.accel_m_s2) == bits([m.linear_acceleration_m_s2 for m in imus])
        first = next(reader.messages([imu_topic(0)]))
        assert first[1] == T0 + 7 and first[2].stamp_ns == imus[0].stamp_ns
        with pytest.raises(InputError, match=r"rec\.mcap: no topic '/imu1'"):
            reader.read_imu(imu_topic(1))
        with pytest.raises(InputError, match="not sensor_msgs/msg/Imu"):
            reader.read_imu(depth_topic(0))


def test_part_file_renamed_only_on_clean_close(tmp_path: Path) -> None:
    path = tmp_path / "session" / "recording.mcap"
    writer = ArchiveWriter(path)
    writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="id: 1\n"))
    writer.flush(fsync=True)
    assert part_path(path).is_file() and not path.exists()
    assert writer.close() == path
    assert path.is_file() and not part_path(path).exists()
    assert writer.close() == path  # idempotent

    failed = tmp_path / "failed.mcap"
    with pytest.raises(RuntimeError, match="device unplugged"), ArchiveWriter(failed) as writer:
        writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="id: 2\n"))
        raise RuntimeError("device unplugged")
    assert not failed.exists()
    with ArchiveReader(part_path(failed)) as reader:  # complete and indexed all the same
        assert reader.indexed
        assert [m.yaml_text for _, _, m in reader.messages()] == ["id: 2\n"]  # type: ignore[union-attr]

    aborted = ArchiveWriter(tmp_path / "aborted.mcap")
    assert aborted.abort() == part_path(tmp_path / "aborted.mcap")
    assert aborted.closed


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "recording.mcap"
    write_all(path, [(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="a"))])
    with pytest.raises(OutputExistsError, match=r"recording\.mcap: already exists"):
        ArchiveWriter(path)
    part_path(path).write_bytes(b"crashed")
    path.unlink()
    with pytest.raises(OutputExistsError, match=r"recording\.mcap\.part: already exists"):
        ArchiveWriter(path)
    path.write_bytes(b"old")
    write_all(path, [(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text="b"))], overwrite=True)
    with ArchiveReader(path) as reader:
        assert [m.yaml_text for _, _, m in reader.messages()] == ["b"]  # type: ignore[union-attr]
    # Someone else creating the final name while recording: keep the .part, do not clobber.
    other = tmp_path / "other.mcap"
    writer = ArchiveWriter(other)
    other.write_bytes(b"not ours")
    with pytest.raises(OutputExistsError, match="appeared while recording"):
        writer.close()
    assert other.read_bytes() == b"not ours" and part_path(other).is_file()


def test_writer_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="compression 'gzip'"):
        ArchiveWriter(tmp_path / "a.mcap", compression="gzip")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="chunk_size 0"):
        ArchiveWriter(tmp_path / "a.mcap", chunk_size=0)
    with ArchiveWriter(tmp_path / "a.mcap") as writer:
        with pytest.raises(InputError, match="not an archive topic"):
            writer.write("/gps0", SessionInfo(stamp_ns=T0, yaml_text=""))
        with pytest.raises(InputError, match="expected a Imu message, got DepthSample"):
            writer.write(imu_topic(0), DepthSample(stamp_ns=T0, frame_id="d"))
        with pytest.raises(InputError, match="log time -1 ns is not a uint64"):
            writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text=""), log_time_ns=-1)
        with pytest.raises(InputError, match="keys and values must be strings"):
            writer.add_metadata("bad", {"depth": 3})  # type: ignore[dict-item]
        with pytest.raises(InputError, match="not little-endian CDR"):
            writer.write_cdr(SESSION_TOPIC, b"{}", log_time_ns=T0)
    with pytest.raises(WreckmapError, match="already closed"):
        writer.write(SESSION_TOPIC, SessionInfo(stamp_ns=T0, yaml_text=""))
    with pytest.raises(WreckmapError, match="already closed"):
        writer.flush()


def test_write_cdr_copies_records(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    messages = sample_messages(rng)
    source = tmp_path / "a.mcap"
    write_all(source, messages)
    copy = tmp_path / "b.mcap"
    with ArchiveReader(source) as reader, ArchiveWriter(copy) as writer:
        for record in reader.raw_messages():
            writer.write_cdr(record.topic, record.data, log_time_ns=record.log_time_ns)
    with ArchiveReader(source) as a, ArchiveReader(copy) as b:
        assert [(t, lt) for t, lt, _ in a.messages()] == [(t, lt) for t, lt, _ in b.messages()]
        assert a.topics() == b.topics()


def test_empty_archive(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    ArchiveWriter(path).close()
    with ArchiveReader(path) as reader:
        assert reader.topics() == {}
        assert list(reader.messages()) == []
        assert reader.metadata() == {}
        with pytest.raises(InputError, match=r"empty\.mcap: no messages"):
            reader.time_span_ns()


def test_interleaved_queries_and_size(tmp_path: Path) -> None:
    rng = np.random.default_rng(15)
    messages = sample_messages(rng)
    path = tmp_path / "rec.mcap"
    with ArchiveWriter(path, chunk_size=2000) as writer:
        sizes = []
        for topic, message in messages:
            writer.write(topic, message)
            sizes.append(writer.bytes_written)
    # Grows with the data (drops a little when a chunk gets compressed); the summary comes on top.
    assert sizes[0] < sizes[len(sizes) // 2] < sizes[-1] < path.stat().st_size
    with ArchiveReader(path) as reader:
        imu = reader.messages([imu_topic(0)])
        video = reader.messages([video_topic(0)])
        pairs = list(zip(imu, video, strict=False))  # two live iterators over one file
        assert all(a[0] == imu_topic(0) and b[0] == video_topic(0) for a, b in pairs)
        assert len(pairs) == sum(1 for t, _ in messages if t == video_topic(0))
        assert reader.topics()[imu_topic(0)].message_count == 400
