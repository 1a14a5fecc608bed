"""`wreckmap-post merge`: several SLAM sessions in one frame through AprilGrid targets
and the structure they share."""

from __future__ import annotations

import argparse
from pathlib import Path

from postproc.pipeline.options import Flag, add_flags_lazily, options_from_args

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


# The flags of MergeOptions' fields (names kept from the first command line).
MERGE_FLAGS = [
    Flag(field="natural_features", flag="--natural-features", off_flag="--no-natural-features"),
    Flag(field="reference", metavar="NAME"),
    Flag(field="method"),
    Flag(field="dof"),
    Flag(field="depth_fused", flag="--depth-fused", off_flag="--no-depth-fused"),
    Flag(field="min_tags"),
    Flag(field="rotation_mean"),
    Flag(field="outlier_rule"),
    Flag(field="drift_weighting", flag="--no-drift-weighting", negate=True),
    Flag(field="tilt_sigma_deg"),
    Flag(field="camera"),
    Flag(field="plot", flag="--no-plot", negate=True),
]


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
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    # The stage's options: type, default, choices and help from MergeOptions itself.
    add_flags_lazily(parser, _options_type, MERGE_FLAGS)
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_merge)


def _options_type() -> type:
    from postproc.merge.options import MergeOptions

    return MergeOptions


def _merge(args: argparse.Namespace) -> int:
    from postproc.merge.stage import run

    options = options_from_args(_options_type(), args, MERGE_FLAGS)
    path = run(options, args.slam_dirs, args.targets, args.out, overwrite=args.overwrite)
    print(path)
    return 0
