"""What we know about GoPro cameras: model names, IMU axes, a first intrinsics guess, IMU noise.

Pure data and math, no I/O.

**Model.** `camera_model_name(firmware, gpmf_model)` names the camera from the
GPMF "Global Settings" model string (MINF, HERO8+) or else from the firmware
prefix (FIRM, e.g. "HD5.02" = HERO5 Black); `lookup_camera` gives its entry in
`GOPRO_CAMERAS`.

**IMU axes.** GoPro labels its IMU axes X, Y, Z with, as HERO5 names the
streams ("Accelerometer (up/down, right/left, forward/back)" for data order
Z, X, Y): X to the camera's right, Y forward (out of the lens), Z up, looking
from behind the camera held level. A stream stores its three values in a
camera-specific order. What GoPro's gpmf-parser documents (README camera
tables, GPMF_common.h key list), per generation:

- HERO5 Black and Session: ACCL/GYRO data order Z, X, Y; no ORIN.
- Fusion: -Y, X, Z (our "yXZ"); no ORIN.
- HERO6 Black: Y, -X, Z ("YxZ"); later firmware also writes it as ORIN.
- HERO7 Black: the HERO6 metadata unchanged, so "YxZ" (its files write ORIN "YxZ").
- HERO8 Black onwards and the MAX: the file says, in three keys on ACCL and GYRO:
  ORIN, the input order (letter i names the axis value i measures, lower case
  = negated, e.g. "zxY" on a HERO8, "XzY" on the MAX, "ZXY" on a HERO9);
  ORIO, the output order the values are presented in (every camera that
  writes it says "ZXY", the HERO5's order); and MTRX, the 3x3 matrix from
  input to output values, which must equal `orientation_matrix(ORIN, ORIO)`
  (checked on the real MAX clip in tests/real/test_gyro_check_gopro.py).
  The file's ORIN always wins over the model table below.

The signs of X and Y are where the documentation and our data part: the
HERO5 Black's documented Z, X, Y with the reading above made the karma
drone's accelerometer read its forward acceleration backwards and the gyro
turn the images the wrong way; "Zxy" (X and Y negated, a 180 degree turn about
Z) is what that real clip measures (the gyro check: focal x1.345, every axis
correlated positively). HERO5 Session shares the Black's documented row and so
its entry. No rigid (unstabilised) HERO8+ clip is at hand to settle the same
question for ORIN cameras; the gyro check's per-axis correlations
(`gyro_check_axis_correlation` in stats.json) are the place to look when one is.

We publish the IMU in a **camera-aligned body frame B**: axes parallel to the
OpenCV camera frame C (x right, y down, z forward), origin at the IMU. So
`p_C = R_C_B p_B` with `R_C_B = I`, and the default Kalibr `T_cam_imu`
written by the importer is the identity (IMU a few centimetres from the
lens: translation unknown, left at 0). A camera held level and still reads
about (0, -9.81, 0) m/s² in B (specific force points up, -y).

**Intrinsics guess.** With no calibration, `guess_camera` builds a Kalibr
pinhole-equidistant (fisheye) model whose focal length reproduces the
model's nominal horizontal field of view in its widest ("Wide") lens mode
across the 16:9/4:3 image width, principal point at the image centre, zero
distortion coefficients. Behind a flat dome-less housing port in water the
paraxial focal length grows by the refractive index (1.333), so
`medium="water"` multiplies it. This is a starting point for calibration
(Kalibr/SLAM refine it), good to perhaps 5-10 % in focal length.

**IMU noise.** `GOPRO_IMU_NOISE` gives Kalibr continuous-time densities for
the Bosch/InvenSense consumer MEMS parts GoPro uses: datasheet values
inflated about 10x, as Kalibr advises for real (vibrating, warming) use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from shared.calibration.cameras import PinholeEquidistant
from shared.calibration.kalibr import ImuNoise
from shared.errors import InputError

WATER_REFRACTIVE_INDEX = 1.333
"""Sea water at ~15 C, visible light; flat-port focal-length factor (paraxial)."""

Medium = Literal["air", "water"]

# R_C_G: GoPro IMU axes (X right, Y forward, Z up) -> OpenCV camera axes
# (x right, y down, z forward): x_C = X, y_C = -Z, z_C = Y.
CAM_FROM_GOPRO_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True, kw_only=True)
class GoProCamera:
    """One GoPro model.

    `firmware_prefixes`: FIRM prefixes ("HD5.02") that identify it;
    `hfov_wide_deg`: nominal horizontal field of view of the Wide lens mode
    (degrees, across the image width; GoPro's published figures);
    `imu_axis_order`: ORIN-style order of the ACCL/GYRO values for cameras
    that do not write ORIN (None: the file must say).
    """

    name: str
    firmware_prefixes: tuple[str, ...]
    hfov_wide_deg: float
    imu_axis_order: str | None = "ZXY"


GOPRO_CAMERAS: tuple[GoProCamera, ...] = (
    # HERO5 Black: checked on a real clip (karma.mp4) against the drone's own
    # velocity log and the image rotation: GoPro X and Y point the other way.
    GoProCamera(name="HERO5 Black", firmware_prefixes=("HD5.02",), hfov_wide_deg=118.2,
                imu_axis_order="Zxy"),
    # HERO5 Session: the same documented data order as the Black, so the same signs.
    GoProCamera(name="HERO5 Session", firmware_prefixes=("HD5.03",), hfov_wide_deg=118.2,
                imu_axis_order="Zxy"),
    GoProCamera(name="HERO6 Black", firmware_prefixes=("HD6.01",), hfov_wide_deg=118.2,
                imu_axis_order="YxZ"),
    # HERO7 Black: HERO6 metadata unchanged (gpmf-parser README), so HERO6's Y, -X, Z.
    GoProCamera(name="HERO7 Black", firmware_prefixes=("HD7.01",), hfov_wide_deg=118.2,
                imu_axis_order="YxZ"),
    GoProCamera(name="HERO7 Silver", firmware_prefixes=("HD7.02",), hfov_wide_deg=118.2,
                imu_axis_order="YXz"),
    GoProCamera(name="HERO7 White", firmware_prefixes=("HD7.03",), hfov_wide_deg=118.2),
    GoProCamera(name="HERO8 Black", firmware_prefixes=("HD8.01",), hfov_wide_deg=118.2),
    GoProCamera(name="HERO9 Black", firmware_prefixes=("HD9.01",), hfov_wide_deg=118.2),
    GoProCamera(name="HERO10 Black", firmware_prefixes=("H21.01",), hfov_wide_deg=118.2),
    GoProCamera(name="HERO11 Black", firmware_prefixes=("H22.01",), hfov_wide_deg=122.6),
    GoProCamera(name="HERO11 Black Mini", firmware_prefixes=("H22.03",), hfov_wide_deg=122.6),
    GoProCamera(name="HERO12 Black", firmware_prefixes=("H23.01",), hfov_wide_deg=122.6),
    GoProCamera(name="HERO13 Black", firmware_prefixes=("H24.01",), hfov_wide_deg=122.6),
    GoProCamera(name="GoPro Max", firmware_prefixes=("H19.03",), hfov_wide_deg=118.2),
    GoProCamera(name="GoPro Fusion", firmware_prefixes=("FS1.04",), hfov_wide_deg=118.2,
                imu_axis_order="yXZ"),
)  # fmt: skip

UNKNOWN_CAMERA = GoProCamera(
    name="GoPro (unknown model)", firmware_prefixes=(), hfov_wide_deg=118.2
)
"""Used when neither MINF nor FIRM identify the camera (HERO5-like defaults)."""

GOPRO_IMU_NOISE = {
    "accelerometer_noise_density": 2.0e-2,  # m/s^2/sqrt(Hz)  (datasheet ~1.8e-3, x10)
    "accelerometer_random_walk": 4.0e-4,  # m/s^3/sqrt(Hz)
    "gyroscope_noise_density": 1.7e-3,  # rad/s/sqrt(Hz)  (datasheet ~1.2e-4, x10+)
    "gyroscope_random_walk": 2.0e-5,  # rad/s^2/sqrt(Hz)
}
"""Typical Kalibr noise values for GoPro IMUs (see the module docstring)."""


def lookup_camera(*, firmware: str | None, gpmf_model: str | None = None) -> GoProCamera:
    """The `GOPRO_CAMERAS` entry for a camera: by MINF model name, else by FIRM prefix.

    Returns `UNKNOWN_CAMERA` when neither matches (never raises: an unknown
    model still imports, with default assumptions written to session.yaml).
    """
    if gpmf_model:
        wanted = gpmf_model.strip().lower()
        for camera in GOPRO_CAMERAS:
            if camera.name.lower() == wanted:
                return camera
    if firmware:
        for camera in GOPRO_CAMERAS:
            if any(firmware.startswith(prefix) for prefix in camera.firmware_prefixes):
                return camera
    return UNKNOWN_CAMERA


def camera_model_name(*, firmware: str | None, gpmf_model: str | None = None) -> str:
    """A readable model name: MINF when the file has it, else from the firmware prefix."""
    if gpmf_model and gpmf_model.strip():
        return gpmf_model.strip()
    camera = lookup_camera(firmware=firmware)
    if camera is UNKNOWN_CAMERA and firmware:
        return f"GoPro (firmware {firmware})"
    return camera.name


def axis_order_matrix(order: str, *, source: str = "<ORIN>") -> np.ndarray:
    """(3, 3) matrix M with `v_gopro = M @ v_file` for an ORIN-style order such as "XzY".

    Letter i names the GoPro axis (X, Y, Z) that value i measures; lower case
    means the value is the negated axis. InputError when it is not a
    permutation of X, Y, Z.
    """
    if len(order) != 3 or sorted(order.upper()) != ["X", "Y", "Z"]:
        raise InputError(f"{source}: IMU axis order {order!r} (expected a permutation of XYZ)")
    matrix = np.zeros((3, 3))
    for column, letter in enumerate(order):
        matrix["XYZ".index(letter.upper()), column] = -1.0 if letter.islower() else 1.0
    return matrix


def orientation_matrix(orin: str, orio: str, *, source: str = "<ORIN>") -> np.ndarray:
    """(3, 3) matrix M with `v_out = M @ v_in` for a stream's ORIN (input) and ORIO
    (output) orders: what GoPro's MTRX key must hold for the same stream.

    Both orders name GoPro axes, lower case negated; InputError when either is
    not a permutation of X, Y, Z.
    """
    into_gopro = axis_order_matrix(orin, source=source)
    out_of_gopro = axis_order_matrix(orio, source=source)
    matrix: np.ndarray = out_of_gopro.T @ into_gopro
    return matrix


def body_from_file_axes(order: str, *, source: str = "<ORIN>") -> np.ndarray:
    """(3, 3) rotation `R_B_file`: file-order IMU values -> camera-aligned body frame B."""
    rotation: np.ndarray = CAM_FROM_GOPRO_AXES @ axis_order_matrix(order, source=source)
    return rotation


def guess_camera(
    camera: GoProCamera,
    *,
    width: int,
    height: int,
    medium: Medium = "water",
) -> PinholeEquidistant:
    """A first intrinsics guess for `camera` at `width` x `height` pixels (see module docstring).

    Equidistant model: r = f * theta, with f chosen so that the image half
    width spans half the Wide horizontal field of view; square pixels;
    principal point at the centre ((W-1)/2, (H-1)/2, OpenCV pixel centres).
    `medium` "water" scales f by `WATER_REFRACTIVE_INDEX` (flat port).
    """
    if width <= 0 or height <= 0:
        raise InputError(f"image size {width}x{height}: expected positive pixel counts")
    if medium not in ("air", "water"):
        raise InputError(f"medium {medium!r}: expected 'air' or 'water'")
    half_fov_rad = math.radians(camera.hfov_wide_deg) / 2.0
    focal_px = (width / 2.0) / half_fov_rad
    if medium == "water":
        focal_px *= WATER_REFRACTIVE_INDEX
    return PinholeEquidistant(
        width=width,
        height=height,
        fx=focal_px,
        fy=focal_px,
        cx=(width - 1) / 2.0,
        cy=(height - 1) / 2.0,
    )


def gopro_imu_noise(update_rate_hz: float, *, topic: str = "/imu0") -> ImuNoise:
    """`GOPRO_IMU_NOISE` as a Kalibr `ImuNoise` at the measured sample rate (Hz)."""
    if not update_rate_hz > 0:
        raise InputError(f"IMU rate {update_rate_hz} Hz: expected a positive rate")
    return ImuNoise(update_rate_hz=float(update_rate_hz), topic=topic, **GOPRO_IMU_NOISE)
