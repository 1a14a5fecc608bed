"""Options of the pipeline's optional calibrate stage (needs `postproc.calibrate`).

Kept apart from `stages` because it imports the calibration stage's own option classes,
which exist only where that stage is built.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from postproc.calibrate.stage import CameraCalibrationOptions, ImuCalibrationOptions


@dataclass(kw_only=True)
class CalibrateOptions:
    """Options of the calibrate stage (`calibration.recording` in the project).

    camera: intrinsics from the AprilGrid views (CameraCalibrationOptions).
    imu: camera-IMU rotation and time shift (ImuCalibrationOptions).
    estimate_imu: also estimate the camera-IMU rotation and time shift (else the
        camera-only camchain is used).
    """

    camera: CameraCalibrationOptions = field(default_factory=CameraCalibrationOptions)
    imu: ImuCalibrationOptions = field(default_factory=ImuCalibrationOptions)
    estimate_imu: bool = True
