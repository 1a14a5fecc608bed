"""ROS 2 message definitions and a small CDR codec for the archive's fixed message set.

CDR as ROS 2 writes it: a 4-byte encapsulation header `00 01 00 00`
(little-endian plain CDR), then the fields in declaration order, each
aligned to its own size (1, 2, 4 or 8 bytes) counted from the first byte
after the header. A string is a uint32 length that includes the trailing NUL,
the UTF-8 bytes and the NUL; a variable-length sequence is a uint32 element
count followed by the elements; a fixed array (`float64[9]`) has no count.

Only the five message types of `shared.archive.messages` are supported, with
hand-written struct layouts: this is several times faster than a generic
serializer, which matters for 200 Hz-1 kHz IMU streams written in Python.
mcap-ros2-support 0.6.0 (the mcap package's ROS 2 codec) decodes our files
from the schemas stored in them, and the archive tests use it as an
independent check, but it decodes IMU messages 4-6x slower than this codec
(bench/bench_archive.py, "IMU CDR decode"), so the codec stays ours.
The schema texts follow the `ros2msg` encoding of rosbag2: the top-level
definition, then every dependency once, each preceded by a line of 80 `=`
and a line `MSG: pkg/Type`.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.archive.messages import (
    ArchiveMessage,
    CompressedImage,
    CompressedVideo,
    DepthSample,
    Imu,
    RecorderEvent,
    SessionInfo,
)
from shared.clock import NS_PER_S
from shared.errors import InputError

ENCAPSULATION_HEADER = b"\x00\x01\x00\x00"
"""CDR little-endian encapsulation (representation id 0x0001, options 0)."""

_INT32_MIN = -(2**31)
_INT32_MAX = 2**31 - 1

# ---------------------------------------------------------------------------
# Message definitions (.msg text). Dependencies are listed by their short
# `pkg/Type` name, as rosbag2 writes them in the `MSG:` lines.

_DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "sensor_msgs/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    ),
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "foxglove_msgs/CompressedVideo": (
        "builtin_interfaces/Time timestamp\nstring frame_id\nuint8[] data\nstring format\n"
    ),
    "wreckmap_msgs/DepthSample": (
        "# One depth / pressure sample of a dive computer or pressure sensor.\n"
        "# header.stamp is the device clock; NaN marks a value the device did not give.\n"
        "std_msgs/Header header\n"
        "float64 depth_m  # metres, positive down\n"
        "float64 pressure_pa  # absolute pressure, Pascals\n"
        "float64 temperature_c  # degrees Celsius\n"
    ),
    "wreckmap_msgs/SessionInfo": (
        "# The session description (session.yaml) recorded inside the archive.\n"
        "std_msgs/Header header\n"
        "string yaml_text\n"
    ),
    "wreckmap_msgs/RecorderEvent": (
        "# Something the recorder saw: a source lost or back, a clock step, a full disk.\n"
        "# header.stamp is host time; header.frame_id the source concerned (may be empty).\n"
        "std_msgs/Header header\n"
        "string kind  # source_lost, source_back, clock_step, disk\n"
        "string yaml_text  # the details\n"
    ),
}

_DEPENDENCIES: dict[str, tuple[str, ...]] = {
    "sensor_msgs/Imu": (
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/Quaternion",
        "geometry_msgs/Vector3",
    ),
    "sensor_msgs/CompressedImage": ("std_msgs/Header", "builtin_interfaces/Time"),
    "foxglove_msgs/CompressedVideo": ("builtin_interfaces/Time",),
    "wreckmap_msgs/DepthSample": ("std_msgs/Header", "builtin_interfaces/Time"),
    "wreckmap_msgs/SessionInfo": ("std_msgs/Header", "builtin_interfaces/Time"),
    "wreckmap_msgs/RecorderEvent": ("std_msgs/Header", "builtin_interfaces/Time"),
}

_SEPARATOR = "=" * 80


def _short_name(ros_type_name: str) -> str:
    """`sensor_msgs/msg/Imu` -> `sensor_msgs/Imu`."""
    package, _, name = ros_type_name.partition("/msg/")
    return f"{package}/{name}"


def schema_text(message_type: type[ArchiveMessage]) -> str:
    """The complete `ros2msg` definition of `message_type` (dependencies concatenated)."""
    short = _short_name(message_type.ROS_TYPE_NAME)
    parts = [_DEFINITIONS[short]]
    for dependency in _DEPENDENCIES[short]:
        parts.append(f"{_SEPARATOR}\nMSG: {dependency}\n{_DEFINITIONS[dependency]}")
    return "".join(parts)


def message_definition(ros_short_name: str) -> str:
    """The bare .msg text of one type, by `pkg/Type` name (for registering types elsewhere)."""
    return _DEFINITIONS[ros_short_name]


# ---------------------------------------------------------------------------
# Helpers


def split_stamp(stamp_ns: int) -> tuple[int, int]:
    """Nanoseconds since epoch -> (sec int32, nanosec in [0, 1e9)) as builtin_interfaces/Time."""
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise InputError(
            f"stamp {stamp_ns} ns: outside the int32 seconds range of builtin_interfaces/Time"
        )
    return sec, nanosec


def _str_field(pos: int, text: str) -> tuple[bytes, int]:
    """Encode a string starting at payload offset `pos` (after the header): (bytes, new pos)."""
    raw = text.encode("utf-8")
    pad = -pos % 4
    chunk = b"\x00" * pad + struct.pack("<I", len(raw) + 1) + raw + b"\x00"
    return chunk, pos + len(chunk)


def _bytes_field(pos: int, data: bytes) -> tuple[list[bytes], int]:
    """Encode a uint8[] sequence starting at payload offset `pos`: (parts, new pos)."""
    pad = -pos % 4
    head = b"\x00" * pad + struct.pack("<I", len(data))
    return [head, data], pos + len(head) + len(data)


class _Cursor:
    """Reads CDR fields from a message payload; offsets are aligned after the 4-byte header."""

    __slots__ = ("data", "name", "pos")

    def __init__(self, data: bytes | memoryview, name: str) -> None:
        if len(data) < 4 or bytes(data[:2]) != b"\x00\x01":
            raise InputError(
                f"{name}: not little-endian CDR (expected encapsulation 00 01, "
                f"got {bytes(data[:4]).hex(' ') or 'nothing'})"
            )
        self.data = data
        self.name = name
        self.pos = 4

    def _align(self, size: int) -> None:
        self.pos += -(self.pos - 4) % size

    def _need(self, size: int) -> None:
        if self.pos + size > len(self.data):
            raise InputError(
                f"{self.name}: CDR message truncated (needs {self.pos + size} bytes, "
                f"has {len(self.data)})"
            )

    def uint32(self) -> int:
        self._align(4)
        self._need(4)
        (value,) = struct.unpack_from("<I", self.data, self.pos)
        self.pos += 4
        return int(value)

    def time_ns(self) -> int:
        self._align(4)
        self._need(8)
        sec, nanosec = struct.unpack_from("<iI", self.data, self.pos)
        self.pos += 8
        return int(sec) * NS_PER_S + int(nanosec)

    def string(self) -> str:
        length = self.uint32()
        self._need(length)
        if length == 0:  # some writers encode "" as length 0; tolerate it
            return ""
        raw = bytes(self.data[self.pos : self.pos + length - 1])
        self.pos += length
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as error:
            raise InputError(f"{self.name}: string field is not UTF-8 ({error})") from None

    def octets(self) -> bytes:
        length = self.uint32()
        self._need(length)
        raw = bytes(self.data[self.pos : self.pos + length])
        self.pos += length
        return raw

    def float64s(self, count: int) -> tuple[float, ...]:
        self._align(8)
        self._need(8 * count)
        values: tuple[float, ...] = struct.unpack_from(f"<{count}d", self.data, self.pos)
        self.pos += 8 * count
        return values


# ---------------------------------------------------------------------------
# sensor_msgs/msg/Imu: a fixed layout once the frame_id is known, so each
# frame_id gets one precompiled struct (header, string, padding, 37 float64).

_IMU_DOUBLES = 37  # quaternion 4 + 9 + vector 3 + 9 + vector 3 + 9
_IMU_GYRO = slice(13, 16)
_IMU_GYRO_COV = slice(16, 25)
_IMU_ACCEL = slice(25, 28)
_IMU_ACCEL_COV = slice(28, 37)
_UNKNOWN_ORIENTATION = (0.0, 0.0, 0.0, 1.0, -1.0) + (0.0,) * 8
_ZERO9 = (0.0,) * 9
_imu_structs: dict[str, tuple[struct.Struct, bytes]] = {}


def _imu_struct(frame_id: str) -> tuple[struct.Struct, bytes]:
    cached = _imu_structs.get(frame_id)
    if cached is None:
        raw = frame_id.encode("utf-8")
        string_end = 8 + 4 + len(raw) + 1  # payload offset after the frame_id NUL
        pad = -string_end % 8
        cached = (struct.Struct(f"<4siII{len(raw) + 1}s{pad}x{_IMU_DOUBLES}d"), raw)
        _imu_structs[frame_id] = cached
    return cached


def imu_doubles_offset(frame_id_length: int) -> int:
    """Byte offset (from the start of the message, header included) of Imu's first float64."""
    string_end = 8 + 4 + frame_id_length + 1
    return 4 + string_end + (-string_end % 8)


