"""`wreckmap-post dense`: depth maps, fusion and a mesh from an SfM model."""

from __future__ import annotations

import argparse
from pathlib import Path

EXAMPLE = """\
example:
  wreckmap-post dense results/dive1/sfm --out results/dive1/dense
  wreckmap-post dense results/dive1/sfm --out dense/ --max-image-size 640 \\
      --colour-correction --attenuation 0.40 0.13 0.11

Reads the COLMAP model in SFM_DIR (sparse/, model/ or the folder itself) and its
images (SFM_DIR/images or SFM_DIR/keyframes, or --images). Depth maps come from
COLMAP PatchMatch when pycolmap has CUDA, else from CPU stereo. Writes workspace/
(COLMAP dense workspace), fused.ply, mesh.ply and dense.json; an interrupted run
resumes where it stopped.
"""


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
    parser.add_argument("--images", type=Path, help="folder of the images the model names")
    parser.add_argument(
        "--max-image-size",
        type=int,
        default=960,
        metavar="PX",
        help="longest side of the undistorted images and depth maps (default: 960)",
    )
    parser.add_argument(
        "--backend",
        choices=("auto", "cpu", "patchmatch"),
        default="auto",
        help="depth maps: auto (PatchMatch when pycolmap has CUDA, else CPU), cpu, patchmatch",
    )
    parser.add_argument(
        "--octree-depth", type=int, metavar="N", help="Poisson octree depth (default: from scene)"
    )
    parser.add_argument("--no-mesh", action="store_true", help="stop after fused.ply")
    parser.add_argument(
        "--colour-correction",
        action="store_true",
        help="also write fused_corrected.ply (attenuation removed) and mesh it",
    )
    parser.add_argument(
        "--attenuation",
        type=float,
        nargs=3,
        metavar=("R", "G", "B"),
        help="known attenuation per channel (1/m); default: estimated from the points",
    )
    parser.add_argument(
        "--backscatter",
        type=float,
        nargs=3,
        metavar=("R", "G", "B"),
        help="known veiling light per channel (linear 0..1; with --attenuation)",
    )
    parser.add_argument("--threads", type=int, default=-1, help="worker threads (-1: all cores)")
    parser.add_argument("--overwrite", action="store_true", help="redo and replace outputs")
    parser.set_defaults(handler=_dense)


def _dense(args: argparse.Namespace) -> int:
    from postproc.dense.colour import ColourOptions
    from postproc.dense.fusion import FusionOptions
    from postproc.dense.meshing import MeshingOptions
    from postproc.dense.stage import DenseOptions, run

    options = DenseOptions(
        max_image_size_px=args.max_image_size,
        backend=args.backend,
        image_dir=args.images,
        make_mesh=not args.no_mesh,
        colour_correction=args.colour_correction or args.attenuation is not None,
        colour=ColourOptions(
            attenuation_per_m=tuple(args.attenuation) if args.attenuation else None,
            backscatter=tuple(args.backscatter) if args.backscatter else None,
        ),
        fusion=FusionOptions(num_threads=args.threads),
        meshing=MeshingOptions(octree_depth=args.octree_depth, num_threads=args.threads),
    )
    result = run(options, args.sfm_dir, args.out, overwrite=args.overwrite)
    print(result)
    return 0
