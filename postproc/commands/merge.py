"""`wreckmap-post merge`: several SLAM sessions in one frame through AprilGrid targets
and the structure they share."""

from __future__ import annotations

import argparse
from pathlib import Path

EXAMPLE = """\
example:
  wreckmap-post merge results/dive1/slam results/dive2/slam \\
      --targets targets/bow.yaml targets/midship.yaml --out results/merged
  wreckmap-post merge dive1/ dive2/ --targets bow.yaml --out merged/ --method paper
  wreckmap-post merge dive1/slam dive2/slam --out merged/      # no targets: the wreck itself

Each target is a Kalibr AprilGrid YAML plus `tagIdOffset` (the id of its
first tag) when two grids share the wreck; the file stem names the target.
The first folder (or --reference) defines the common frame W. Sessions with a
depth stage output beside them (depth/trajectory_world_fused.tum) are aligned
in 4 DoF (x, y, z, yaw), others in 6 DoF. Writes transforms.json (T_W_S and
its 6x6 covariance per session), targets.json, <session>/keyframes_merged.tum,
merge_top.png and merge_side.png. Every pair of sessions is also matched
through the structure both filmed (keyframe features, a vocabulary built from
the sessions, PnP with gravity, a consistency check), and all constraints
(targets, feature matches, gravity, depth) are solved together; transforms.json
then lists the evidence per pair and the residual per constraint. A session
with no chain of targets or consistent matches to the reference is reported
with "placed": false and the evidence; it is never merged on a guess.
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "merge",
        help="put several sessions into one frame through targets and shared structure",
        description="Detect AprilGrid targets in the keyframes of every session, average\n"
        "their poses robustly, match the sessions through the structure they share and\n"
        "estimate each session's pose in a common frame from all constraints together.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("slam_dirs", nargs="+", type=Path, metavar="SLAM_DIR")
    parser.add_argument(
        "--targets",
        nargs="*",
        default=[],
        type=Path,
        metavar="TARGET_YAML",
        help="Kalibr AprilGrid YAMLs (with tagIdOffset for a second grid); optional with "
        "natural features",
    )
    features = parser.add_mutually_exclusive_group()
    features.add_argument(
        "--no-natural-features",
        action="store_true",
        help="targets only, placed session by session (no matching through the wreck itself)",
    )
    features.add_argument(
        "--natural-features",
        action="store_true",
        help="always match through the wreck and estimate jointly with the targets (default: "
        "only when the targets leave a session unplaced or none are given)",
    )
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument(
        "--reference", metavar="NAME", help="session (folder name) that defines W (default: first)"
    )
    parser.add_argument(
        "--method",
        choices=("ours", "paper"),
        default="ours",
        help="ours: whole-grid PnP, robust SE(3) mean, weighted alignment; "
        "paper: per-tag poses, one-sigma rejection, Euler means",
    )
    parser.add_argument(
        "--dof",
        choices=("auto", "4", "6"),
        default="auto",
        help="alignment degrees of freedom (auto: 4 for depth-fused sessions, else 6)",
    )
    fused = parser.add_mutually_exclusive_group()
    fused.add_argument(
        "--depth-fused",
        dest="depth_fused",
        action="store_true",
        default=None,
        help="require the depth stage's world trajectories (default: use them if all have one)",
    )
    fused.add_argument(
        "--no-depth-fused",
        dest="depth_fused",
        action="store_false",
        help="ignore depth stage outputs",
    )
    parser.add_argument(
        "--min-tags", type=int, default=2, help="fewest tags of a target in a keyframe (default 2)"
    )
    parser.add_argument(
        "--rotation-mean",
        choices=("chordal", "quaternion"),
        default="chordal",
        help="rotation averaging (default: chordal L2)",
    )
    parser.add_argument(
        "--outlier-rule",
        choices=("mad", "chi2"),
        default="mad",
        help="outlier rejection of observations (default: median/MAD)",
    )
    parser.add_argument(
        "--no-drift-weighting",
        action="store_true",
        help="average a target's passes equally instead of leaning on the passes nearest the "
        "session start (drift weighting, the default, places the session frame best; equal "
        "weights overlay the sessions best at the targets)",
    )
    parser.add_argument(
        "--tilt-sigma-deg",
        type=float,
        default=None,
        help="roll/pitch error (1-sigma, deg) of each session's gravity alignment: fit 6 DoF "
        "with that prior on the relative tilt instead of 4 DoF (default: 4 DoF when "
        "depth-fused)",
    )
    parser.add_argument("--camera", default="cam0", help="camchain entry of the keyframes")
    parser.add_argument("--no-plot", action="store_true", help="skip the PNG views")
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_merge)


def _merge(args: argparse.Namespace) -> int:
    from postproc.merge.stage import MergeOptions, run

    options = MergeOptions(
        method=args.method,
        reference=args.reference,
        dof="auto" if args.dof == "auto" else int(args.dof),
        depth_fused=args.depth_fused,
        min_tags=args.min_tags,
        rotation_mean=args.rotation_mean,
        outlier_rule=args.outlier_rule,
        drift_weighting=not args.no_drift_weighting,
        tilt_sigma_deg=args.tilt_sigma_deg,
        natural_features=(
            False if args.no_natural_features else True if args.natural_features else "auto"
        ),
        camera=args.camera,
        plot=not args.no_plot,
    )
    path = run(options, args.slam_dirs, args.targets, args.out, overwrite=args.overwrite)
    print(path)
    return 0
