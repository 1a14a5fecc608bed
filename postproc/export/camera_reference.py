"""Camera positions with accuracies for Agisoft Metashape and RealityCapture, with the
images undistorted to a pinhole camera (so neither tool has to guess our lens model).

Written into the export folder::

    cameras.csv       label, x, y, z (m), omega, phi, kappa (deg), and one-sigma accuracies
    calibration.xml   the undistorted pinhole camera, as Metashape's calibration file
                      (with several cameras: calibration_camera<id>.xml for each, the
                      CSV's camera_id column says which images it holds)
    images/<label>    the undistorted images (same size and focal length as recorded)

Angles (pure math here): omega, phi, kappa as photogrammetry (and Metashape's reference
pane) define them: `R = Rx(omega) Ry(phi) Rz(kappa)` maps the classical camera axes (x
right, y up, z back, looking along -z) to the world; a camera looking straight down with
the image top towards world +y has all three zero. Our camera axes are OpenCV's (y down,
z forward), so `R = R_W_C diag(1, -1, -1)`.

Accuracies: the position sigma of each camera is its motion-only covariance
(`postproc.export.cameras.pose_accuracy`: reprojection residuals, points held fixed) but
never below `floor_m`; the angle accuracy is the largest rotation sigma about any world
axis, never below `floor_deg`. Images too sparse for a covariance get `default_m` and
`default_deg` (stated in the CSV's `accuracy_source` column).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from postproc.export.cameras import ExportCamera, pose_accuracy

FloatArray = npt.NDArray[np.float64]

CLASSICAL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
CSV_NAME = "cameras.csv"
CALIBRATION_NAME = "calibration.xml"
IMAGE_DIR = "images"
COLUMNS = (
    "label", "x_m", "y_m", "z_m", "omega_deg", "phi_deg", "kappa_deg",
    "x_sigma_m", "y_sigma_m", "z_sigma_m", "angle_sigma_deg", "accuracy_source",
    "camera_id",
)  # fmt: skip


@dataclass(kw_only=True)
class ReferenceOptions:
    """Accuracy floors and defaults of the camera reference (metres, degrees)."""

    floor_m: float = 0.005
    floor_deg: float = 0.05
    default_m: float = 0.10
    default_deg: float = 2.0


def opk_deg(world_from_cam: FloatArray) -> tuple[float, float, float]:
    """(omega, phi, kappa) in degrees of a camera pose `T_W_C` (OpenCV camera axes)."""
    M = np.asarray(world_from_cam, float)[:3, :3] @ CLASSICAL_FROM_OPENCV
    phi = np.arcsin(np.clip(M[0, 2], -1.0, 1.0))
    omega = np.arctan2(-M[1, 2], M[2, 2])
    kappa = np.arctan2(-M[0, 1], M[0, 0])
    return float(np.degrees(omega)), float(np.degrees(phi)), float(np.degrees(kappa))


def label(name: str) -> str:
    """A flat file name for an image name with folders (`s1/123.png` -> `s1__123.png`)."""
    return name.replace("/", "__")


def reference_rows(cameras: list[ExportCamera], options: ReferenceOptions) -> list[dict[str, str]]:
    """One CSV row per camera (see `COLUMNS`), positions in W."""
    rows = []
    for camera in cameras:
        pose = camera.world_from_cam
        # Rounded to the printed precision first so that no "-0.00000" is written.
        omega, phi, kappa = (round(a, 5) + 0.0 for a in opk_deg(pose))
        accuracy = pose_accuracy(camera)
        sigmas: tuple[float, ...]
        if accuracy is None:
            sigmas = (options.default_m,) * 3
            angle = options.default_deg
            source = "default"
        else:
            sigmas = tuple(max(s, options.floor_m) for s in accuracy.position_sigma_m)
            angle = max(max(accuracy.rotation_sigma_deg), options.floor_deg)
            source = accuracy.source
        rows.append(
            {
                "label": label(camera.name),
                "x_m": f"{pose[0, 3]:.4f}", "y_m": f"{pose[1, 3]:.4f}",
                "z_m": f"{pose[2, 3]:.4f}",
                "omega_deg": f"{omega:.5f}", "phi_deg": f"{phi:.5f}",
                "kappa_deg": f"{kappa:.5f}",
                "x_sigma_m": f"{sigmas[0]:.4f}", "y_sigma_m": f"{sigmas[1]:.4f}",
                "z_sigma_m": f"{sigmas[2]:.4f}", "angle_sigma_deg": f"{angle:.4f}",
                "accuracy_source": source,
                "camera_id": str(camera.camera_id),
            }
        )  # fmt: skip
    return rows


def reference_csv(rows: list[dict[str, str]]) -> str:
    """The CSV text: a header row, then one row per camera (comma separated)."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def calibration_xml(camera: ExportCamera) -> str:
    """Metashape's camera calibration file for the undistorted pinhole: `f` = fy, `b1` =
    fx - fy (Metashape's aspect term), `cx`, `cy` offsets of the principal point from the
    image centre (pixels), no distortion."""
    p = camera.named_params()
    values = {
        "projection": "frame", "width": str(camera.width), "height": str(camera.height),
        "f": f"{p['fy']:.6f}", "cx": f"{p['cx'] - camera.width / 2:.6f}",
        "cy": f"{p['cy'] - camera.height / 2:.6f}", "b1": f"{p['fx'] - p['fy']:.6f}",
    }  # fmt: skip
    body = "".join(f"  <{k}>{v}</{k}>\n" for k, v in values.items())
    return f'<?xml version="1.0" encoding="UTF-8"?>\n<calibration>\n{body}</calibration>\n'


