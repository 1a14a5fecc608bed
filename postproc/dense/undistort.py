"""Undistorted images for the dense workspace, resampled here instead of by COLMAP.

COLMAP's undistorter chooses each image's PINHOLE camera (written into the workspace's
`sparse/` by `postproc.dense.stage.undistort`) and can write the images too, but it
evaluates the distortion model afresh for every pixel of every image: about 150 ms of
CPU a 960x540 image, 68 s for the 774 images of a 10-minute dive. The cameras of a dive
are few, so here the pixel map from each PINHOLE camera to its distorted camera is
computed once (through pycolmap's own projection, so every COLMAP camera model works),
and each image is then one `cv2.remap` (bilinear, black outside the source, as COLMAP),
over a thread pool (OpenCV's reading, remapping and writing release the GIL).

Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at
(0, 0); the map converts on both sides.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.errors import InputError
from shared.formats.png import encode_png
from shared.fsutil import write_bytes_atomic

# Below this ratio of PINHOLE to source focal length (COLMAP's max_image_size shrank the
# undistorted image), the source is first shrunk by area averaging, so that bilinear
# sampling does not alias.
_SHRINK_BELOW = 0.75


@dataclass(frozen=True)
class PinholeTarget:
    """The undistorted camera of one image: 3x3 K (COLMAP's pixel convention) and size."""

    K: tuple[tuple[float, ...], ...]
    width: int
    height: int

    @classmethod
    def of(cls, K: npt.NDArray[np.float64], width: int, height: int) -> PinholeTarget:
        return cls(tuple(tuple(float(x) for x in row) for row in K), int(width), int(height))


@dataclass(frozen=True)
class ImageMap:
    """How to resample a distorted image into its PINHOLE image: shrink the source from
    `source_size` to `sample_size` (width, height; equal: no shrinking), then
    `cv2.remap` through `map_x`, `map_y` (float32, OpenCV pixel convention)."""

    source_size: tuple[int, int]
    sample_size: tuple[int, int]
    map_x: npt.NDArray[np.float32]
    map_y: npt.NDArray[np.float32]


def undistortion_map(camera: Any, target: PinholeTarget) -> ImageMap:
    """For each pixel of the PINHOLE image `target`, where it falls in the image of the
    distorted pycolmap `camera`. When the PINHOLE image is much smaller than the source
    (COLMAP's max_image_size), the source is first shrunk to about the PINHOLE's scale,
    by area averaging, so that bilinear sampling does not alias. Pixels that do not
    project map outside the source (black)."""
    import pycolmap

    source_size = (int(camera.width), int(camera.height))
    ratio = target.K[0][0] / float(camera.focal_length_x)
    if ratio < _SHRINK_BELOW:
        camera = pycolmap.Camera(
            model=camera.model, width=camera.width, height=camera.height, params=camera.params
        )
        camera.rescale(max(1, round(source_size[0] * ratio)), max(1, round(source_size[1] * ratio)))
    K = np.asarray(target.K, dtype=np.float64)
    u, v = np.meshgrid(
        np.arange(target.width, dtype=np.float64), np.arange(target.height, dtype=np.float64)
    )
    x = (u.ravel() + 0.5 - K[0, 2]) / K[0, 0]
    y = (v.ravel() + 0.5 - K[1, 2]) / K[1, 1]
    rays = np.column_stack((x, y, np.ones_like(x)))
    pixels = np.asarray(camera.img_from_cam(rays, check_cheirality=False), dtype=np.float64)
    pixels = np.where(np.isfinite(pixels), pixels - 0.5, -1e6)
    shape = (target.height, target.width)
    return ImageMap(
        source_size=source_size,
        sample_size=(int(camera.width), int(camera.height)),
        map_x=pixels[:, 0].reshape(shape).astype(np.float32),
        map_y=pixels[:, 1].reshape(shape).astype(np.float32),
    )


def _write_params(path: Path) -> list[int]:
    import cv2

    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        return [cv2.IMWRITE_JPEG_QUALITY, 95]
    return []


def undistort_image(source: Path, target: Path, image_map: ImageMap) -> None:
    """Resample one image (8-bit colour, as COLMAP's undistorter writes it) through
    `image_map` into `target`, atomically."""
    import cv2

    pixels = cv2.imread(str(source), cv2.IMREAD_COLOR)
    if pixels is None:
        raise InputError(f"{source}: cannot read the image (expected a PNG or JPEG)")
    size = (pixels.shape[1], pixels.shape[0])
    if size != image_map.source_size:
        raise InputError(
            f"{source}: {size[0]}x{size[1]} pixels, but its camera is "
            f"{image_map.source_size[0]}x{image_map.source_size[1]}"
        )
    if image_map.sample_size != size:
        pixels = cv2.resize(pixels, image_map.sample_size, interpolation=cv2.INTER_AREA)
    out = cv2.remap(
        pixels,
        image_map.map_x,
        image_map.map_y,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    if target.suffix.lower() == ".png":
        # zlib-ng's level 2: half the time of OpenCV's level 1 and a few % fewer bytes
        # (its level 1 is faster still but a third larger on these smooth resamplings).
        data = encode_png(out, level=2)
    else:
        ok, encoded = cv2.imencode(target.suffix, out, _write_params(target))
        if not ok:
            raise InputError(f"{target}: cannot encode the undistorted image as {target.suffix}")
        data = encoded.tobytes()
    write_bytes_atomic(target, data, overwrite=True)


def undistort_images(
    model_dir: Path,
    image_dir: Path,
    out_dir: Path,
    targets: dict[str, PinholeTarget],
    *,
    workers: int | None = None,
    on_done: Callable[[], None] | None = None,
) -> None:
    """Write `out_dir/<name>` for each name of `targets` (its PINHOLE camera), resampled
    from `image_dir/<name>`, whose distorted camera is in the COLMAP model at
    `model_dir`. `workers` threads (None: one per core); `on_done` is called after each
    image (progress)."""
    import cv2
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    camera_of = {image.name: image.camera_id for image in rec.images.values()}
    missing = [name for name in targets if name not in camera_of]
    if missing:
        raise InputError(f"{model_dir}: no image {missing[0]} in the model")
    threads = workers or os.cpu_count() or 1
    cameras = {camera_of[name]: rec.cameras[camera_of[name]] for name in targets}

    # A few maps at a time (8 MB each at 960x540): a model may give every image its own
    # camera. The images run camera by camera, so each map is made about once.
    @functools.lru_cache(maxsize=2 * threads)
    def image_map(key: tuple[int, PinholeTarget]) -> ImageMap:
        return undistortion_map(cameras[key[0]], key[1])

    jobs = sorted(
        (((camera_of[name], targets[name]), name) for name in targets),
        key=lambda job: (job[0][0], job[1]),
    )

    def one(job: tuple[tuple[int, PinholeTarget], str]) -> None:
        key, name = job
        undistort_image(Path(image_dir) / name, Path(out_dir) / name, image_map(key))
        if on_done is not None:
            on_done()

    cv2_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # the pool is the parallelism
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=threads) as pool:
            for future in [pool.submit(one, job) for job in jobs]:
                future.result()
    finally:
        cv2.setNumThreads(cv2_threads)
