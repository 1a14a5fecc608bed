"""COLMAP dense-workspace files: depth and normal maps (`.bin`), the workspace layout, and
the camera/pose summary of an undistorted model.

COLMAP's `mvs::Mat` file format: an ASCII header `"{width}&{height}&{channels}&"` followed
by `width * height * channels` little-endian float32 values stored channel by channel
(planar), each channel row-major: the value at (row, col, channel) is at index
`channel * width * height + row * width + col`. Depth maps hold the camera-frame z of each
pixel in metres (0 = no depth); normal maps hold unit normals in the camera frame (x right,
y down, z forward), pointing towards the camera.
"""

from __future__ import annotations

import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.errors import InputError
from shared.fsutil import atomic_path

F32 = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]

# Longest header we accept: three numbers and three '&' (guards against reading a wrong file).
_MAX_HEADER_BYTES = 64


def array_bytes(array: npt.ArrayLike) -> bytes:
    """A (H, W) or (H, W, C) array as the bytes of a COLMAP `.bin` map."""
    values = np.asarray(array, dtype=np.float32)
    if values.ndim == 2:
        values = values[..., None]
    if values.ndim != 3:
        raise ValueError(f"expected a (H, W) or (H, W, C) array, got shape {values.shape}")
    height, width, channels = values.shape
    header = f"{width}&{height}&{channels}&".encode("ascii")
    planar = np.ascontiguousarray(np.moveaxis(values, 2, 0), dtype="<f4")
    return header + planar.tobytes()


def write_array(path: Path | str, array: npt.ArrayLike, *, overwrite: bool = False) -> Path:
    """Write a depth map (H, W) or normal map (H, W, 3) in COLMAP's format (atomic)."""
    data = array_bytes(array)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def parse_array(data: bytes, *, name: str = "<bytes>") -> F32:
    """Decode COLMAP `.bin` map bytes: (H, W) for one channel, (H, W, C) otherwise."""
    fields: list[int] = []
    start = 0
    for _ in range(3):
        end = data.find(b"&", start, _MAX_HEADER_BYTES)
        if end < 0:
            raise InputError(
                f"{name}: not a COLMAP depth/normal map "
                "(expected a 'width&height&channels&' header)"
            )
        text = data[start:end]
        if not text.isdigit():
            raise InputError(f"{name}: bad header field {text!r} (expected a positive integer)")
        fields.append(int(text))
        start = end + 1
    width, height, channels = fields
    expected = width * height * channels * 4
    if width == 0 or height == 0 or channels == 0 or len(data) - start != expected:
        raise InputError(
            f"{name}: header says {width}x{height}x{channels} float32 ({expected} bytes) "
            f"but {len(data) - start} bytes follow"
        )
    planar = np.frombuffer(data, dtype="<f4", offset=start).reshape(channels, height, width)
    values = np.moveaxis(planar, 0, 2).astype(np.float32)
    return values[..., 0] if channels == 1 else values


