"""`wreckmap-post depth`: put a trajectory at its true depth with a dive computer's profile."""

from __future__ import annotations

import argparse
from pathlib import Path

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
    parser.add_argument(
        "--method",
        choices=("ours", "paper"),
        default="ours",
        help="ours: coarse search + robust Gauss-Newton; paper: 100 Hz cross-correlation",
    )
    parser.add_argument(
        "--time-offset",
        type=float,
        metavar="SECONDS",
        help="known clock offset (dive-computer minus camera time at the trajectory start): "
        "skips the search",
    )
    parser.add_argument(
        "--max-offset",
        type=float,
        default=15 * 3600.0,
        metavar="SECONDS",
        help="largest clock offset searched (default: 15 h, time-zone errors included)",
    )
    parser.add_argument("--no-drift", action="store_true", help="do not estimate clock drift")
    parser.add_argument(
        "--estimate-scale", action="store_true", help="estimate a depth scale (default: 1)"
    )
    parser.add_argument("--no-fuse", action="store_true", help="skip the depth-factor fusion")
    parser.add_argument("--no-plot", action="store_true", help="skip depth_sync.png")
    parser.add_argument(
        "--depth-sigma",
        type=float,
        metavar="METRES",
        help="one-sigma error of a depth sample (default: 0.058 m)",
    )
    parser.add_argument(
        "--clock-window",
        type=float,
        default=300.0,
        metavar="SECONDS",
        help="when the depth match alone is ambiguous, look for the offset within this "
        "distance of a whole time-zone step between the camera and dive-computer clocks "
        "(default: 300 s; 0 turns the prior off)",
    )
    parser.add_argument(
        "--min-evidence",
        type=float,
        default=6.0,
        help="how much better the chosen offset must fit than any clearly different one "
        "(log-likelihood ratio; default: 6)",
    )
    parser.add_argument(
        "--trajectory-format",
        choices=("auto", "tum", "svin"),
        default="auto",
        help="stamps of --trajectory: tum (decimal seconds), svin (SVIn2: seconds, '.', "
        "nanoseconds without zero padding) or auto (decided per file; default)",
    )
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_depth)


def _depth(args: argparse.Namespace) -> int:
    from postproc.depth.stage import DepthOptions, run

    options = DepthOptions(
        method=args.method,
        time_offset_s=args.time_offset,
        max_offset_s=args.max_offset,
        estimate_drift=not args.no_drift,
        estimate_scale=args.estimate_scale,
        fuse=not args.no_fuse,
        plot=not args.no_plot,
        clock_prior_window_s=args.clock_window if args.clock_window > 0 else None,
        min_evidence=args.min_evidence,
        trajectory_format=args.trajectory_format,
    )
    if args.depth_sigma is not None:
        options.depth_sigma_m = args.depth_sigma
    sync_path = run(options, args.trajectory, args.dive, args.out, overwrite=args.overwrite)
    print(sync_path)
    return 0
