"""`wreckmap-field gopro import`: GoPro chapters or a whole DCIM folder into session folders.

Registered from `field.commands.gopro.register` (the `gopro` group); heavy
imports happen in the handler.
"""

from __future__ import annotations

import argparse
from pathlib import Path

IMPORT_EXAMPLE = """\
examples:
  wreckmap-field gopro import GX010042.MP4 GX020042.MP4 --out sessions/dive1
  wreckmap-field gopro import /media/sd/DCIM --out sessions/

Files: the chapters of ONE recording -> the session folder --out.
A folder: every recording found under it -> one session per recording in
--out (named <creation time>_<GX0042>); recordings already imported are
skipped. Each session holds recording.mcap (video packets copied without
decoding + IMU), metadata.yaml (rosbag2), calib/ and session.yaml.
"""


def register_import(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the `import` sub-command to the `gopro` group's sub-parsers."""
    parser = commands.add_parser(
        "import",
        help="import GoPro chapters (or a DCIM folder) into session folders",
        epilog=IMPORT_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="VIDEO", help=".MP4 files or folders"
    )
    parser.add_argument("--out", required=True, type=Path, help="session folder (or parent folder)")
    parser.add_argument(
        "--medium", choices=("water", "air"), default="water",
        help="for the intrinsics guess: flat-port housing in water, or air (default water)",
    )  # fmt: skip
    parser.add_argument(
        "--camchain", type=Path, help="Kalibr camchain.yaml to use instead of a guess"
    )
    parser.add_argument(
        "--imu-yaml", type=Path, help="Kalibr imu.yaml to use instead of typical values"
    )
    parser.add_argument(
        "--parameter-sets", type=Path, metavar="MP4",
        help="finalised MP4 of the same camera mode, to salvage an unfinalised file alone",
    )  # fmt: skip
    parser.add_argument("--salvage-fps", type=float, help="frame rate (Hz) of a salvaged file")
    parser.add_argument(
        "--require-imu", action="store_true", help="fail when a chapter has no GPMF IMU data"
    )
    parser.add_argument(
        "--compression", choices=("none", "zstd", "lz4"), default="none",
        help="MCAP chunk compression (video does not compress; default none)",
    )  # fmt: skip
    parser.add_argument("--overwrite", action="store_true", help="replace existing sessions")
    parser.set_defaults(handler=_import)


def _import(args: argparse.Namespace) -> int:
    import sys

    from field.gopro.importer import ImportOptions, ImportResult, import_videos

    options = ImportOptions(
        medium=args.medium,
        camchain=args.camchain,
        imu_yaml=args.imu_yaml,
        parameter_sets_from=args.parameter_sets,
        salvage_fps=args.salvage_fps,
        require_imu=args.require_imu,
        compression=args.compression,
    )

    def report(result: ImportResult) -> None:
        if result.status == "imported":
            rate = result.duration_s / result.seconds if result.seconds else 0.0
            print(
                f"{result.session_dir}: imported {result.frames} frames, "
                f"{result.imu_samples} IMU samples, {result.duration_s:.1f} s of video "
                f"in {result.seconds:.1f} s ({rate:.0f}x real time)"
            )
            for line in result.warnings:
                print(f"  warning: {line}")
        elif result.status == "skipped":
            print(f"{result.session_dir}: already imported, skipped")
        else:
            print(f"{result.session_dir}: FAILED: {result.error}", file=sys.stderr)

    results = import_videos(
        options, args.inputs, args.out, overwrite=args.overwrite, on_result=report
    )
    return 1 if any(r.status == "failed" for r in results) else 0