def _vector(values: Any, size: int, what: str) -> tuple[float, ...]:
    flat = tuple(float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1))
    if len(flat) != size:
        raise InputError(f"Imu.{what}: expected {size} values, got {len(flat)}")
    return flat


def encode_imu(message: Imu) -> bytes:
    """CDR bytes of a `sensor_msgs/msg/Imu`."""
    packer, frame = _imu_struct(message.frame_id)
    sec, nanosec = split_stamp(message.stamp_ns)
    gyro = message.angular_velocity_rad_s
    accel = message.linear_acceleration_m_s2
    try:
        g0, g1, g2 = gyro
        a0, a1, a2 = accel
    except (TypeError, ValueError):
        g0, g1, g2 = _vector(gyro, 3, "angular_velocity_rad_s")
        a0, a1, a2 = _vector(accel, 3, "linear_acceleration_m_s2")
    gyro_cov = (
        _ZERO9
        if message.angular_velocity_covariance is None
        else _vector(message.angular_velocity_covariance, 9, "angular_velocity_covariance")
    )
    accel_cov = (
        _ZERO9
        if message.linear_acceleration_covariance is None
        else _vector(message.linear_acceleration_covariance, 9, "linear_acceleration_covariance")
    )
    return packer.pack(
        ENCAPSULATION_HEADER,
        sec,
        nanosec,
        len(frame) + 1,
        frame,
        *_UNKNOWN_ORIENTATION,
        g0,
        g1,
        g2,
        *gyro_cov,
        a0,
        a1,
        a2,
        *accel_cov,
    )


