"""COLMAP stereo fusion of the workspace's depth and normal maps into `fused.ply`."""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from shared.errors import OutputExistsError, StageError


@dataclass(kw_only=True)
class FusionOptions:
    """COLMAP StereoFusionOptions we set (the rest keep COLMAP's defaults).

    min_num_pixels: images that must agree on a point; max_reproj_error_px: reprojection
    agreement; max_depth_error_rel: depth agreement as a fraction of the depth;
    max_normal_error_deg: normal agreement (our CPU normals come from finite differences of
    the depth, noisier than PatchMatch's, so the default is looser than COLMAP's 10);
    check_num_images: overlapping images checked per reference image; input_type:
    "geometric" (filtered maps) or "photometric".

    min_num_pixels 2 and max_depth_error_rel 0.02 (looser than COLMAP's 5 and 0.01) were
    measured on the simulated survey (640x360, true poses): completeness at 5 cm 58.7 ->
    67.6 %, accuracy 99.9 -> 99.3 %. Far surfaces (5-8 m through hazy water) are matched
    by few images and with depth errors near 1-2 %: the stricter rules dropped them.
    min_num_pixels 1 since depth maps exist for reference views only (about a third of
    the keyframes, `ViewSelectionOptions`): each far surface is then in fewer depth maps
    (`bench_dense.py`, 960x540, 19 of 56 keyframes: accuracy / completeness at 5 cm
    99.9 / 48.9 % with 2, 97.3 / 72.1 % with 1). Every depth kept already passed the
    stereo's left-right check.
    """

    min_num_pixels: int = 1
    max_reproj_error_px: float = 2.0
    max_depth_error_rel: float = 0.02
    max_normal_error_deg: float = 25.0
    check_num_images: int = 50
    input_type: str = "geometric"
    num_threads: int = -1


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
