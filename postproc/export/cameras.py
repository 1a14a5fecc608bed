"""The registered cameras of a COLMAP model, in the terms every export needs.

`read_cameras` is the only function here that does I/O (pycolmap); the rest is pure math:
OpenCV intrinsics and distortion of each supported COLMAP camera model, and the
motion-only covariance of a camera pose from its reprojection residuals.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.errors import InputError

FloatArray = npt.NDArray[np.float64]

# COLMAP camera model -> the names of its parameters (COLMAP's order).
CAMERA_PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}


@dataclass(frozen=True)
class ExportCamera:
    """One registered image: `name` (relative to the image folder), its camera (COLMAP
    `model` and `params`, `width` x `height` px), `cam_from_world` (4x4 `T_C_W`, metres,
    OpenCV camera axes), and the sparse points it observes: `points_m` (P, 3) in W and
    `pixels` (P, 2) where it observed them (COLMAP pixel convention: the centre of the
    top-left pixel is (0.5, 0.5))."""

    name: str
    camera_id: int
    model: str
    params: tuple[float, ...]
    width: int
    height: int
    cam_from_world: FloatArray
    points_m: FloatArray
    pixels: FloatArray

    @property
    def world_from_cam(self) -> FloatArray:
        out = np.eye(4)
        R = self.cam_from_world[:3, :3]
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ self.cam_from_world[:3, 3]
        return out

    def named_params(self) -> dict[str, float]:
        """The parameters by name (fx, fy, cx, cy, k1...; `f` of the simple models is
        given as fx = fy)."""
        values = dict(zip(CAMERA_PARAMS[self.model], self.params, strict=True))
        if "f" in values:
            values["fx"] = values["fy"] = values.pop("f")
        return values

    def intrinsic_matrix(self) -> FloatArray:
        """3x3 intrinsic matrix (pixels; COLMAP's principal point, whose convention puts
        the centre of the top-left pixel at 0.5)."""
        p = self.named_params()
        return np.array([[p["fx"], 0.0, p["cx"]], [0.0, p["fy"], p["cy"]], [0.0, 0.0, 1.0]])

    @property
    def fisheye(self) -> bool:
        return self.model == "OPENCV_FISHEYE"

    def distortion(self) -> FloatArray:
        """OpenCV distortion coefficients: (k1, k2, p1, p2) for the radtan models, (k1,
        k2, k3, k4) for OPENCV_FISHEYE (cv2.fisheye); zeros for the pinhole models."""
        p = self.named_params()
        names = ("k1", "k2", "k3", "k4") if self.fisheye else ("k1", "k2", "p1", "p2")
        return np.array([p.get(n, 0.0) for n in names])


def project(camera: ExportCamera, points_m: FloatArray, cam_from_world: FloatArray) -> FloatArray:
    """Pixels (N, 2) of world points (N, 3) in `camera` at pose `cam_from_world` (the
    OPENCV / OPENCV_FISHEYE distortion models written out; COLMAP's pixel convention)."""
    pc = np.asarray(points_m, float) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    p = camera.named_params()
    if camera.fisheye:
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        k = camera.distortion()
        theta_d = theta * (1 + k[0] * t2 + k[1] * t2**2 + k[2] * t2**3 + k[3] * t2**4)
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        xd, yd = x * scale, y * scale
    else:
        k1, k2, p1, p2 = camera.distortion()
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    pixels: FloatArray = np.column_stack((p["fx"] * xd + p["cx"], p["fy"] * yd + p["cy"]))
    return pixels


def _rotation(omega: FloatArray) -> FloatArray:
    """Rodrigues: rotation matrix of the rotation vector `omega` (radians)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R: FloatArray = np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * (Kx @ Kx)
    return R


@dataclass(frozen=True)
class PoseAccuracy:
    """One-sigma accuracy of a camera: position (x, y, z) m in W and rotation (about W's
    x, y, z) degrees; `source` says where it came from."""

    position_sigma_m: tuple[float, float, float]
    rotation_sigma_deg: tuple[float, float, float]
    source: str


def pose_accuracy(
    camera: ExportCamera, *, min_points: int = 6, step: float = 1e-6
) -> PoseAccuracy | None:
    """Motion-only covariance of the camera's pose: the Gauss-Newton covariance
    sigma^2 (J^T J)^-1 of its reprojection residuals with the sparse points held fixed,
    sigma the image's own RMS residual (px, at least 0.1 px). Parameters: the camera
    centre in W and a small rotation about W's axes (`R_W_C <- Exp(d) R_W_C`). Holding the
    points fixed makes this a lower bound (it leaves out the points' and the gauge's
    uncertainty). None when the image observes fewer than `min_points` points or the
    system is degenerate."""
    if len(camera.points_m) < min_points:
        return None
    world_from_cam = camera.world_from_cam
    R_wc, centre = world_from_cam[:3, :3], world_from_cam[:3, 3]

    def pixels(delta: FloatArray) -> FloatArray:
        R = _rotation(delta[3:]) @ R_wc
        c = centre + delta[:3]
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = R.T
        cam_from_world[:3, 3] = -R.T @ c
        return project(camera, camera.points_m, cam_from_world).ravel()

    base = pixels(np.zeros(6))
    residual = base - camera.pixels.ravel()
    # Per-coordinate RMS with the six pose parameters taken out of the degrees of freedom.
    dof = max(len(residual) - 6, 1)
    sigma_px = max(float(np.sqrt(np.sum(residual**2) / dof)), 0.1)
    J = np.empty((len(base), 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = step
        J[:, i] = (pixels(d) - pixels(-d)) / (2 * step)
    H = J.T @ J
    if np.linalg.cond(H) > 1e14:
        return None
    cov = sigma_px**2 * np.linalg.inv(H)
    sig = np.sqrt(np.diag(cov))
    return PoseAccuracy(
        position_sigma_m=(float(sig[0]), float(sig[1]), float(sig[2])),
        rotation_sigma_deg=tuple(float(np.degrees(s)) for s in sig[3:]),  # type: ignore[arg-type]
        source=f"reprojection ({len(camera.points_m)} points, {sigma_px:.2f} px)",
    )


def read_cameras(model_dir: Path | str) -> list[ExportCamera]:
    """The registered images of a COLMAP binary or text model, in image-name order.

    Raises InputError when the model is missing or a camera model is not one of
    `CAMERA_PARAMS`.
    """
    import pycolmap

    model_dir = Path(model_dir)
    if not ((model_dir / "images.bin").is_file() or (model_dir / "images.txt").is_file()):
        raise InputError(f"{model_dir}: no COLMAP model (expected cameras.bin, images.bin)")
    rec = pycolmap.Reconstruction(str(model_dir))
    xyz = {int(pid): np.asarray(point.xyz, float) for pid, point in rec.points3D.items()}
    cameras = []
    for image_id in rec.reg_image_ids():
        image = rec.images[image_id]
        camera = rec.cameras[image.camera_id]
        model = str(camera.model_name)
        if model not in CAMERA_PARAMS:
            raise InputError(
                f"{model_dir}: camera {camera.camera_id} is {model} "
                f"(expected one of {', '.join(CAMERA_PARAMS)})"
            )
        pose = np.eye(4)
        pose[:3, :] = np.asarray(image.cam_from_world().matrix(), float)
        seen = [p for p in image.points2D if p.has_point3D()]
        cameras.append(
            ExportCamera(
                name=str(image.name),
                camera_id=int(image.camera_id),
                model=model,
                params=tuple(float(v) for v in camera.params),
                width=int(camera.width),
                height=int(camera.height),
                cam_from_world=pose,
                points_m=np.array([xyz[int(p.point3D_id)] for p in seen]).reshape(-1, 3),
                pixels=np.array([np.asarray(p.xy, float) for p in seen]).reshape(-1, 2),
            )
        )
    cameras.sort(key=lambda c: c.name)
    if not cameras:
        raise InputError(f"{model_dir}: the model has no registered images")
    return cameras
