"""A nerfstudio dataset (`transforms.json` + images + sparse points) for NeRF and
Gaussian splatting (nerfstudio's splatfacto; gsplat reads the COLMAP export instead).

Conventions, from nerfstudio's data-format documentation: `transform_matrix` is the
camera-to-world pose with OpenGL camera axes (x right, y up, z back: the camera looks
along -z), so our `T_W_C` (OpenCV axes: y down, z forward) has its y and z columns
negated. The world is ours (z up, metres), which is also nerfstudio's world orientation.
Intrinsics are COLMAP's (pixel centres at +0.5, as nerfstudio assumes); distortion is
`k1, k2, p1, p2` for camera_model OPENCV and `k1..k4` for OPENCV_FISHEYE. Images keep
their recorded distortion (nerfstudio undistorts them itself).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from postproc.export.cameras import ExportCamera

# Our camera axes (OpenCV) to nerfstudio's (OpenGL): negate y and z.
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
IMAGE_DIR = "images"
POINTS_NAME = "sparse_pc.ply"


def _intrinsics(camera: ExportCamera) -> dict[str, Any]:
    p = camera.named_params()
    out: dict[str, Any] = {
        "camera_model": "OPENCV_FISHEYE" if camera.fisheye else "OPENCV",
        "fl_x": p["fx"], "fl_y": p["fy"], "cx": p["cx"], "cy": p["cy"],
        "w": camera.width, "h": camera.height,
    }  # fmt: skip
    names = ("k1", "k2", "k3", "k4") if camera.fisheye else ("k1", "k2", "p1", "p2")
    out.update({n: float(v) for n, v in zip(names, camera.distortion(), strict=True)})
    return out


def transforms_document(cameras: list[ExportCamera], *, with_points: bool) -> dict[str, Any]:
    """The `transforms.json` content: shared intrinsics at the top when every image has
    the same camera, else per frame; one frame per camera with `file_path`
    (`images/<name>`) and `transform_matrix` (4x4, OpenGL axes, metres)."""
    intrinsics = [_intrinsics(c) for c in cameras]
    shared = all(i == intrinsics[0] for i in intrinsics)
    document: dict[str, Any] = dict(intrinsics[0]) if shared else {}
    frames = []
    for camera, own in zip(cameras, intrinsics, strict=True):
        frame: dict[str, Any] = {} if shared else dict(own)
        frame["file_path"] = f"{IMAGE_DIR}/{camera.name}"
        frame["transform_matrix"] = (camera.world_from_cam @ OPENGL_FROM_OPENCV).tolist()
        frames.append(frame)
    document["frames"] = frames
    if with_points:
        document["ply_file_path"] = POINTS_NAME
    return document


def write_nerfstudio(
    model_dir: Path, image_dir: Path, out_dir: Path, *, overwrite: bool = False
) -> Path:
    """Write `out_dir/transforms.json`, `out_dir/images/` and `out_dir/sparse_pc.ply` (the
    SfM points with their colours, nerfstudio's splat initialisation); returns
    `out_dir/transforms.json`."""
    import json

    import pycolmap

    from postproc.export.cameras import read_cameras
    from postproc.export.images import link_or_copy_images
    from shared.formats.ply import PlyData, write_ply
    from shared.fsutil import atomic_path

    cameras = read_cameras(model_dir)
    rec = pycolmap.Reconstruction(str(model_dir))
    points = [(np.asarray(p.xyz), np.asarray(p.color)) for p in rec.points3D.values()]
    document = transforms_document(cameras, with_points=bool(points))
    with atomic_path(out_dir, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        link_or_copy_images([c.name for c in cameras], image_dir, tmp / IMAGE_DIR)
        if points:
            write_ply(
                tmp / POINTS_NAME,
                PlyData(
                    vertices=np.array([p for p, _ in points], float),
                    colors=np.array([c for _, c in points], np.uint8),
                ),
            )
        (tmp / "transforms.json").write_text(json.dumps(document, indent=2) + "\n")
    return out_dir / "transforms.json"