def decode_imu(data: bytes | memoryview, name: str = "sensor_msgs/msg/Imu") -> Imu:
    """Decode one `sensor_msgs/msg/Imu` (the orientation is dropped: never recorded)."""
    cursor = _Cursor(data, name)
    stamp_ns = cursor.time_ns()
    frame_id = cursor.string()
    values = cursor.float64s(_IMU_DOUBLES)
    return Imu(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        angular_velocity_rad_s=np.array(values[_IMU_GYRO]),
        linear_acceleration_m_s2=np.array(values[_IMU_ACCEL]),
        angular_velocity_covariance=np.array(values[_IMU_GYRO_COV]),
        linear_acceleration_covariance=np.array(values[_IMU_ACCEL_COV]),
    )


@dataclass
class ImuArrays:
    """Many Imu messages decoded at once (rows in input order)."""

    stamps_ns: NDArray[np.int64]
    gyro_rad_s: NDArray[np.float64]
    accel_m_s2: NDArray[np.float64]


def decode_imu_batch(
    payloads: Sequence[bytes | memoryview], name: str = "sensor_msgs/msg/Imu"
) -> ImuArrays:
    """Decode many `sensor_msgs/msg/Imu` payloads with numpy on the fixed layout.

    Messages of equal size with equal frame_id length share one layout; they
    are decoded as a 2-D byte array. Any other message falls back to
    `decode_imu`.
    """
    count = len(payloads)
    stamps = np.empty(count, dtype=np.int64)
    gyro = np.empty((count, 3), dtype=np.float64)
    accel = np.empty((count, 3), dtype=np.float64)
    groups: dict[int, list[int]] = {}
    for index, payload in enumerate(payloads):
        groups.setdefault(len(payload), []).append(index)
    for size, indices in groups.items():
        rows = np.frombuffer(b"".join(payloads[i] for i in indices), dtype=np.uint8)
        rows = rows.reshape(len(indices), size)
        if size < 16:
            raise InputError(f"{name}: CDR message truncated ({size} bytes)")
        header_ok = (rows[:, 0] == 0) & (rows[:, 1] == 1)
        frame_len = rows[:, 12:16].copy().view("<u4")[:, 0].astype(np.int64) - 1
        uniform = bool(header_ok.all()) and bool((frame_len == frame_len[0]).all())
        offset = imu_doubles_offset(int(frame_len[0])) if uniform else 0
        if not uniform or offset + 8 * _IMU_DOUBLES != size:
            for i in indices:
                message = decode_imu(payloads[i], name)
                stamps[i] = message.stamp_ns
                gyro[i] = message.angular_velocity_rad_s
                accel[i] = message.linear_acceleration_m_s2
            continue
        where = np.asarray(indices)
        sec = rows[:, 4:8].copy().view("<i4")[:, 0].astype(np.int64)
        nanosec = rows[:, 8:12].copy().view("<u4")[:, 0].astype(np.int64)
        stamps[where] = sec * NS_PER_S + nanosec
        doubles = rows[:, offset:size].copy().view("<f8")
        gyro[where] = doubles[:, _IMU_GYRO]
        accel[where] = doubles[:, _IMU_ACCEL]
    return ImuArrays(stamps_ns=stamps, gyro_rad_s=gyro, accel_m_s2=accel)