def read_array(path: Path | str) -> F32:
    """Read a COLMAP depth or normal map (`.bin`)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such depth/normal map")
    return parse_array(path.read_bytes(), name=str(path))


@dataclass(frozen=True)
class DenseWorkspace:
    """The folder layout COLMAP's undistorter writes and stereo fusion reads (COLMAP's
    names, not our hand-off names; a `DenseFolder`'s `workspace` is one).

    root/images/<name> (undistorted images), root/sparse/ (PINHOLE model),
    root/stereo/{depth_maps,normal_maps}/<name>.<kind>.bin with kind "geometric" or
    "photometric", root/stereo/fusion.cfg (images to fuse, one name a line); ours beside
    them: root/stereo/support_maps/<name>.pairs.bin (the CPU stereo's count of agreeing
    pairs per pixel, same format).
    """

    root: Path

    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @property
    def sparse_dir(self) -> Path:
        return self.root / "sparse"

    @property
    def stereo_dir(self) -> Path:
        return self.root / "stereo"

    def depth_map_path(self, image_name: str, kind: str = "geometric") -> Path:
        return self.stereo_dir / "depth_maps" / f"{image_name}.{kind}.bin"

    def normal_map_path(self, image_name: str, kind: str = "geometric") -> Path:
        return self.stereo_dir / "normal_maps" / f"{image_name}.{kind}.bin"

    def support_map_path(self, image_name: str) -> Path:
        return self.stereo_dir / "support_maps" / f"{image_name}.pairs.bin"

    def is_undistorted(self) -> bool:
        """True when the undistorter finished here (model, images and fusion.cfg present)."""
        return (
            (self.sparse_dir / "images.bin").is_file()
            and self.images_dir.is_dir()
            and (self.stereo_dir / "fusion.cfg").is_file()
        )


@dataclass
class PinholeView:
    """One undistorted image: name, K (3x3, pixels), size, `cam_from_world` (4x4, metres),
    and the world positions (P, 3) m of the sparse points it observes (depth range,
    neighbour choice)."""

    name: str
    K: FloatArray
    width: int
    height: int
    cam_from_world: FloatArray
    points_m: FloatArray

    def point_depths_m(self) -> FloatArray:
        """Camera-z depths of the sparse points this image observes (those in front)."""
        z: FloatArray = self.points_m @ self.cam_from_world[2, :3] + self.cam_from_world[2, 3]
        return z[z > 0]

    @property
    def world_from_cam(self) -> FloatArray:
        return np.asarray(np.linalg.inv(self.cam_from_world), dtype=np.float64)

    @property
    def centre_m(self) -> FloatArray:
        return self.world_from_cam[:3, 3]


def read_pinhole_views(model_dir: Path | str) -> list[PinholeView]:
    """The registered images of an undistorted COLMAP model, in the model's registered-image
    order (the order COLMAP's fusion indexes images in `fused.ply.vis`).

    Raises InputError when the model is missing or holds a non-pinhole camera.
    """
    import pycolmap

    model_dir = Path(model_dir)
    if not (model_dir / "images.bin").is_file():
        raise InputError(f"{model_dir}: no COLMAP model (expected cameras.bin, images.bin)")
    rec = pycolmap.Reconstruction(str(model_dir))
    xyz = {int(pid): np.asarray(point.xyz) for pid, point in rec.points3D.items()}
    views = []
    for image_id in rec.reg_image_ids():
        image = rec.images[image_id]
        camera = rec.cameras[image.camera_id]
        if camera.model_name not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise InputError(
                f"{model_dir}: camera {camera.camera_id} is {camera.model_name} "
                "(expected an undistorted PINHOLE camera)"
            )
        K = np.asarray(camera.calibration_matrix(), dtype=np.float64)
        pose = np.eye(4)
        pose[:3, :] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        points = np.array(
            [xyz[int(p.point3D_id)] for p in image.points2D if p.has_point3D()],
            dtype=np.float64,
        ).reshape(-1, 3)
        views.append(
            PinholeView(
                name=image.name,
                K=K,
                width=int(camera.width),
                height=int(camera.height),
                cam_from_world=pose,
                points_m=points,
            )
        )
    return views


@dataclass(frozen=True)
class FusionVisibility:
    """The images each fused point came from, packed: point i's image indices are
    `images[offsets[i]:offsets[i + 1]]`. Reads like a list of arrays (`len`, `[i]`,
    iteration) without one array object a point (20 million points on a 10-minute dive).
    """

    offsets: npt.NDArray[np.int64]
    images: npt.NDArray[np.uint32]

    @classmethod
    def from_lists(
        cls, per_point: list[list[int]] | list[npt.NDArray[np.uint32]]
    ) -> FusionVisibility:
        """Packed from one list (or array) of image indices a point."""
        counts = np.array([len(images) for images in per_point], np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        flat = [int(k) for images in per_point for k in images]
        return cls(offsets, np.asarray(flat, np.uint32).reshape(-1))

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, index: int) -> npt.NDArray[np.uint32]:
        return self.images[self.offsets[index] : self.offsets[index + 1]]

    def __iter__(self) -> Iterator[npt.NDArray[np.uint32]]:
        for index in range(len(self)):
            yield self[index]

    @property
    def counts(self) -> npt.NDArray[np.int64]:
        """Images per point."""
        return np.diff(self.offsets)

    def subset(self, points: npt.NDArray[np.int64]) -> FusionVisibility:
        """The entries of `points` (indices), in that order."""
        counts = self.counts[points]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        starts = np.repeat(self.offsets[:-1][points] - offsets[:-1], counts)
        return FusionVisibility(offsets, self.images[starts + np.arange(offsets[-1])])

    def point_of_each_image(self) -> npt.NDArray[np.int64]:
        """For each entry of `images`, the point it belongs to."""
        return np.repeat(np.arange(len(self), dtype=np.int64), self.counts)

    def to_bytes(self) -> bytes:
        """The `.vis` file's bytes (the layout `read_fusion_visibility` reads)."""
        counts = self.counts
        words = np.empty(len(counts) + len(self.images), "<u4")
        heads = self.offsets[:-1] + np.arange(len(counts))
        words[heads] = counts
        is_image = np.ones(len(words), bool)
        is_image[heads] = False
        words[is_image] = self.images
        return struct.pack("<Q", len(counts)) + words.tobytes()


def read_fusion_visibility(path: Path | str) -> FusionVisibility:
    """The `fused.ply.vis` file of COLMAP's fusion: for each fused point, the indices (in
    the workspace model's registered-image order) of the images it was fused from.

    Layout: uint64 point count, then per point a uint32 count and that many uint32 indices.
    """
    from array import array

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no fusion visibility file")
    data = path.read_bytes()
    if len(data) < 8 or (len(data) - 8) % 4:
        raise InputError(f"{path}: not a fusion visibility file (bad size {len(data)})")
    count = int(np.frombuffer(data, "<u8", 1)[0])
    values = np.frombuffer(data, "<u4", offset=8)
    # Where each point's count sits is known only by walking them: a plain loop over an
    # array of Python ints (4 s for 20 million points), keeping positions, not objects.
    words = array("I")
    words.frombytes(data[8:])
    if sys.byteorder != "little":
        words.byteswap()
    heads = array("q")
    at, size = 0, len(words)
    for point in range(count):
        if at >= size:
            raise InputError(f"{path}: truncated after {point} of {count} points")
        heads.append(at)
        at += 1 + words[at]
    if at > size:
        raise InputError(f"{path}: truncated in point {count - 1} of {count}")
    if at != size:
        raise InputError(f"{path}: {size - at} values past the last point")
    del words
    head = np.frombuffer(heads, np.int64)
    counts = values[head].astype(np.int64)
    is_image = np.ones(len(values), bool)
    is_image[head] = False
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return FusionVisibility(offsets, values[is_image].copy())


def write_known_pose_model(
    model_dir: Path | str,
    *,
    camera_model: str,
    camera_params: npt.ArrayLike,
    size: tuple[int, int],
    image_names: list[str],
    cams_from_world: list[FloatArray],
    points_m: npt.ArrayLike | None = None,
    observations: list[list[tuple[int, float, float]]] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a COLMAP binary model of images with known poses (one shared camera).

    camera_model, camera_params: a COLMAP camera ("PINHOLE": fx fy cx cy; "OPENCV": fx fy
    cx cy k1 k2 p1 p2); size: (width, height) px; cams_from_world: 4x4 `T_C_W` per image;
    points_m: (P, 3) sparse points in the world; observations: per image, (point index,
    x px, y px) of each point it sees. Fusion needs the points: it picks each image's
    overlapping images from the points they share.
    """
    import pycolmap

    model_dir = Path(model_dir)
    width, height = size
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(1, camera_model, 1.0, int(width), int(height))
    camera.params = np.asarray(camera_params, dtype=np.float64).tolist()
    rec.add_camera_with_trivial_rig(camera)
    observations = observations or [[] for _ in image_names]
    tracks: dict[int, list[tuple[int, int]]] = {}
    for k, (name, pose) in enumerate(zip(image_names, cams_from_world, strict=True)):
        seen = observations[k]
        keypoints = np.array([(x, y) for _, x, y in seen], dtype=np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.asarray(pose)[:3, :4]))
        for idx, (point, _, _) in enumerate(seen):
            tracks.setdefault(int(point), []).append((k + 1, idx))
    if points_m is not None:
        points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        for point, elements in sorted(tracks.items()):
            if len(elements) < 2:
                continue
            track = pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in elements])
            rec.add_point3D(points[point], track, np.array([128, 128, 128], np.uint8))
    with atomic_path(model_dir, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        rec.write_binary(str(tmp))
    return model_dir
