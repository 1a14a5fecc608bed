"""COLMAP stereo fusion of the workspace's depth and normal maps into `fused.ply`."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from postproc.dense.options import FusionOptions as FusionOptions
from shared.errors import OutputExistsError, StageError


def fuse(
    options: FusionOptions, workspace_dir: Path, output_ply: Path, *, overwrite: bool = False
) -> Path:
    """Fuse the depth maps of the COLMAP workspace at `workspace_dir` into `output_ply`
    (with COLMAP's `<output_ply>.vis` beside it). Raises StageError when nothing fuses."""
    import pycolmap

    output_ply = Path(output_ply)
    vis = output_ply.with_name(output_ply.name + ".vis")
    if output_ply.exists() and not overwrite:
        raise OutputExistsError(f"{output_ply}: already exists (refusing to overwrite)")
    colmap_options = pycolmap.StereoFusionOptions(
        min_num_pixels=options.min_num_pixels,
        max_reproj_error=options.max_reproj_error_px,
        max_depth_error=options.max_depth_error_rel,
        max_normal_error=options.max_normal_error_deg,
        check_num_images=options.check_num_images,
        num_threads=options.num_threads,
    )
    output_ply.parent.mkdir(parents=True, exist_ok=True)
    # Fusion writes two files; both go to a temporary folder and move into place together
    # (the .vis first, so a present fused.ply always has its .vis).
    with tempfile.TemporaryDirectory(prefix=".fusion.", dir=output_ply.parent) as tmp:
        tmp_ply = Path(tmp) / output_ply.name
        rec = pycolmap.stereo_fusion(
            output_path=str(tmp_ply),
            workspace_path=str(workspace_dir),
            workspace_format="COLMAP",
            input_type=options.input_type,
            options=colmap_options,
            output_type="PLY",
        )
        if rec.num_points3D() == 0:
            raise StageError(
                f"{workspace_dir}: stereo fusion produced no points (depth maps empty or "
                "inconsistent, or the sparse model shares no points between images)"
            )
        shutil.move(tmp_ply.with_name(tmp_ply.name + ".vis"), vis)
        shutil.move(tmp_ply, output_ply)
    return output_ply
