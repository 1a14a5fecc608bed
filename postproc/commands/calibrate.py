"""`wreckmap-post calibrate`: camera intrinsics, camera-IMU rotation and time shift, two rigs."""

from __future__ import annotations

import argparse
from pathlib import Path

from postproc.pipeline.options import Flag, add_flags_lazily, options_from_args

EXAMPLE = """\
example:
  wreckmap-post calibrate camera sessions/calib1 --target aprilgrid.yaml --out calib/
  wreckmap-post calibrate imu sessions/calib1 --calib calib/camchain.yaml \\
      --target aprilgrid.yaml --out calib/
  wreckmap-post calibrate rig sessions/left sessions/right \\
      --calib0 left/camchain-imucam.yaml --calib1 right/camchain-imucam.yaml --out rig/

camera: AprilGrid views of a session folder (MCAP), an EuRoC folder, a folder of
images or a video file -> camchain.yaml, camera_calibration.json, coverage.png.
imu: the recording's camera and IMU -> camchain-imucam.yaml (T_cam_imu rotation and
timeshift_cam_imu; translation kept from --calib), camera_imu.json, camera_imu.png.
rig: two rigs' IMU streams -> camchain-rig.yaml (both cameras on rig 0's IMU frame
and clock) and rig.json.
"""


# The flags of each calibration's options (names kept from the first command lines):
# camera's --rate is max_candidate_rate_hz, --no-distortion sets intrinsics.zero_distortion;
# imu's --camera is camera_index, --no-features turns use_features off, --stride is
# frame_stride; rig's offsets are those of its sync estimate.
CAMERA_FLAGS = [
    Flag(field="intrinsics.model"),
    Flag(field="topic"),
    Flag(field="selection.max_frames", metavar="N"),
    Flag(field="max_candidate_rate_hz", flag="--rate", metavar="HZ"),
    Flag(field="intrinsics.fix_principal_point"),
    Flag(field="intrinsics.fix_aspect_ratio"),
    Flag(field="intrinsics.zero_distortion", flag="--no-distortion"),
    Flag(field="intrinsics.min_views", metavar="N"),
]
IMU_FLAGS = [
    Flag(field="camera_index", flag="--camera", metavar="INDEX"),
    Flag(field="topic"),
    Flag(field="imu_topic"),
    Flag(field="estimate.max_timeshift_s", flag="--max-timeshift", metavar="SECONDS"),
    Flag(field="use_features", flag="--no-features", negate=True),
    Flag(field="frame_stride", flag="--stride", metavar="N"),
]
RIG_FLAGS = [
    Flag(field="imu_topic0"),
    Flag(field="imu_topic1"),
    Flag(field="sync.max_offset_s", flag="--max-offset", metavar="SECONDS"),
    Flag(field="sync.prior_offset_s", flag="--prior-offset", metavar="SECONDS"),
]


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="camera, camera-IMU and two-rig calibration (Kalibr YAML out)",
        description="Calibrate without ROS: intrinsics from AprilGrid views, the camera-IMU\n"
        "rotation and time shift from a recording, and two unsynchronised rigs.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="calibrate_command", metavar="WHAT", required=True)

    camera = commands.add_parser(
        "camera",
        help="intrinsics from AprilGrid views",
        description="Select well-spread sharp views of the grid, fit the camera model and\n"
        "write a Kalibr camchain.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    camera.add_argument(
        "source", type=Path, metavar="SESSION_OR_VIDEO", help="session, EuRoC, images or video"
    )
    camera.add_argument("--target", required=True, type=Path, help="Kalibr AprilGrid YAML")
    camera.add_argument("--out", required=True, type=Path, help="output folder")
    add_flags_lazily(camera, _camera_options_type, CAMERA_FLAGS)
    camera.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    camera.set_defaults(handler=_camera)

    imu = commands.add_parser(
        "imu",
        help="camera-IMU rotation and time shift from a recording",
        description="Align the camera's rotations with the gyro's: coarse time shift from the\n"
        "rate magnitudes, then rotation, shift and gyro bias by least squares.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    imu.add_argument("recording", type=Path, metavar="SESSION", help="session or EuRoC folder")
    imu.add_argument("--calib", required=True, type=Path, help="camchain.yaml of the camera")
    imu.add_argument("--out", required=True, type=Path, help="output folder")
    imu.add_argument(
        "--target", type=Path, help="AprilGrid YAML when the grid is filmed (else features)"
    )
    add_flags_lazily(imu, _imu_options_type, IMU_FLAGS)
    imu.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    imu.set_defaults(handler=_imu)

    rig = commands.add_parser(
        "rig",
        help="clock offset and rotation between two rigs from their IMUs",
        description="Two cameras with their own IMUs on one mount: the clock offset from the\n"
        "gyros' rate magnitudes, refined to sub-sample, and the rotation between them.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rig.add_argument("recording0", type=Path, metavar="SESSION0", help="rig 0's recording")
    rig.add_argument("recording1", type=Path, metavar="SESSION1", help="rig 1's recording")
    rig.add_argument("--calib0", required=True, type=Path, help="rig 0's camchain")
    rig.add_argument("--calib1", required=True, type=Path, help="rig 1's camchain")
    rig.add_argument("--out", required=True, type=Path, help="output folder")
    add_flags_lazily(rig, _rig_options_type, RIG_FLAGS)
    rig.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    rig.set_defaults(handler=_rig)


def _camera_options_type() -> type:
    from postproc.calibrate.options import CameraCalibrationOptions

    return CameraCalibrationOptions


def _imu_options_type() -> type:
    from postproc.calibrate.options import ImuCalibrationOptions

    return ImuCalibrationOptions


def _rig_options_type() -> type:
    from postproc.calibrate.options import RigCalibrationOptions

    return RigCalibrationOptions


def _camera(args: argparse.Namespace) -> int:
    from postproc.calibrate.stage import run_camera

    options = options_from_args(_camera_options_type(), args, CAMERA_FLAGS)
    result = run_camera(options, args.source, args.target, args.out, overwrite=args.overwrite)
    print(result)
    return 0


def _imu(args: argparse.Namespace) -> int:
    from postproc.calibrate.stage import run_imu

    options = options_from_args(_imu_options_type(), args, IMU_FLAGS)
    result = run_imu(
        options, args.recording, args.calib, args.target, args.out, overwrite=args.overwrite
    )
    print(result)
    return 0


def _rig(args: argparse.Namespace) -> int:
    from postproc.calibrate.stage import run_rig

    options = options_from_args(_rig_options_type(), args, RIG_FLAGS)
    result = run_rig(
        options,
        args.recording0,
        args.recording1,
        args.calib0,
        args.calib1,
        args.out,
        overwrite=args.overwrite,
    )
    print(result)
    return 0
