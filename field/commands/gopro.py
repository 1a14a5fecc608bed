"""`wreckmap-field gopro`: GoPro MP4 files (telemetry now; import is added beside it)."""

from __future__ import annotations

import argparse
from pathlib import Path

TELEMETRY_EXAMPLE = """\
example:
  wreckmap-field gopro telemetry GX010042.MP4
  wreckmap-field gopro telemetry GX010042.MP4 --stream ACCL --csv accl.csv

The CSV has a header `t_s,v0,v1,v2`: media time in seconds from the start of
the video, then the values divided by SCAL, in the file's axis order and the
stream's units (ACCL m/s², GYRO rad/s).
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    group = subparsers.add_parser("gopro", help="GoPro MP4: telemetry (GPMF)")
    commands = group.add_subparsers(dest="gopro_command", metavar="GOPRO_COMMAND", required=True)
    telemetry = commands.add_parser(
        "telemetry",
        help="summarise the GPMF telemetry of a GoPro MP4 or export one stream as CSV",
        epilog=TELEMETRY_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    telemetry.add_argument("video", type=Path, metavar="VIDEO", help="GoPro .MP4 file")
    telemetry.add_argument("--stream", help="FourCC of the stream (ACCL, GYRO, GPS5, ...)")
    telemetry.add_argument("--csv", type=Path, metavar="OUT", help="write the stream to this CSV")
    telemetry.add_argument("--overwrite", action="store_true", help="replace an existing CSV")
    telemetry.set_defaults(handler=_telemetry)
    from field.commands.gopro_import import register_import

    register_import(commands)


def _telemetry(args: argparse.Namespace) -> int:
    from field.gopro.telemetry import format_summary, read_telemetry, write_telemetry_csv
    from shared.errors import InputError

    if args.csv is not None and not args.stream:
        raise InputError("--csv needs --stream (which stream to write, e.g. ACCL)")
    keys = {args.stream} if args.stream else None
    telemetry = read_telemetry(args.video, keys=keys)
    if args.stream:
        stream = telemetry.stream(args.stream)
        if args.csv is not None:
            path = write_telemetry_csv(stream, args.csv, overwrite=args.overwrite)
            print(f"{path}: {stream.samples} samples of {args.stream} at {stream.rate_hz:.3f} Hz")
            return 0
    print(format_summary(telemetry))
    return 0
