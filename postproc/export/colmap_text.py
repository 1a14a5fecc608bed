"""The SfM model as a COLMAP text model with its images (COLMAP, gsplat, Metashape,
RealityCapture and nerfstudio's `ns-process-data` all read this layout)::

    OUT/sparse/0/cameras.txt, images.txt, points3D.txt (+ rigs.txt, frames.txt)
    OUT/images/<name>   the keyframes as recorded (distorted; the cameras say how)
"""

from __future__ import annotations

from pathlib import Path

from postproc.export.images import link_or_copy_images
from shared.fsutil import atomic_path


def write_colmap_text(
    model_dir: Path, image_dir: Path, out_dir: Path, *, overwrite: bool = False
) -> Path:
    """Convert the binary model in `model_dir` to text in `out_dir/sparse/0` and put the
    images it names in `out_dir/images`; returns `out_dir`."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    names = [rec.images[i].name for i in rec.reg_image_ids()]
    with atomic_path(out_dir, overwrite=overwrite) as tmp:
        (tmp / "sparse" / "0").mkdir(parents=True)
        rec.write_text(str(tmp / "sparse" / "0"))
        link_or_copy_images(names, image_dir, tmp / "images")
    return out_dir