def undistort_maps(camera: ExportCamera) -> tuple[npt.NDArray[np.float32], ...]:
    """cv2 remap tables from the recorded image to the pinhole with the same K (the dense
    stage's `undistortion_map`, through COLMAP's own projection of the camera's model)."""
    import pycolmap

    from postproc.dense.undistort import PinholeTarget, undistortion_map

    recorded = pycolmap.Camera(
        model=camera.model, width=camera.width, height=camera.height, params=list(camera.params)
    )
    pinhole = PinholeTarget.of(camera.intrinsic_matrix(), camera.width, camera.height)
    image_map = undistortion_map(recorded, pinhole)
    return (image_map.map_x, image_map.map_y)


def write_camera_reference(
    model_dir: Path,
    image_dir: Path,
    out_dir: Path,
    options: ReferenceOptions,
    *,
    overwrite: bool = False,
) -> Path:
    """Write `cameras.csv`, `calibration.xml` and the undistorted `images/` into
    `out_dir`; returns the CSV's path."""
    import cv2

    from postproc.export.cameras import read_cameras
    from shared.errors import InputError
    from shared.fsutil import atomic_path
    from shared.progress import progress

    cameras = read_cameras(model_dir)
    first = cameras[0]
    with atomic_path(out_dir, overwrite=overwrite) as tmp:
        (tmp / IMAGE_DIR).mkdir(parents=True)
        maps: dict[int, tuple[npt.NDArray[np.float32], ...]] = {}
        for camera in progress(cameras, total=len(cameras), desc="undistort", unit="image"):
            source = image_dir / camera.name
            image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"{source}: not an image OpenCV can read")
            if image.shape[:2] != (camera.height, camera.width):
                raise InputError(
                    f"{source}: {image.shape[1]}x{image.shape[0]} px "
                    f"(expected {camera.width}x{camera.height}, as the model says)"
                )
            if camera.camera_id not in maps:
                maps[camera.camera_id] = undistort_maps(camera)
            map_x, map_y = maps[camera.camera_id]
            flat = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            if not cv2.imwrite(str(tmp / IMAGE_DIR / label(camera.name)), flat):
                raise InputError(f"{source}: cannot write its undistorted copy")
        (tmp / CSV_NAME).write_text(reference_csv(reference_rows(cameras, options)))
        (tmp / CALIBRATION_NAME).write_text(calibration_xml(first))
        distinct = {c.camera_id: c for c in cameras}
        if len(distinct) > 1:
            for camera_id, camera in sorted(distinct.items()):
                (tmp / f"calibration_camera{camera_id}.xml").write_text(calibration_xml(camera))
    return out_dir / CSV_NAME
