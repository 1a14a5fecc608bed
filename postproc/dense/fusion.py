"""COLMAP stereo fusion of the workspace's depth and normal maps into `fused.ply`.

COLMAP's fusion keeps every fused point of a call in memory, and pycolmap hands them
back as a Reconstruction too: about 450 bytes a point, 8.8 GB for the 21 million points
of a 10-minute dive. So when the depth maps hold more valid pixels than
`FusionOptions.max_tile_pixels`, space is cut into boxes of at most that many
(`postproc.dense.tiles`), and each box is fused by one call that reads only the depth
maps reaching into it and keeps only the pixels inside it (COLMAP's bounding box);
the boxes' clouds and visibility files are then joined on disk, one at a time. Pixels
that one call would have fused across a cut become two points, one a side.
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.dense.colmap_io import (
    DenseWorkspace,
    FusionVisibility,
    PinholeView,
    read_array,
    read_fusion_visibility,
)
from postproc.dense.options import FusionOptions as FusionOptions
from postproc.dense.tiles import Box, split_boxes
from shared.errors import OutputExistsError, StageError
from shared.formats.ply import vertex_ply_header
from shared.fsutil import write_text_atomic
from shared.progress import progress

log = logging.getLogger(__name__)

# Every SAMPLE_STEP-th depth pixel along rows and columns places the boxes.
SAMPLE_STEP = 4


def fuse(
    options: FusionOptions,
    workspace: DenseWorkspace,
    views: list[PinholeView],
    references: list[int],
    output_ply: Path,
    *,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Fuse the depth maps of `views[k]` for k in `references` into `output_ply` (with
    COLMAP's `<output_ply>.vis` beside it; both appear together, the .vis first), box by
    box when they hold more than `options.max_tile_pixels` valid pixels.

    Returns {"tiles", "depth_pixels", "points", "images_per_tile"} for dense.json. Raises
    StageError when nothing fuses."""
    output_ply = Path(output_ply)
    vis = output_ply.with_name(output_ply.name + ".vis")
    if output_ply.exists() and not overwrite:
        raise OutputExistsError(f"{output_ply}: already exists (refusing to overwrite)")
    samples, owners, weights = sample_depth_points(workspace, views, references)
    budget = options.max_tile_pixels
    boxes = split_boxes(samples, weights, budget if budget > 0 else math.inf)
    output_ply.parent.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {
        "tiles": len(boxes),
        "depth_pixels": int(weights.sum()),
        "points": 0,
        "images_per_tile": [],
    }
    with tempfile.TemporaryDirectory(prefix=".fusion.", dir=output_ply.parent) as tmp:
        fusion_ws = DenseWorkspace(Path(tmp) / "workspace")
        full_index = references_workspace(workspace, views, references, fusion_ws)
        parts: list[Path] = []
        # A map whose few pixels in a box fell between samples still counts for the box.
        margin = 0.01 * float(np.linalg.norm(np.ptp(samples, axis=0))) if len(samples) else 0.0
        tiles = enumerate(boxes)
        for t, box in progress(tiles, total=len(boxes), desc="fusion", unit="tile"):
            if len(boxes) == 1:
                chosen = list(references)
            else:
                # The references with a sampled pixel in the box or within the margin.
                hit = np.unique(owners[box.contains(samples, margin_m=margin)])
                chosen = [references[int(i)] for i in hit]
            report["images_per_tile"].append(len(chosen))
            if not chosen:
                continue
            part = Path(tmp) / f"tile{t:04d}.ply"
            _write_fusion_cfg(fusion_ws, [views[k].name for k in chosen])
            points = _fuse_call(options, fusion_ws, part, None if len(boxes) == 1 else box)
            if points:
                parts.append(part)
                report["points"] += points
        if not parts:
            raise StageError(
                f"{workspace.root}: stereo fusion produced no points (depth maps empty or "
                "inconsistent, or the sparse model shares no points between images)"
            )
        tmp_ply = Path(tmp) / output_ply.name
        tmp_vis = tmp_ply.with_name(tmp_ply.name + ".vis")
        join_plys(parts, tmp_ply)
        join_visibility([p.with_name(p.name + ".vis") for p in parts], tmp_vis, full_index)
        shutil.move(tmp_vis, vis)
        shutil.move(tmp_ply, output_ply)
    # fusion.cfg names the references, as COLMAP's own fusion of the workspace reads them.
    _write_fusion_cfg(workspace, [views[k].name for k in references])
    return report


def references_workspace(
    workspace: DenseWorkspace,
    views: list[PinholeView],
    references: list[int],
    out: DenseWorkspace,
) -> npt.NDArray[np.uint32]:
    """A workspace at `out` for fusing the references alone: their sparse model (the
    other images deregistered) and links to the images and maps of `workspace`. Returns,
    for each image index of that model, the index of the same image in `views`.

    Why: COLMAP's fusion checks each reference against the `check_num_images` images
    sharing the most sparse points with it, found over the whole model (27 s on a
    10-minute dive's 1228 keyframes, at each call); among all keyframes most of those
    have no depth map, so fewer references met and fewer pixels fused (20.9 against 14.0
    million points for the same maps)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(workspace.sparse_dir))
    keep = {views[k].name for k in references}
    # A rig's frame holds several images: it stays when any of them is a reference.
    frames = {rec.images[i].frame_id for i in rec.reg_image_ids()}
    kept_frames = {
        rec.images[i].frame_id for i in rec.reg_image_ids() if rec.images[i].name in keep
    }
    for frame_id in sorted(frames - kept_frames):
        rec.deregister_frame(frame_id)
    out.sparse_dir.mkdir(parents=True)
    rec.write(str(out.sparse_dir))
    (out.stereo_dir).mkdir(parents=True)
    out.images_dir.symlink_to(workspace.images_dir.resolve(), target_is_directory=True)
    for kind in ("depth_maps", "normal_maps"):
        target = (workspace.stereo_dir / kind).resolve()
        (out.stereo_dir / kind).symlink_to(target, target_is_directory=True)
    # The order COLMAP indexes the written model's images in (its registered order).
    written = pycolmap.Reconstruction(str(out.sparse_dir))
    by_name = {v.name: k for k, v in enumerate(views)}
    order = [by_name[written.images[i].name] for i in written.reg_image_ids()]
    return np.asarray(order, np.uint32)


def _write_fusion_cfg(workspace: DenseWorkspace, names: list[str]) -> None:
    """The images COLMAP's next fusion call reads, one name a line."""
    write_text_atomic(
        workspace.stereo_dir / "fusion.cfg", "".join(n + "\n" for n in names), overwrite=True
    )


