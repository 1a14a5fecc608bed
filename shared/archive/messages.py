"""The message types an archive holds, as plain dataclasses.

Every time is an integer count of nanoseconds since the UNIX epoch in the
clock of the device that produced the sample (`stamp_ns`); the MCAP log time
(when the host received the message) is kept beside the message, not in it.
Each class maps to one ROS 2 message type (see `ROS_TYPE_NAME`), encoded as
CDR by `shared.archive.cdr`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray


@dataclass(eq=False)
class Imu:
    """One IMU sample -> `sensor_msgs/msg/Imu` (orientation unknown).

    `angular_velocity_rad_s` and `linear_acceleration_m_s2` are (3,) float64
    vectors in the IMU frame `frame_id`. The covariances are row-major (9,)
    arrays in (rad/s)^2 and (m/s^2)^2; `None` writes zeros ("unknown").
    The orientation is not estimated, so the ROS message carries
    `orientation_covariance[0] = -1` as ROS prescribes.
    """

    ROS_TYPE_NAME: ClassVar[str] = "sensor_msgs/msg/Imu"

    stamp_ns: int
    frame_id: str
    angular_velocity_rad_s: NDArray[np.float64]
    linear_acceleration_m_s2: NDArray[np.float64]
    angular_velocity_covariance: NDArray[np.float64] | None = None
    linear_acceleration_covariance: NDArray[np.float64] | None = None


@dataclass
class CompressedImage:
    """One compressed still image -> `sensor_msgs/msg/CompressedImage`.

    `format` is the codec name as ROS uses it ("jpeg", "png"); `data` the
    encoded file bytes.
    """

    ROS_TYPE_NAME: ClassVar[str] = "sensor_msgs/msg/CompressedImage"

    stamp_ns: int
    frame_id: str
    format: str
    data: bytes


@dataclass
class CompressedVideo:
    """One video packet -> `foxglove_msgs/msg/CompressedVideo`.

    `format` is "h264" or "h265"; `data` is one access unit in Annex B byte
    stream form (start codes, parameter sets in-band before keyframes).
    """

    ROS_TYPE_NAME: ClassVar[str] = "foxglove_msgs/msg/CompressedVideo"

    stamp_ns: int
    frame_id: str
    format: str
    data: bytes


@dataclass
class DepthSample:
    """One dive-computer or pressure-sensor sample -> `wreckmap_msgs/msg/DepthSample`.

    `depth_m` is metres positive down, `pressure_pa` absolute pressure in
    Pascals, `temperature_c` in degrees Celsius; NaN where the device gives
    no value.
    """

    ROS_TYPE_NAME: ClassVar[str] = "wreckmap_msgs/msg/DepthSample"

    stamp_ns: int
    frame_id: str
    depth_m: float = float("nan")
    pressure_pa: float = float("nan")
    temperature_c: float = float("nan")


@dataclass
class SessionInfo:
    """The session description (the text of session.yaml) -> `wreckmap_msgs/msg/SessionInfo`.

    `stamp_ns` is the host time at which the session description was written.
    """

    ROS_TYPE_NAME: ClassVar[str] = "wreckmap_msgs/msg/SessionInfo"

    stamp_ns: int
    yaml_text: str


@dataclass
class RecorderEvent:
    """Something the recorder saw happen -> `wreckmap_msgs/msg/RecorderEvent`.

    `stamp_ns` is host time (the recorder's monotonic-based clock, like every log time);
    `frame_id` names the source concerned ("" for the recorder itself); `kind` is one of
    `EVENT_KINDS`; `yaml_text` holds the details (times in ns, lengths in s).
    """

    ROS_TYPE_NAME: ClassVar[str] = "wreckmap_msgs/msg/RecorderEvent"

    stamp_ns: int
    frame_id: str
    kind: str
    yaml_text: str


EVENT_KINDS: dict[str, str] = {
    "source_lost": "a source stopped delivering (unplugged, stalled); the others go on",
    "source_back": "a lost source delivers again; the gap lasted `gap_s`",
    "clock_step": "the host wall clock stepped by `step_s` against the monotonic clock",
    "disk": "free space fell under the watermark, or a write failed",
}
"""What a `RecorderEvent.kind` can be."""


ArchiveMessage = Imu | CompressedImage | CompressedVideo | DepthSample | SessionInfo | RecorderEvent
"""Any message an archive can hold."""

MESSAGE_TYPES: tuple[type[ArchiveMessage], ...] = (
    Imu,
    CompressedImage,
    CompressedVideo,
    DepthSample,
    SessionInfo,
    RecorderEvent,
)
