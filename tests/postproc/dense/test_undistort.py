"""Our resampling of undistorted images against COLMAP's own undistorter."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from postproc.dense.colmap_io import read_pinhole_views, write_known_pose_model
from postproc.dense.options import DenseOptions
from postproc.dense.stage import undistort
from postproc.dense.undistort import PinholeTarget, undistort_images
from shared.errors import InputError

CAMERAS = {
    "OPENCV": [300.0, 302.0, 161.0, 118.0, -0.25, 0.06, 3e-4, -2e-4],
    "OPENCV_FISHEYE": [200.0, 200.0, 159.0, 121.0, 0.05, -0.01, 0.002, -0.001],
    "SIMPLE_RADIAL": [280.0, 160.0, 120.0, -0.1],
}


def textured_model(folder: Path, model: str, params: list[float], count: int = 3) -> None:
    """`count` smooth random colour images (320x240) and a model naming them."""
    rng = np.random.default_rng(len(model))
    (folder / "images" / "sub").mkdir(parents=True)
    names = [f"sub/{k:02d}.png" for k in range(count)]
    for name in names:
        noise = rng.uniform(0, 255, (240, 320, 3)).astype(np.float32)
        image = cv2.GaussianBlur(noise, (0, 0), 3.0)
        image = (image - image.min()) * (255.0 / np.ptp(image))
        cv2.imwrite(str(folder / "images" / name), image.astype(np.uint8))
    write_known_pose_model(
        folder / "sparse",
        camera_model=model,
        camera_params=params,
        size=(320, 240),
        image_names=names,
        cams_from_world=[np.eye(4)] * count,
    )


@pytest.mark.parametrize(
    ("model", "max_size", "tolerance"),
    [("OPENCV", 320, 0.05), ("OPENCV_FISHEYE", 320, 0.05), ("SIMPLE_RADIAL", 320, 0.05),
     ("OPENCV", 160, 1.0)],
)  # fmt: skip
def test_the_same_pixels_as_colmaps_undistorter(
    tmp_path: Path, model: str, max_size: int, tolerance: float
) -> None:
    textured_model(tmp_path, model, CAMERAS[model])
    options = DenseOptions(max_image_size_px=max_size)
    undistort(options, tmp_path / "sparse", tmp_path / "images", tmp_path / "colmap")
    views = read_pinhole_views(tmp_path / "colmap" / "sparse")
    assert max(views[0].width, views[0].height) <= max_size
    targets = {v.name: PinholeTarget.of(v.K, v.width, v.height) for v in views}
    done: list[int] = []
    out = tmp_path / "ours"
    undistort_images(
        tmp_path / "sparse", tmp_path / "images", out, targets, on_done=lambda: done.append(1)
    )
    assert len(done) == len(views)
    assert not list(out.rglob(".*"))  # written under a temporary name, then renamed
    for view in views:
        theirs = cv2.imread(str(tmp_path / "colmap" / "images" / view.name))
        mine = cv2.imread(str(out / view.name))
        assert theirs is not None and mine is not None and mine.shape == theirs.shape
        diff = np.abs(mine.astype(np.int16) - theirs.astype(np.int16))
        # Native size: COLMAP's rounding only. Shrunk: area averaging against COLMAP's
        # bilinear rescale of the full-size image.
        assert diff.mean() < tolerance, (view.name, diff.mean())
        assert np.percentile(diff, 99) <= (1 if tolerance < 1 else 6), view.name


def test_a_wrong_sized_image_is_refused_by_name(tmp_path: Path) -> None:
    textured_model(tmp_path, "OPENCV", CAMERAS["OPENCV"], count=1)
    cv2.imwrite(str(tmp_path / "images" / "sub" / "00.png"), np.zeros((100, 100, 3), np.uint8))
    target = PinholeTarget.of(np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), 320, 240)
    with pytest.raises(InputError, match=r"00\.png: 100x100 pixels, but its camera is 320x240"):
        undistort_images(
            tmp_path / "sparse", tmp_path / "images", tmp_path / "o", {"sub/00.png": target}
        )
    with pytest.raises(InputError, match=r"no image nope\.png"):
        undistort_images(
            tmp_path / "sparse", tmp_path / "images", tmp_path / "o", {"nope.png": target}
        )
    assert not (tmp_path / "o" / "sub" / "00.png").exists()
