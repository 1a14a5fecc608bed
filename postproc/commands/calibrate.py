"""`wreckmap-post calibrate`: camera intrinsics, camera-IMU rotation and time shift, two rigs."""

from __future__ import annotations

import argparse
from pathlib import Path

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
    camera.add_argument(
        "--model",
        choices=("pinhole-radtan", "pinhole-equidistant"),
        default="pinhole-radtan",
        help="camera model (default: pinhole-radtan)",
    )
    camera.add_argument("--topic", help="camera topic of a session (default: /cam0/video)")
    camera.add_argument(
        "--max-frames", type=int, default=40, help="views used in the fit (default: 40)"
    )
    camera.add_argument(
        "--rate",
        type=float,
        default=4.0,
        metavar="HZ",
        help="frames examined per second of recording (default: 4; 0: every frame)",
    )
    camera.add_argument(
        "--fix-principal-point", action="store_true", help="keep cx, cy at the image centre"
    )
    camera.add_argument("--fix-aspect-ratio", action="store_true", help="fx = fy")
    camera.add_argument("--no-distortion", action="store_true", help="fit no distortion")
    camera.add_argument(
        "--min-views", type=int, default=3, help="fewest views accepted (default: 3)"
    )
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
    imu.add_argument("--camera", type=int, default=0, help="camera index in --calib (default 0)")
    imu.add_argument("--topic", help="camera topic of a session (default: /cam0/video)")
    imu.add_argument("--imu-topic", default="/imu0", help="IMU topic (default: /imu0)")
    imu.add_argument(
        "--max-timeshift",
        type=float,
        default=0.5,
        metavar="SECONDS",
        help="largest |time shift| searched (default: 0.5)",
    )
    imu.add_argument(
        "--no-features", action="store_true", help="use grid poses only, no feature tracks"
    )
    imu.add_argument(
        "--stride", type=int, default=1, metavar="N", help="use every Nth frame (default: 1)"
    )
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
    rig.add_argument("--imu-topic0", default="/imu0", help="rig 0's IMU topic (default /imu0)")
    rig.add_argument("--imu-topic1", default="/imu0", help="rig 1's IMU topic (default /imu0)")
    rig.add_argument(
        "--max-offset",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="largest |clock offset - prior| searched (default: 30)",
    )
    rig.add_argument(
        "--prior-offset",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="expected clock offset, rig 1 minus rig 0 (default: 0)",
    )
    rig.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    rig.set_defaults(handler=_rig)


def _camera(args: argparse.Namespace) -> int:
    from postproc.calibrate.frame_selection import FrameSelectionOptions
    from postproc.calibrate.intrinsics import IntrinsicsOptions
    from postproc.calibrate.stage import CameraCalibrationOptions, run_camera

    options = CameraCalibrationOptions(
        topic=args.topic,
        max_candidate_rate_hz=args.rate,
        selection=FrameSelectionOptions(max_frames=args.max_frames),
        intrinsics=IntrinsicsOptions(
            model=args.model,
            fix_principal_point=args.fix_principal_point,
            fix_aspect_ratio=args.fix_aspect_ratio,
            zero_distortion=args.no_distortion,
            min_views=args.min_views,
        ),
    )
    result = run_camera(options, args.source, args.target, args.out, overwrite=args.overwrite)
    print(result)
    return 0


def _imu(args: argparse.Namespace) -> int:
    from postproc.calibrate.camera_imu import CameraImuOptions
    from postproc.calibrate.stage import ImuCalibrationOptions, run_imu

    options = ImuCalibrationOptions(
        camera_index=args.camera,
        topic=args.topic,
        imu_topic=args.imu_topic,
        use_features=not args.no_features,
        frame_stride=args.stride,
        estimate=CameraImuOptions(max_timeshift_s=args.max_timeshift),
    )
    result = run_imu(
        options, args.recording, args.calib, args.target, args.out, overwrite=args.overwrite
    )
    print(result)
    return 0


def _rig(args: argparse.Namespace) -> int:
    from postproc.calibrate.stage import RigCalibrationOptions, run_rig
    from postproc.calibrate.two_camera import RigSyncOptions

    options = RigCalibrationOptions(
        imu_topic0=args.imu_topic0,
        imu_topic1=args.imu_topic1,
        sync=RigSyncOptions(max_offset_s=args.max_offset, prior_offset_s=args.prior_offset),
    )
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
