"""Data passed between the SLAM modules: feature tracks of one frame, IMU samples.

Pure data, no I/O. Times are int64 nanoseconds since the UNIX epoch; image
stamps are on the camera clock as recorded, IMU stamps on the IMU clock
(Kalibr: t_imu = t_cam + timeshift_cam_imu).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.imu import ImuSamples

__all__ = ["FloatArray", "FrameTracks", "ImuSamples", "IntArray"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass
class FrameTracks:
    """Features of one image that survived tracking and outlier rejection.

    stamp_ns: image time (camera clock, int64 ns).
    track_ids: (N,) int64, a track keeps its id while it is tracked frame to frame.
    xy_normalised: (N, 2) undistorted normalised coordinates (x/z, y/z in the
        OpenCV camera frame), what the backend uses.
    pixels: (N, 2) distorted pixel positions in the frontend image (for the
        keyframe overlap test).
    image_size: (width, height) of the frontend image in pixels.
    """

    stamp_ns: int
    track_ids: IntArray
    xy_normalised: FloatArray
    pixels: FloatArray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        n = len(self.track_ids)
        if self.xy_normalised.shape != (n, 2) or self.pixels.shape != (n, 2):
            raise ValueError(
                f"FrameTracks: expected ({n}, 2) coordinates, got {self.xy_normalised.shape} "
                f"and {self.pixels.shape}"
            )
