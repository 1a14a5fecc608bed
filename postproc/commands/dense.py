"""`wreckmap-post dense`: depth maps, fusion and a mesh from an SfM model."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from postproc.pipeline.options import Flag, add_flags_lazily, options_from_args

if TYPE_CHECKING:
    from postproc.dense.options import DenseOptions

EXAMPLE = """\
example:
  wreckmap-post dense results/dive1/sfm --out results/dive1/dense
  wreckmap-post dense results/dive1/sfm --out dense/ --max-image-size 640 \\
      --colour-correction --attenuation 0.40 0.13 0.11

Reads the COLMAP model in SFM_DIR (sparse/, model/ or the folder itself) and its
images (SFM_DIR/images or SFM_DIR/keyframes, or --images). Depth maps come from
COLMAP PatchMatch when pycolmap has CUDA, else from CPU stereo. Writes workspace/
(COLMAP dense workspace), fused.ply, mesh.ply and dense.json; an interrupted run
resumes where it stopped. A known --attenuation implies --colour-correction.
"""


# The flags of DenseOptions' fields (names kept from the first command line): --images is
# image_dir, --no-mesh turns make_mesh off, --threads sets both fusion's and meshing's
# threads. One more alias in `_dense`: a known --attenuation turns --colour-correction on.
DENSE_FLAGS = [
    Flag(field="image_dir", flag="--images", metavar="DIR"),
    Flag(field="max_image_size_px", flag="--max-image-size", metavar="PX"),
    Flag(field="backend"),
    Flag(field="meshing.octree_depth", metavar="N"),
    Flag(field="make_mesh", flag="--no-mesh", negate=True),
    Flag(field="colour_correction"),
    Flag(field="colour.attenuation_per_m", flag="--attenuation", metavar=("R", "G", "B")),
    Flag(field="colour.backscatter", metavar=("R", "G", "B")),
    Flag(field="fusion.num_threads", flag="--threads", also=("meshing.num_threads",), metavar="N"),
]


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "dense",
        help="dense point cloud and mesh from an SfM model",
        description="Undistort, compute depth maps (GPU PatchMatch or CPU stereo), fuse\n"
        "them with COLMAP and mesh the points (screened Poisson, trimmed).",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("sfm_dir", type=Path, metavar="SFM_DIR", help="SfM output folder")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    # The stage's options: type, default, choices and help from DenseOptions itself.
    add_flags_lazily(parser, _options_type, DENSE_FLAGS)
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_dense)


def _options_type() -> type:
    from postproc.dense.options import DenseOptions

    return DenseOptions


def dense_options(args: argparse.Namespace) -> DenseOptions:
    """The DenseOptions of the parsed flags; a known attenuation means colour correction
    (the flag's help says so), as on the first command line."""
    options: DenseOptions = options_from_args(_options_type(), args, DENSE_FLAGS)
    if options.colour.attenuation_per_m is not None:
        options = dataclasses.replace(options, colour_correction=True)
    return options


def _dense(args: argparse.Namespace) -> int:
    from postproc.dense.stage import run

    result = run(dense_options(args), args.sfm_dir, args.out, overwrite=args.overwrite)
    print(result)
    return 0
