"""The MCAP archive: the contract between the field tools (writers) and the lab (readers).

Archives are MCAP files with the ROS 2 profile: CDR messages, `ros2msg`
schemas, standard message types where one exists, so Foxglove, rosbag2 and
`rosbags` open them. Times are int64 nanoseconds since the UNIX epoch.

The records are written by the `mcap` package (`writer.py`; our own record
writer remains as `engine="wreckmap"` where its lower cost matters), the
summary is parsed by it (`reader.py`); chunk loading, salvage of crashed
recordings and the CDR codec (`cdr.py`, 4-6x faster than mcap-ros2-support's
generic decoder) stay ours, each module says why.
"""

from __future__ import annotations

from shared.archive.messages import (
    ArchiveMessage,
    CompressedImage,
    CompressedVideo,
    DepthSample,
    Imu,
    RecorderEvent,
    SessionInfo,
)
from shared.archive.reader import (
    ArchiveReader,
    ImuSeries,
    RawRecord,
    TopicInfo,
    iter_records_salvage,
)
from shared.archive.rosbag2 import write_rosbag2_metadata
from shared.archive.topics import (
    HEALTH_TOPIC,
    SESSION_TOPIC,
    depth_topic,
    image_topic,
    imu_topic,
    message_type_for_topic,
    video_topic,
)
from shared.archive.writer import ArchiveWriter, part_path

__all__ = [
    "HEALTH_TOPIC",
    "SESSION_TOPIC",
    "ArchiveMessage",
    "ArchiveReader",
    "ArchiveWriter",
    "CompressedImage",
    "CompressedVideo",
    "DepthSample",
    "Imu",
    "ImuSeries",
    "RawRecord",
    "RecorderEvent",
    "SessionInfo",
    "TopicInfo",
    "depth_topic",
    "image_topic",
    "imu_topic",
    "iter_records_salvage",
    "message_type_for_topic",
    "part_path",
    "video_topic",
    "write_rosbag2_metadata",
]