# ---------------------------------------------------------------------------
# The other types: header, strings and byte sequences.


def _header(stamp_ns: int, frame_id: str) -> tuple[bytes, int]:
    sec, nanosec = split_stamp(stamp_ns)
    frame, pos = _str_field(8, frame_id)
    return ENCAPSULATION_HEADER + struct.pack("<iI", sec, nanosec) + frame, pos


def encode_compressed_image(message: CompressedImage) -> bytes:
    """CDR bytes of a `sensor_msgs/msg/CompressedImage`."""
    head, pos = _header(message.stamp_ns, message.frame_id)
    fmt, pos = _str_field(pos, message.format)
    data, pos = _bytes_field(pos, message.data)
    return b"".join((head, fmt, *data))


def decode_compressed_image(
    data: bytes | memoryview, name: str = "sensor_msgs/msg/CompressedImage"
) -> CompressedImage:
    """Decode one `sensor_msgs/msg/CompressedImage`."""
    cursor = _Cursor(data, name)
    stamp_ns = cursor.time_ns()
    frame_id = cursor.string()
    fmt = cursor.string()
    return CompressedImage(stamp_ns=stamp_ns, frame_id=frame_id, format=fmt, data=cursor.octets())


def encode_compressed_video(message: CompressedVideo) -> bytes:
    """CDR bytes of a `foxglove_msgs/msg/CompressedVideo` (timestamp, frame_id, data, format)."""
    head, pos = _header(message.stamp_ns, message.frame_id)
    data, pos = _bytes_field(pos, message.data)
    fmt, pos = _str_field(pos, message.format)
    return b"".join((head, *data, fmt))


def decode_compressed_video(
    data: bytes | memoryview, name: str = "foxglove_msgs/msg/CompressedVideo"
) -> CompressedVideo:
    """Decode one `foxglove_msgs/msg/CompressedVideo`."""
    cursor = _Cursor(data, name)
    stamp_ns = cursor.time_ns()
    frame_id = cursor.string()
    payload = cursor.octets()
    return CompressedVideo(
        stamp_ns=stamp_ns, frame_id=frame_id, format=cursor.string(), data=payload
    )


