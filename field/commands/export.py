"""`wreckmap-field export`: a session folder as EuRoC, ROS 1 bag or ROS 2 bag."""

from __future__ import annotations

import argparse
from pathlib import Path

EXAMPLE = """\
examples:
  wreckmap-field export sessions/dive1 --format euroc --out dive1_euroc
  wreckmap-field export sessions/dive1 --format rosbag1 --out dive1.bag --compressed
  wreckmap-field export sessions/dive1 --format rosbag2 --out dive1_bag

euroc: mav0/cam0 PNGs (grey unless --color) + imu0/data.csv + sensor.yaml.
rosbag1: sensor_msgs/Image (or CompressedImage JPEG) + sensor_msgs/Imu.
rosbag2: the session's MCAP + metadata.yaml, hard-linked.
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "export",
        help="export a session for other tools (EuRoC, ROS 1 bag, ROS 2 bag)",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("session", type=Path, metavar="SESSION_DIR", help="session folder")
    parser.add_argument("--format", required=True, choices=("euroc", "rosbag1", "rosbag2"))
    parser.add_argument("--out", required=True, type=Path, help="output folder or .bag file")
    parser.add_argument("--color", action="store_true", help="BGR images instead of grey")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale factor (0-1]")
    parser.add_argument(
        "--compressed", action="store_true", help="rosbag1: JPEG CompressedImage, not raw Image"
    )
    parser.add_argument("--jpeg-quality", type=int, default=95, help="1-100 (with --compressed)")
    parser.add_argument("--video-topic", default="/cam0/video", help="session video topic")
    parser.add_argument("--imu-topic", default="/imu0", help="session IMU topic")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")
    parser.set_defaults(handler=_export)


def _export(args: argparse.Namespace) -> int:
    from field.export import ExportOptions, export_session

    options = ExportOptions(
        format=args.format,
        video_topic=args.video_topic,
        imu_topic=args.imu_topic,
        grayscale=not args.color,
        scale=args.scale,
        compressed=args.compressed,
        jpeg_quality=args.jpeg_quality,
    )
    path = export_session(options, args.session, args.out, overwrite=args.overwrite)
    print(f"{path}: written ({args.format})")
    return 0
