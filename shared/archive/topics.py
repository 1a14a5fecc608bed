"""The topic registry: which topic names an archive uses and what each one holds.

Device streams are numbered from 0 per kind, so a two-camera rig with one
IMU writes `/cam0/video`, `/cam1/video` and `/imu0`.

| topic          | message           | meaning                                        |
|----------------|-------------------|------------------------------------------------|
| /cam{N}/video  | CompressedVideo   | H.264/H.265 packets of camera N (Annex B)      |
| /cam{N}/image  | CompressedImage   | JPEG stills of camera N                        |
| /imu{N}        | Imu               | gyro + accelerometer samples of IMU N          |
| /depth{N}      | DepthSample       | depth / pressure / temperature of sensor N     |
| /session       | SessionInfo       | the session description (session.yaml text)    |
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from shared.archive.messages import (
    ArchiveMessage,
    CompressedImage,
    CompressedVideo,
    DepthSample,
    Imu,
    RecorderEvent,
    SessionInfo,
)
from shared.errors import InputError

SESSION_TOPIC = "/session"
"""The one topic holding the session description."""

HEALTH_TOPIC = "/health"
"""The recorder's events: sources lost and back, clock steps, disk (`RecorderEvent`)."""


@dataclass(frozen=True)
class TopicKind:
    """One family of topics: a name pattern, its message class and what it means."""

    pattern: str
    message_type: type[ArchiveMessage]
    meaning: str


TOPIC_KINDS: dict[str, TopicKind] = {
    "video": TopicKind(
        r"/cam(\d+)/video", CompressedVideo, "H.264/H.265 packets of camera N, Annex B"
    ),
    "image": TopicKind(r"/cam(\d+)/image", CompressedImage, "compressed stills of camera N"),
    "imu": TopicKind(r"/imu(\d+)", Imu, "gyro (rad/s) and accelerometer (m/s^2) of IMU N"),
    "depth": TopicKind(
        r"/depth(\d+)", DepthSample, "depth (m), pressure (Pa), temperature (C) of sensor N"
    ),
    "session": TopicKind(re.escape(SESSION_TOPIC), SessionInfo, "session description (YAML)"),
    "health": TopicKind(
        re.escape(HEALTH_TOPIC), RecorderEvent, "recorder events: source gaps, clock steps"
    ),
}

_COMPILED = [(re.compile(kind.pattern), kind) for kind in TOPIC_KINDS.values()]


def _index(kind: str, index: int) -> int:
    if not isinstance(index, int) or isinstance(index, bool) or index < 0:
        raise InputError(f"{kind} index {index!r}: expected an integer >= 0")
    return index


def video_topic(camera_index: int = 0) -> str:
    """`/cam{N}/video`: compressed video packets of camera `camera_index`."""
    return f"/cam{_index('camera', camera_index)}/video"


def image_topic(camera_index: int = 0) -> str:
    """`/cam{N}/image`: compressed still images of camera `camera_index`."""
    return f"/cam{_index('camera', camera_index)}/image"


def imu_topic(imu_index: int = 0) -> str:
    """`/imu{N}`: samples of IMU `imu_index`."""
    return f"/imu{_index('imu', imu_index)}"


def depth_topic(sensor_index: int = 0) -> str:
    """`/depth{N}`: samples of depth sensor `sensor_index`."""
    return f"/depth{_index('depth sensor', sensor_index)}"


def topic_kind(topic: str) -> TopicKind:
    """The registry entry of `topic`; InputError for a topic outside the registry."""
    for regex, kind in _COMPILED:
        if regex.fullmatch(topic):
            return kind
    expected = ", ".join(
        k.pattern.replace(r"(\d+)", "{N}").replace("\\", "") for k in TOPIC_KINDS.values()
    )
    raise InputError(f"topic {topic!r}: not an archive topic (expected one of: {expected})")


def message_type_for_topic(topic: str) -> type[ArchiveMessage]:
    """The message class a topic holds; InputError for a topic outside the registry."""
    return topic_kind(topic).message_type
