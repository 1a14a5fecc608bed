"""Where SLAM gets its images and IMU samples: any recording `shared.formats.recordings`
reads (EuRoC folder, session folder or `.mcap` archive, folder of images, video file).

`open_input` asks the recording registry for the path and reads the IMU once,
cleaned by `shared.imu` (repeated stamps merged, rows out of order dropped, separate
gyro and accelerometer rows merged, with a warning). A recording without IMU (a
camera-only EuRoC cut, a folder of images) has an empty `imu`: only the visual-only
path (`--no-imu`) can run on it, and the stage says so.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from shared.calibration.kalibr import CameraCalibration, ImuNoise
from shared.formats.recordings import Frame, Keep, Recording, open_recording
from shared.imu import ImuCleaning, ImuSamples

__all__ = ["Frame", "SlamInput", "open_input"]


class SlamInput:
    """A recording SLAM runs on: its frames, its cleaned IMU and what it says of itself."""

    def __init__(self, recording: Recording) -> None:
        self.recording = recording
        self.imu: ImuSamples
        """All IMU samples (IMU clock), strictly increasing; empty without an IMU."""
        self.imu_cleaning: ImuCleaning
        """What was merged, dropped or interpolated to make `imu` (shared.imu)."""
        if recording.has_imu:
            self.imu, self.imu_cleaning = recording.imu()
        else:
            self.imu = ImuSamples(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
            self.imu_cleaning = ImuCleaning()

    @property
    def name(self) -> str:
        """What to call it in messages (the folder or file name)."""
        return self.recording.name

    @property
    def calibration(self) -> CameraCalibration | None:
        """Camera model, `cam_from_imu` and time shift, when the input carries them."""
        return self.recording.calibration

    @property
    def imu_noise(self) -> ImuNoise | None:
        """IMU noise densities, when the input carries them."""
        return self.recording.imu_noise

    @property
    def calibration_is_guess(self) -> bool:
        """Whether the calibration it carries is a nominal guess (not measured)."""
        return self.recording.calibration_is_guess

    @property
    def frame_count(self) -> int:
        """Number of images (for the progress bar; 0 when the container does not say)."""
        return self.recording.frame_count or 0

    def frames(self, *, min_step_ns: int = 0, keep: Keep | None = None) -> Iterator[Frame]:
        """Images in time order, as decoded (grey or BGR), PNG bytes kept as recorded;
        none closer than `min_step_ns` to the last one given (0: all), or those whose
        stamps `keep` passes; the others not decoded where the recording allows (see
        `shared.formats.recordings`)."""
        return self.recording.frames(min_step_ns=min_step_ns, keep=keep)


def open_input(path: Path | str) -> SlamInput:
    """The SLAM input at `path` (any kind `shared.formats.recordings` reads); InputError
    naming the path and the kinds expected otherwise."""
    return SlamInput(open_recording(path))
