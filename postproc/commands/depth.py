"""`wreckmap-post depth`: put a trajectory at its true depth with a dive computer's profile."""

from __future__ import annotations

import argparse
from pathlib import Path

from postproc.pipeline.options import Flag, add_flags_lazily, options_from_args

EXAMPLE = """\
example:
  wreckmap-post depth --trajectory results/dive1/slam/trajectory.tum \\
      --dive dives/ --out results/dive1/depth
  wreckmap-post depth --trajectory orbslam3_f_dataset.txt --dive dive68.csv \\
      --out depth/ --time-offset 289.8        # known clock offset: no search
  wreckmap-post depth --trajectory svin/stamped_traj.txt --dive dives/ --out depth/

The trajectory is any TUM file (ours, SVIn2's with its unpadded nanoseconds,
ORB-SLAM3's) or OKVIS CSV in a gravity-aligned frame with z up, on the camera
clock; the depth found is that of the frame the file holds (body or camera
poses). --dive is one dive CSV or a dive folder
(the dive that overlaps the trajectory is chosen). Writes sync.json,
trajectory_world.tum, trajectory_world_fused.tum and depth_sync.png.
"""


# The flags of DepthOptions' fields (names kept from the first command line).
DEPTH_FLAGS = [
    Flag(field="method"),
    Flag(field="time_offset_s", flag="--time-offset", metavar="SECONDS"),
    Flag(field="max_offset_s", flag="--max-offset", metavar="SECONDS"),
    Flag(field="estimate_drift", flag="--no-drift", negate=True),
    Flag(field="estimate_scale", flag="--estimate-scale"),
    Flag(field="fuse", flag="--no-fuse", negate=True),
    Flag(field="plot", flag="--no-plot", negate=True),
    Flag(field="depth_sigma_m", flag="--depth-sigma", metavar="METRES"),
    Flag(field="clock_prior_window_s", flag="--clock-window", zero_is_none=True, metavar="SECONDS"),
    Flag(field="min_evidence"),
    Flag(field="trajectory_format"),
]


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "depth",
        help="dive-computer clock sync and true depth of a trajectory",
        description="Find the dive computer's clock offset and drift against the camera and\n"
        "the depth of the trajectory's origin; write the trajectory at its true depth\n"
        "and re-optimise it with depth factors.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--trajectory", required=True, type=Path, help="TUM, SVIn2 or OKVIS trajectory"
    )
    parser.add_argument("--dive", required=True, type=Path, help="dive CSV or dive folder")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    # The stage's options: type, default, choices and help from DepthOptions itself.
    add_flags_lazily(parser, _options_type, DEPTH_FLAGS)
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_depth)


def _options_type() -> type:
    from postproc.depth.options import DepthOptions

    return DepthOptions


def _depth(args: argparse.Namespace) -> int:
    from postproc.depth.stage import run

    options = options_from_args(_options_type(), args, DEPTH_FLAGS)
    sync_path = run(options, args.trajectory, args.dive, args.out, overwrite=args.overwrite)
    print(sync_path)
    return 0
