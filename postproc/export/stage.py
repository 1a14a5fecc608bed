"""`run(options, run_dir, out_dir)`: every export asked for, from a finished run.

Formats (`FORMATS`, name -> writer; each writes one entry under `out_dir`):

- `glb`, `gltf`: `mesh.glb`, `mesh.gltf` + `mesh.bin` (the full mesh, vertex colours);
- `las`, `laz`: `points.las`, `points.laz` (the fused points, 1 mm steps, RGB);
- `colmap-text`: `colmap/` (`sparse/0/*.txt`, `images/`);
- `nerfstudio`: `nerfstudio/` (`transforms.json`, `images/`, `sparse_pc.ply`);
- `camera-csv`: `camera_reference/` (`cameras.csv`, `calibration.xml`, undistorted
  `images/`) for Metashape and RealityCapture;
- `ortho`: `ortho/` (`ortho.tif`, `dem.tif`, `ortho.png`, `dem.png`, `ortho.json`).

Nothing already there is overwritten unless `overwrite`; each entry is written under a
temporary name and renamed.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from postproc.export.camera_reference import ReferenceOptions
from postproc.export.ortho import Georeference
from postproc.export.run_folder import RunFolder, find_run
from shared.errors import InputError
from shared.folders import MergeFolder

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class OrthoOptions:
    """resolution_m: ground size of a raster cell (metres, default 1 cm); georeference:
    put the rasters on a map (None: the run's local frame); preview_max_px: longest side
    of the PNG previews."""

    resolution_m: float = 0.01
    georeference: Georeference | None = None
    preview_max_px: int = 1600

    def __post_init__(self) -> None:
        if not self.resolution_m > 0:
            raise ValueError(f"resolution_m must be positive, got {self.resolution_m}")


@dataclass(kw_only=True)
class ExportOptions:
    """formats: names from `FORMATS`; ortho, reference: options of those exports."""

    formats: Sequence[str] = ("glb",)
    ortho: OrthoOptions = field(default_factory=OrthoOptions)
    reference: ReferenceOptions = field(default_factory=ReferenceOptions)

    def __post_init__(self) -> None:
        unknown = [f for f in self.formats if f not in FORMATS]
        if unknown or not self.formats:
            raise ValueError(
                f"unknown export format {', '.join(unknown) or '(none)'} "
                f"(expected some of {', '.join(FORMATS)})"
            )


def export_mesh(
    options: ExportOptions, run: RunFolder, out: Path, suffix: str, overwrite: bool
) -> Path:
    from postproc.export.gltf import write_mesh_gltf
    from shared.formats.ply import read_ply

    path = run.need_mesh()
    mesh = read_ply(path)
    if mesh.faces is None or len(mesh.faces) == 0:
        raise InputError(f"{path}: no faces (expected a triangle mesh)")
    return write_mesh_gltf(out / f"mesh{suffix}", mesh.vertices, mesh.faces, mesh.colors,
                           overwrite=overwrite)  # fmt: skip


def export_points(
    options: ExportOptions, run: RunFolder, out: Path, suffix: str, overwrite: bool
) -> Path:
    from postproc.export.las import write_points_las
    from shared.formats.ply import read_ply

    cloud = read_ply(run.need_fused())
    return write_points_las(out / f"points{suffix}", cloud.vertices, cloud.colors,
                            overwrite=overwrite)  # fmt: skip


def export_colmap(
    options: ExportOptions, run: RunFolder, out: Path, suffix: str, overwrite: bool
) -> Path:
    from postproc.export.colmap_text import write_colmap_text

    return write_colmap_text(run.need_model(), run.need_images(), out / "colmap",
                             overwrite=overwrite)  # fmt: skip


def export_nerfstudio(
    options: ExportOptions, run: RunFolder, out: Path, suffix: str, overwrite: bool
) -> Path:
    from postproc.export.nerfstudio import write_nerfstudio

    return write_nerfstudio(run.need_model(), run.need_images(), out / "nerfstudio",
                            overwrite=overwrite)  # fmt: skip


def export_reference(
    options: ExportOptions, run: RunFolder, out: Path, suffix: str, overwrite: bool
) -> Path:
    from postproc.export.camera_reference import write_camera_reference

    return write_camera_reference(run.need_model(), run.need_images(),
                                  out / "camera_reference", options.reference,
                                  overwrite=overwrite)  # fmt: skip


def target_position_m(targets_json: Path | None, name: str) -> np.ndarray:
    """World position (3,) m of merge target `name` (its `T_W_m` translation)."""
    if targets_json is None:
        raise InputError(f"georeference: no merge/targets.json to find target {name!r} in")
    document = MergeFolder(targets_json.parent).read_targets()
    try:
        pose = np.asarray(document[name]["T_W_m"], float)
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(
            f"{targets_json}: no world pose T_W_m for target {name!r} ({error})"
        ) from error
    if pose.shape != (4, 4):
        raise InputError(f"{targets_json}: T_W_m of {name!r} is not 4x4")
    return pose[:3, 3]


def write_ortho(
    options: OrthoOptions,
    mesh_ply: Path,
    out_dir: Path,
    *,
    targets_json: Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Orthophoto and DEM of the mesh into `out_dir` (see `postproc.export.ortho`);
    returns `out_dir/ortho.tif`."""
    from postproc.export import ortho
    from shared.formats.ply import read_ply
    from shared.fsutil import atomic_path

    mesh = read_ply(mesh_ply)
    if mesh.faces is None or len(mesh.faces) == 0:
        raise InputError(f"{mesh_ply}: no faces (expected a triangle mesh)")
    georef = options.georeference
    position = target_position_m(targets_json, georef.target) if georef else None
    to_map = ortho.map_from_world(georef, position)
    vertices = mesh.vertices.copy()
    vertices[:, :2] = mesh.vertices[:, :2] @ to_map[:2, :2].T + to_map[:2, 2]
    # Only the vertices the triangles use (a trimmed mesh keeps its unused ones).
    grid = ortho.raster_grid(vertices[np.unique(mesh.faces), :2], options.resolution_m)
    log.info("ortho: %d x %d cells at %g m", grid.width, grid.height, grid.resolution_m)
    from shared.progress import progress_bar

    bar = progress_bar(total=len(mesh.faces), desc="ortho", unit="triangle")
    try:
        elevation, rgb = ortho.rasterise_top_down(
            vertices, mesh.faces, mesh.colors, grid, on_progress=bar.update
        )
    finally:
        bar.close()
    valid = np.isfinite(elevation)
    epsg = georef.epsg if georef else None
    frame = f"EPSG:{epsg}" if epsg else "wreckmap local world frame (x, y, z up; metres)"
    citation = f"wreckmap ortho; {frame}; elevation z m, 0 at the sea surface"
    rgba = np.dstack((rgb, np.where(valid, 255, 0).astype(np.uint8)))
    caption = f"{grid.resolution_m * 100:g} cm/px, {frame}"
    depth_range = (
        f"z {np.nanmin(elevation):.2f} to {np.nanmax(elevation):.2f} m" if valid.any() else ""
    )
    summary = {
        "resolution_m": grid.resolution_m,
        "width": grid.width,
        "height": grid.height,
        "top_left_m": [grid.x0_m, grid.y0_m],
        "pixel_centre": "x0 + (col + 0.5) * res, y0 - (row + 0.5) * res",
        "frame": frame,
        "elevation": "world z, metres, up, 0 at the sea surface (NaN: no surface)",
        "covered_fraction": float(valid.mean()),
        "elevation_range_m": [float(np.nanmin(elevation)), float(np.nanmax(elevation))]
        if valid.any() else None,
        "georeference": asdict(georef) if georef else None,
        "heading_assumed": bool(georef and georef.heading_deg is None),
        "mesh": str(mesh_ply),
    }  # fmt: skip
    with atomic_path(out_dir, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        (tmp / "ortho.tif").write_bytes(
            ortho.geotiff_bytes(rgba, grid, epsg=epsg, citation=citation)
        )
        (tmp / "dem.tif").write_bytes(
            ortho.geotiff_bytes(elevation, grid, epsg=epsg, citation=citation)
        )
        (tmp / "ortho.png").write_bytes(
            ortho.preview_png(
                rgb, valid, grid.resolution_m, max_side_px=options.preview_max_px, caption=caption
            )
        )
        (tmp / "dem.png").write_bytes(
            ortho.preview_png(
                ortho.colourise_elevation(elevation),
                valid,
                grid.resolution_m,
                max_side_px=options.preview_max_px,
                caption=f"{caption}; {depth_range}",
            )
        )
        (tmp / "ortho.json").write_text(json.dumps(summary, indent=2) + "\n")
    return out_dir / "ortho.tif"  # fmt: skip


def export_ortho(
    options: ExportOptions, run: RunFolder, out: Path, suffix: str, overwrite: bool
) -> Path:
    return write_ortho(options.ortho, run.need_mesh(), out / "ortho",
                       targets_json=run.targets_json, overwrite=overwrite)  # fmt: skip


Writer = Callable[[ExportOptions, RunFolder, Path, str, bool], Path]
FORMATS: dict[str, tuple[Writer, str]] = {
    "glb": (export_mesh, ".glb"),
    "gltf": (export_mesh, ".gltf"),
    "las": (export_points, ".las"),
    "laz": (export_points, ".laz"),
    "colmap-text": (export_colmap, ""),
    "nerfstudio": (export_nerfstudio, ""),
    "camera-csv": (export_reference, ""),
    "ortho": (export_ortho, ""),
}


def run(options: ExportOptions, run_dir: Path, out_dir: Path, *, overwrite: bool = False) -> Path:
    """The stage entry point: `export_formats` into `out_dir`; returns `out_dir`."""
    export_formats(options, run_dir, out_dir, overwrite=overwrite)
    return Path(out_dir)


def export_formats(
    options: ExportOptions, run_dir: Path, out_dir: Path, *, overwrite: bool = False
) -> dict[str, Path]:
    """Write every format of `options.formats` from the run in `run_dir` into `out_dir`;
    returns format -> its main file or folder."""
    found = find_run(run_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    for name in dict.fromkeys(options.formats):
        writer, suffix = FORMATS[name]
        log.info("export %s", name)
        written[name] = writer(options, found, out_dir, suffix, overwrite)
    return written
