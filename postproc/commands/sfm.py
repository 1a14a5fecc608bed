"""`wreckmap-post sfm`: global bundle adjustment with COLMAP, seeded by the SLAM poses."""

from __future__ import annotations

import argparse
from pathlib import Path

from postproc.pipeline.options import Flag, add_flags_lazily, options_from_args

EXAMPLE = """\
example:
  wreckmap-post sfm results/dive1/slam --out results/dive1/sfm
  wreckmap-post sfm results/merge --out results/sfm            # merged sessions
  wreckmap-post sfm results/dive1/slam results/dive2/slam --out results/sfm \\
      --max-features 512 --max-image-size 960     # a faster, coarser run

Inputs are SLAM result folders (keyframes.tum, keyframes/, calib/camchain.yaml)
and/or one merge folder (transforms.json). Without a merge folder the first
session defines the world frame (at true depth when <dive>/depth/ is beside its
SLAM folder); sessions without a world pose are tied in by natural features
when they overlap. Writes sparse/0 (COLMAP binary model), sessions/<name>/
keyframes.tum (input's frame), transforms.json and stats.json.
No network access: no vocabulary tree or model is ever downloaded.
"""


# The flags of SfmOptions' fields (names kept from the first command line).
SFM_FLAGS = [
    Flag(field="features.max_num_features", flag="--max-features"),
    Flag(field="features.max_image_size_px", flag="--max-image-size", metavar="PX"),
    Flag(field="pairs.sequential_neighbours", flag="--sequential"),
    Flag(field="pairs.spatial_neighbours", flag="--spatial"),
    Flag(field="pairs.spatial_radius_m", flag="--spatial-radius", metavar="METRES"),
    Flag(field="prior_sigma_m", flag="--prior-sigma", metavar="METRES"),
    Flag(field="refine.mapper", flag="--mapper"),
    Flag(field="refine.refine_intrinsics", flag="--refine-intrinsics"),
    Flag(field="features.num_threads", flag="--threads", also=("refine.num_threads",)),
]


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "sfm",
        help="COLMAP bundle adjustment of the keyframes, seeded by the SLAM poses",
        description="Match the keyframes of every session (pairs chosen from the prior\n"
        "poses), triangulate at the SLAM poses and bundle-adjust with position priors.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="SLAM_OR_MERGE_DIR", help="input folders"
    )
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    # The stage's options: type, default, choices and help from SfmOptions itself.
    add_flags_lazily(parser, _options_type, SFM_FLAGS)
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_sfm)


def _options_type() -> type:
    from postproc.sfm.options import SfmOptions

    return SfmOptions


def _sfm(args: argparse.Namespace) -> int:
    from postproc.sfm.stage import run

    options = options_from_args(_options_type(), args, SFM_FLAGS)
    model = run(options, args.inputs, args.out, overwrite=args.overwrite)
    print(model)
    return 0