def encode_depth_sample(message: DepthSample) -> bytes:
    """CDR bytes of a `wreckmap_msgs/msg/DepthSample`."""
    head, pos = _header(message.stamp_ns, message.frame_id)
    values = struct.pack(
        "<3d", float(message.depth_m), float(message.pressure_pa), float(message.temperature_c)
    )
    return head + b"\x00" * (-pos % 8) + values


def decode_depth_sample(
    data: bytes | memoryview, name: str = "wreckmap_msgs/msg/DepthSample"
) -> DepthSample:
    """Decode one `wreckmap_msgs/msg/DepthSample`."""
    cursor = _Cursor(data, name)
    stamp_ns = cursor.time_ns()
    frame_id = cursor.string()
    depth_m, pressure_pa, temperature_c = cursor.float64s(3)
    return DepthSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        depth_m=depth_m,
        pressure_pa=pressure_pa,
        temperature_c=temperature_c,
    )


def encode_session_info(message: SessionInfo) -> bytes:
    """CDR bytes of a `wreckmap_msgs/msg/SessionInfo` (empty frame_id)."""
    head, pos = _header(message.stamp_ns, "")
    text, pos = _str_field(pos, message.yaml_text)
    return head + text


def decode_session_info(
    data: bytes | memoryview, name: str = "wreckmap_msgs/msg/SessionInfo"
) -> SessionInfo:
    """Decode one `wreckmap_msgs/msg/SessionInfo`."""
    cursor = _Cursor(data, name)
    stamp_ns = cursor.time_ns()
    cursor.string()  # frame_id: always empty, a session has no frame
    return SessionInfo(stamp_ns=stamp_ns, yaml_text=cursor.string())


def encode_recorder_event(message: RecorderEvent) -> bytes:
    """CDR bytes of a `wreckmap_msgs/msg/RecorderEvent`."""
    head, pos = _header(message.stamp_ns, message.frame_id)
    kind, pos = _str_field(pos, message.kind)
    text, pos = _str_field(pos, message.yaml_text)
    return head + kind + text


def decode_recorder_event(
    data: bytes | memoryview, name: str = "wreckmap_msgs/msg/RecorderEvent"
) -> RecorderEvent:
    """Decode one `wreckmap_msgs/msg/RecorderEvent`."""
    cursor = _Cursor(data, name)
    stamp_ns = cursor.time_ns()
    frame_id = cursor.string()
    kind = cursor.string()
    return RecorderEvent(stamp_ns=stamp_ns, frame_id=frame_id, kind=kind, yaml_text=cursor.string())


# ---------------------------------------------------------------------------
# Dispatch by class and by ROS type name.

ENCODERS: dict[type[Any], Callable[[Any], bytes]] = {
    Imu: encode_imu,
    CompressedImage: encode_compressed_image,
    CompressedVideo: encode_compressed_video,
    DepthSample: encode_depth_sample,
    SessionInfo: encode_session_info,
    RecorderEvent: encode_recorder_event,
}

DECODERS: dict[str, Callable[[bytes | memoryview, str], ArchiveMessage]] = {
    Imu.ROS_TYPE_NAME: decode_imu,
    CompressedImage.ROS_TYPE_NAME: decode_compressed_image,
    CompressedVideo.ROS_TYPE_NAME: decode_compressed_video,
    DepthSample.ROS_TYPE_NAME: decode_depth_sample,
    SessionInfo.ROS_TYPE_NAME: decode_session_info,
    RecorderEvent.ROS_TYPE_NAME: decode_recorder_event,
}


def encode(message: ArchiveMessage) -> bytes:
    """CDR bytes (encapsulation header included) of any archive message."""
    encoder = ENCODERS.get(type(message))
    if encoder is None:
        raise InputError(f"{type(message).__name__}: not an archive message type")
    return encoder(message)


def decode(schema_name: str, data: bytes | memoryview, *, where: str = "") -> ArchiveMessage:
    """Decode CDR bytes of the ROS type `schema_name` (e.g. "sensor_msgs/msg/Imu").

    `where` (file and topic) prefixes error messages.
    """
    decoder = DECODERS.get(schema_name)
    if decoder is None:
        known = ", ".join(DECODERS)
        raise InputError(f"{where or schema_name}: unknown schema {schema_name!r} (known: {known})")
    return decoder(data, where or schema_name)
