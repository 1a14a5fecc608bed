"""The COLMAP database of a run: cameras, rigs, frames, images and pose priors.

Since COLMAP 3.12 every image belongs to a frame, and every frame to a rig. A
keyframe here is one image in one frame of a trivial rig holding its camera, so
`frame.rig_from_world` is the image's `cam_from_world`. One COLMAP camera is
written per physical camera (sessions recorded with the same calibration share
it). Pixel conventions differ: OpenCV puts the centre of the top-left pixel at
(0, 0), COLMAP at (0.5, 0.5), so principal points move by half a pixel.

Pose priors hold the camera centre in the world frame (metres) with an
isotropic covariance and the gravity direction in the camera frame; pycolmap
4.2.1's `PosePrior` has no rotation, so SLAM rotations only seed the poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from shared.calibration.cameras import CameraModel, PinholeEquidistant, PinholeRadtan
from shared.errors import InputError

if TYPE_CHECKING:
    import pycolmap

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# The world is gravity-aligned with z up (conventions.md), so gravity points along -z.
_GRAVITY_DIRECTION_W = np.array([0.0, 0.0, -1.0])


@dataclass
class KeyframeSet:
    """The keyframes of every input session, in one order (the database's image order).

    names: image names relative to the run's image folder ("<session>/<stamp_ns>.png").
    sources: the image files as recorded. session: index of each keyframe's session.
    camera: index into the camera list of each keyframe. stamps_ns: int64 ns, camera clock.
    world_from_cam: prior poses `T_W_C` (N, 4, 4), metres; for sessions that are not
        placed in the world (`placed[i]` false) these are `T_S_C` in their own frame.
    placed: whether the keyframe's session has a known `T_W_S`.
    prior_sigma_m: one-sigma position error of each prior (N,), metres.
    """

    names: list[str]
    sources: list[Path]
    session: IntArray
    camera: IntArray
    stamps_ns: IntArray
    world_from_cam: FloatArray
    placed: npt.NDArray[np.bool_]
    prior_sigma_m: FloatArray

    def __len__(self) -> int:
        return len(self.names)


def colmap_camera(camera: CameraModel, camera_id: int) -> pycolmap.Camera:
    """The COLMAP camera of a Kalibr camera model (OPENCV or OPENCV_FISHEYE)."""
    import pycolmap

    # COLMAP's pixel centres sit at +0.5 compared with OpenCV's.
    if isinstance(camera, PinholeRadtan):
        model = "OPENCV"
        extra = [camera.k1, camera.k2, camera.p1, camera.p2]
    elif isinstance(camera, PinholeEquidistant):
        model = "OPENCV_FISHEYE"
        extra = [camera.k1, camera.k2, camera.k3, camera.k4]
    else:
        raise InputError(
            f"camera model {camera.kalibr_model}: not supported by the SfM stage "
            "(expected pinhole-radtan or pinhole-equidistant)"
        )
    params = [camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, *extra]
    return pycolmap.Camera(
        camera_id=camera_id,
        model=model,
        width=int(camera.width),
        height=int(camera.height),
        params=np.asarray(params, dtype=np.float64),
        has_prior_focal_length=True,
    )


def rigid3d_from_pose(T: FloatArray) -> pycolmap.Rigid3d:
    """A pycolmap `Rigid3d` from a 4x4 pose (the same transform)."""
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.ascontiguousarray(T[:3, :3])), T[:3, 3].copy())


def pose_from_rigid3d(rigid: pycolmap.Rigid3d) -> FloatArray:
    """The 4x4 pose of a pycolmap `Rigid3d`."""
    T = np.eye(4)
    T[:3, :4] = rigid.matrix()
    return T


def pose_prior(
    world_from_cam: FloatArray, sigma_m: float, image: pycolmap.Image
) -> pycolmap.PosePrior:
    """A position prior (camera centre in W, isotropic sigma) with gravity in the camera frame."""
    import pycolmap

    prior = pycolmap.PosePrior()
    prior.corr_data_id = image.data_id
    prior.position = world_from_cam[:3, 3].copy()
    prior.position_covariance = np.eye(3) * float(sigma_m) ** 2
    prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
    prior.gravity = world_from_cam[:3, :3].T @ _GRAVITY_DIRECTION_W
    return prior


def write_database(
    path: Path, cameras: list[CameraModel], keyframes: KeyframeSet, *, with_priors: bool = True
) -> dict[str, int]:
    """Create the database at `path` (must not exist); returns image name -> image id.

    Writes one camera per entry of `cameras`, one trivial rig per camera, and one
    frame and image per keyframe. Pose priors are written for placed keyframes only
    (an unplaced session's poses are in another frame) when `with_priors`.
    """
    import pycolmap

    if path.exists():
        raise InputError(f"{path}: database already exists (expected a new path)")
    image_ids: dict[str, int] = {}
    with pycolmap.Database.open(path) as db:
        rig_ids: list[int] = []
        sensors: list[Any] = []
        for k, model in enumerate(cameras):
            camera = colmap_camera(model, k + 1)
            camera_id = db.write_camera(camera, use_camera_id=True)
            camera.camera_id = camera_id
            rig = pycolmap.Rig()
            rig.add_ref_sensor(camera.sensor_id)
            rig_ids.append(db.write_rig(rig))
            sensors.append(camera.sensor_id)
        for i, name in enumerate(keyframes.names):
            k = int(keyframes.camera[i])
            image = pycolmap.Image(name=name, camera_id=k + 1)
            image_id = db.write_image(image)
            image.image_id = image_id
            frame = pycolmap.Frame()
            frame.rig_id = rig_ids[k]
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            image_ids[name] = image_id
            if with_priors and keyframes.placed[i]:
                db.write_pose_prior(
                    pose_prior(keyframes.world_from_cam[i], keyframes.prior_sigma_m[i], image)
                )
    return image_ids


def read_image_ids(path: Path) -> dict[str, int]:
    """Image name -> image id of an existing database."""
    import pycolmap

    with pycolmap.Database.open(path) as db:
        return {image.name: int(image.image_id) for image in db.read_all_images()}
