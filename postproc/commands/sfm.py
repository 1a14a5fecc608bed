"""`wreckmap-post sfm`: global bundle adjustment with COLMAP, seeded by the SLAM poses."""

from __future__ import annotations

import argparse
from pathlib import Path

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
    parser.add_argument(
        "--max-features", type=int, help="SIFT features per image (default 512)"
    )
    parser.add_argument(
        "--max-image-size",
        type=int,
        metavar="PX",
        help="longer image side for feature extraction, px (default 640)",
    )
    parser.add_argument(
        "--sequential", type=int, help="sequential neighbours per keyframe (default 3)"
    )
    parser.add_argument(
        "--spatial", type=int, help="spatial/loop partners per keyframe (default 4)"
    )
    parser.add_argument(
        "--spatial-radius",
        type=float,
        metavar="METRES",
        help="distance between viewed points of spatial partners, m (default 1.5)",
    )
    parser.add_argument(
        "--prior-sigma",
        type=float,
        metavar="METRES",
        help="fixed one-sigma error of the position priors (default: derived from drift)",
    )
    parser.add_argument(
        "--mapper",
        choices=("auto", "prior", "incremental"),
        default="auto",
        help="prior: triangulate + BA from the priors; incremental: COLMAP's mapper with "
        "priors; auto: prior, incremental if too few keyframes end up in the model",
    )
    parser.add_argument("--refine-intrinsics", action="store_true", help="adjust the cameras too")
    parser.add_argument("--threads", type=int, default=-1, help="worker threads (-1: all cores)")
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_sfm)


def _sfm(args: argparse.Namespace) -> int:
    from postproc.sfm.features import FeatureOptions
    from postproc.sfm.pairs import PairOptions
    from postproc.sfm.refine import RefineOptions
    from postproc.sfm.stage import SfmOptions, run
    from shared.errors import InputError

    try:
        options = SfmOptions(
            features=FeatureOptions(
                **_given(
                    max_num_features=args.max_features,
                    max_image_size_px=args.max_image_size,
                    num_threads=args.threads,
                )
            ),
            pairs=PairOptions(
                **_given(
                    sequential_neighbours=args.sequential,
                    spatial_neighbours=args.spatial,
                    spatial_radius_m=args.spatial_radius,
                )
            ),
            refine=RefineOptions(
                mapper=args.mapper,
                refine_intrinsics=args.refine_intrinsics,
                num_threads=args.threads,
            ),
            prior_sigma_m=args.prior_sigma,
        )
    except ValueError as error:
        raise InputError(f"sfm: {error}") from error
    model = run(options, args.inputs, args.out, overwrite=args.overwrite)
    print(model)
    return 0


def _given(**options: object) -> dict[str, object]:
    """The options given on the command line (None: keep the stage's default)."""
    return {name: value for name, value in options.items() if value is not None}
