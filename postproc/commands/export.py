"""`wreckmap-post export`: a finished run in the formats other tools open."""

from __future__ import annotations

import argparse
from pathlib import Path

FORMAT_NAMES = ("glb", "gltf", "las", "laz", "colmap-text", "nerfstudio", "camera-csv", "ortho")

EXAMPLE = """\
example:
  wreckmap-post export results/survey --format glb laz ortho --out results/survey/export
  wreckmap-post export results/survey --format ortho --resolution-m 0.02 \\
      --georef-target grid_a --easting-m 512345.2 --northing-m 6543210.8 --epsg 32633

RUN is a `wreckmap-post run` output folder (sfm/, dense/, merge/ inside) or an SfM or
dense stage folder. Writes into OUT (default RUN/export): mesh.glb or mesh.gltf
(+ mesh.bin), points.las or points.laz, colmap/ (text model + images), nerfstudio/
(transforms.json + images), camera_reference/ (cameras.csv with omega/phi/kappa and
accuracies, calibration.xml, undistorted images for Metashape and RealityCapture),
ortho/ (ortho.tif, dem.tif GeoTIFFs, PNG previews with a scale bar, ortho.json).
Without --georef-target the rasters are in the run's local metric frame; with it, the
target's world position is put at EASTING, NORTHING of EPSG, and world x is taken to
point east unless --heading-deg gives its bearing.
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "export",
        help="glTF, LAS/LAZ, COLMAP text, nerfstudio, camera CSV, orthophoto and DEM",
        description="Write a finished run in the formats of Metashape, RealityCapture,\n"
        "CloudCompare, MeshLab, QGIS, Blender and nerfstudio/gsplat.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("run_dir", type=Path, metavar="RUN", help="run output folder")
    parser.add_argument(
        "--format", nargs="+", required=True, choices=FORMAT_NAMES, dest="formats",
        metavar="FORMAT", help=f"one or more of: {', '.join(FORMAT_NAMES)}",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, help="output folder (default: RUN/export)")
    parser.add_argument(
        "--resolution-m", type=float, default=0.01, metavar="M",
        help="ortho/DEM ground resolution in metres (default: 0.01)",
    )  # fmt: skip
    parser.add_argument("--georef-target", metavar="NAME", help="merge target with a map position")
    parser.add_argument("--easting-m", type=float, help="the target's easting (metres)")
    parser.add_argument("--northing-m", type=float, help="the target's northing (metres)")
    parser.add_argument("--epsg", type=int, help="EPSG code of the projected CRS (e.g. UTM)")
    parser.add_argument(
        "--heading-deg", type=float,
        help="bearing of world x, degrees clockwise from grid north (default: assumed 90)",
    )  # fmt: skip
    parser.add_argument("--overwrite", action="store_true", help="replace existing exports")
    parser.set_defaults(handler=_export)


def _export(args: argparse.Namespace) -> int:
    from postproc.export.ortho import Georeference
    from postproc.export.stage import ExportOptions, OrthoOptions, export_formats
    from shared.errors import InputError

    georef = None
    if args.georef_target is not None:
        if args.easting_m is None or args.northing_m is None or args.epsg is None:
            raise InputError("--georef-target needs --easting-m, --northing-m and --epsg")
        georef = Georeference(
            target=args.georef_target,
            easting_m=args.easting_m,
            northing_m=args.northing_m,
            epsg=args.epsg,
            heading_deg=args.heading_deg,
        )
    if not args.resolution_m > 0:
        raise InputError(f"--resolution-m must be positive, got {args.resolution_m}")
    options = ExportOptions(
        formats=tuple(args.formats),
        ortho=OrthoOptions(resolution_m=args.resolution_m, georeference=georef),
    )
    out = args.out if args.out is not None else args.run_dir / "export"
    written = export_formats(options, args.run_dir, out, overwrite=args.overwrite)
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0
