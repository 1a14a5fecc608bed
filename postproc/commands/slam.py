"""`wreckmap-post slam`: keyframe visual-inertial SLAM of one recording."""

from __future__ import annotations

import argparse
from pathlib import Path

EXAMPLE = """\
example:
  wreckmap-post slam sessions/dive1 --out results/dive1/slam
  wreckmap-post slam euroc/MH_01 --out slam_mh01 --calib camchain.yaml --imu imu.yaml

INPUT is an EuRoC folder (mav0/cam0, mav0/imu0) or a session folder
(recording.mcap, calib/). Writes trajectory.tum (body poses at every image),
keyframes.tum (camera poses of keyframes), keyframes/<ns>.png, calib/,
map.ply and stats.json, in a gravity-aligned frame (z up) whose origin is the
first keyframe.
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "slam",
        help="keyframe visual-inertial SLAM (trajectory, keyframes, sparse map)",
        description="Track features, select keyframes and estimate a metric trajectory\n"
        "with IMU preintegration and visual factors (GTSAM, ISAM2).",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("input", type=Path, metavar="INPUT", help="EuRoC or session folder")
    parser.add_argument("--out", required=True, type=Path, help="SLAM result folder to write")
    parser.add_argument("--calib", type=Path, help="Kalibr camchain.yaml (overrides the input's)")
    parser.add_argument("--imu", type=Path, help="Kalibr imu.yaml (overrides the input's)")
    parser.add_argument(
        "--width",
        type=int,
        default=960,
        help="frontend image width, px; wider images are shrunk (0: as recorded)",
    )
    parser.add_argument(
        "--no-imu",
        action="store_true",
        help="visual-only baseline (arbitrary scale, not gravity-aligned)",
    )
    parser.add_argument("--max-frames", type=int, help="stop after this many images")
    parser.add_argument(
        "--max-speed",
        type=float,
        default=10.0,
        help="m/s between keyframes above which the estimate counts as diverged (0: no check)",
    )
    parser.add_argument(
        "--gyro-check",
        choices=("auto", "on", "off"),
        default="auto",
        help="compare the images' rotation with the gyro first: fixes a guessed focal length "
        "and time shift, and detects stabilised video (auto: only when the calibration is "
        "a guess)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing result")
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from postproc.slam.frontend import FrontendOptions
    from postproc.slam.stage import SlamOptions, run

    options = SlamOptions(
        frontend=FrontendOptions(width_px=args.width),
        use_imu=not args.no_imu,
        max_frames=args.max_frames,
        max_speed_m_s=args.max_speed if args.max_speed > 0 else None,
        gyro_check=args.gyro_check,
    )
    out = run(
        options,
        args.input,
        args.out,
        camchain=args.calib,
        imu_yaml=args.imu,
        overwrite=args.overwrite,
    )
    print(out)
    return 0
