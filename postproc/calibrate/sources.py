"""Where calibration images and gyro samples come from: any recording
`shared.formats.recordings` reads (EuRoC folder, session folder or `.mcap` archive,
folder of images, video file), as grey frames.

`open_frames` picks the camera of a session by topic (default `/cam0/image`, else
`/cam0/video`; a camera asked for as video that was recorded as stills is found, and
back); `read_gyro` reads the IMU of a session (by topic) or an EuRoC folder, cleaned
by `shared.imu`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.formats.recordings import Recording, open_recording, recording_kind

GrayImage = npt.NDArray[np.uint8]


class FrameSource:
    """Grey frames of one recording: `frames()` yields (index, stamp_ns, image (H, W) uint8)."""

    def __init__(self, recording: Recording) -> None:
        self.recording = recording
        self.path = recording.path
        self.topic = recording.camera_topic

    def frame_count(self) -> int | None:
        return self.recording.frame_count

    def frames(self) -> Iterator[tuple[int, int, GrayImage]]:
        for frame in self.recording.frames(grayscale=True):
            yield frame.index, frame.stamp_ns, frame.image


def source_kind(path: Path | str) -> str:
    """ "session", "euroc", "images" or "video" for `path`; InputError when none fits."""
    return recording_kind(path)


def open_frames(path: Path | str, *, topic: str | None = None) -> FrameSource:
    """The grey frames of `path`; `topic` picks the camera of a session (default cam0)."""
    return FrameSource(open_recording(path, camera_topic=topic))


def read_gyro(
    path: Path | str, *, topic: str = "/imu0"
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """(stamps_ns (N,) int64 sensor clock, gyro (N,3) rad/s) of a session or EuRoC folder."""
    imu, _ = open_recording(path, imu_topic=topic, need_camera=False).imu()
    return imu.stamps_ns, imu.gyro_rad_s
