"""`wreckmap-post slam`: keyframe visual-inertial SLAM of one recording."""

from __future__ import annotations

import argparse
from pathlib import Path

from postproc.pipeline.options import Flag, add_flags_lazily, options_from_args

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


# The flags of SlamOptions' fields (names kept from the first command line): --width is
# the frontend's width_px, --no-imu turns use_imu off, --max-speed 0 turns the check off.
SLAM_FLAGS = [
    Flag(field="frontend.width_px", flag="--width", metavar="PX"),
    Flag(field="use_imu", flag="--no-imu", negate=True),
    Flag(field="max_frames", metavar="N"),
    Flag(field="max_speed_m_s", flag="--max-speed", zero_is_none=True, metavar="M_S"),
    Flag(field="gyro_check"),
    Flag(field="estimator_process"),
]


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
    # The stage's options: type, default, choices and help from SlamOptions itself.
    add_flags_lazily(parser, _options_type, SLAM_FLAGS)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing result")
    parser.set_defaults(handler=_run)


def _options_type() -> type:
    from postproc.slam.options import SlamOptions

    return SlamOptions


def _run(args: argparse.Namespace) -> int:
    from postproc.slam.stage import run

    options = options_from_args(_options_type(), args, SLAM_FLAGS)
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