def _fuse_call(
    options: FusionOptions, workspace: DenseWorkspace, output_ply: Path, box: Box | None
) -> int:
    """One COLMAP fusion of the images in the workspace's fusion.cfg into `output_ply`
    (and its .vis), keeping pixels in `box` (None: all); returns the points written."""
    import pycolmap

    colmap_options = pycolmap.StereoFusionOptions(
        min_num_pixels=options.min_num_pixels,
        max_reproj_error=options.max_reproj_error_px,
        max_depth_error=options.max_depth_error_rel,
        max_normal_error=options.max_normal_error_deg,
        check_num_images=options.check_num_images,
        num_threads=options.num_threads,
    )
    if box is not None:
        colmap_options.bounding_box = (box.lo.astype(np.float32), box.hi.astype(np.float32))
    rec = pycolmap.stereo_fusion(
        output_path=str(output_ply),
        workspace_path=str(workspace.root),
        workspace_format="COLMAP",
        input_type=options.input_type,
        options=colmap_options,
        output_type="PLY",
    )
    count = int(rec.num_points3D())
    del rec
    return count


def sample_depth_points(
    workspace: DenseWorkspace, views: list[PinholeView], references: list[int]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Every SAMPLE_STEP-th valid pixel of each reference's geometric depth map, in the
    world (m): (points (N, 3), the index into `references` each came from (N,), weights
    (N,): the valid pixels each stands for, so that they sum to the maps' valid pixels).
    A reference without a depth map contributes nothing."""
    chunks, owners, weights = [], [], []
    for i, k in enumerate(references):
        view = views[k]
        path = workspace.depth_map_path(view.name)
        if not path.is_file():
            continue
        depth = read_array(path)
        valid = depth > 0
        rows, cols = np.nonzero(valid[::SAMPLE_STEP, ::SAMPLE_STEP])
        if len(rows) == 0:
            continue
        rows, cols = rows * SAMPLE_STEP, cols * SAMPLE_STEP
        z = depth[rows, cols].astype(np.float64)
        # The depth map may be smaller than the image (COLMAP scales K with it).
        sx, sy = depth.shape[1] / view.width, depth.shape[0] / view.height
        x = (cols - view.K[0, 2] * sx) / (view.K[0, 0] * sx) * z
        y = (rows - view.K[1, 2] * sy) / (view.K[1, 1] * sy) * z
        cam = np.column_stack((x, y, z))
        world = view.world_from_cam
        chunks.append(cam @ world[:3, :3].T + world[:3, 3])
        owners.append(np.full(len(z), i, np.int64))
        weights.append(np.full(len(z), np.count_nonzero(valid) / len(z)))
    if not chunks:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(chunks), np.concatenate(owners), np.concatenate(weights)


def join_plys(parts: list[Path], output: Path) -> None:
    """Concatenate binary PLYs of vertices with the same properties into `output`."""
    headers = [vertex_ply_header(p) for p in parts]
    layout = [[ln for ln in h[0] if not ln.startswith(b"element ")] for h in headers]
    if any(other != layout[0] for other in layout[1:]):
        raise StageError(f"{parts[0].parent}: fusion wrote PLYs with different properties")
    total = sum(h[1] for h in headers)
    lines = [
        b"element vertex %d" % total if ln.startswith(b"element vertex ") else ln
        for ln in headers[0][0]
    ]
    with output.open("wb") as out:
        out.write(b"\n".join(lines) + b"\nend_header\n")
        for part, (_, _, offset) in zip(parts, headers, strict=True):
            with part.open("rb") as f:
                f.seek(offset)
                shutil.copyfileobj(f, out, 16 << 20)


def join_visibility(
    parts: list[Path], output: Path, image_index: npt.NDArray[np.uint32] | None = None
) -> None:
    """Concatenate COLMAP fusion `.vis` files (uint64 point count, then per point a
    uint32 count and that many uint32 image indices) into `output`, each image index k
    written as `image_index[k]` (None: as it is). One part in memory at a time."""
    total = 0
    for part in parts:
        with part.open("rb") as f:
            head = f.read(8)
        if len(head) != 8:
            raise StageError(f"{part}: truncated fusion visibility file")
        total += int(np.frombuffer(head, "<u8")[0])
    with output.open("wb") as out:
        out.write(np.uint64(total).astype("<u8").tobytes())
        for part in parts:
            if image_index is None:
                with part.open("rb") as f:
                    f.seek(8)
                    shutil.copyfileobj(f, out, 16 << 20)
                continue
            visible = read_fusion_visibility(part)
            if len(visible.images) and int(visible.images.max()) >= len(image_index):
                raise StageError(f"{part}: image index past the {len(image_index)} fused")
            remapped = FusionVisibility(visible.offsets, image_index[visible.images])
            out.write(memoryview(remapped.to_bytes())[8:])  # without its point count
