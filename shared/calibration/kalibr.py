"""Kalibr's YAML files: camera chain, IMU noise and calibration target.

The formats are those Kalibr reads and writes (ethz-asl/kalibr wiki, "YAML
formats"):

- `camchain.yaml` / `camchain-imucam.yaml`: one mapping per camera (`cam0`,
  `cam1`, ...) with `camera_model`, `intrinsics` [fu, fv, pu, pv] (pixels),
  `distortion_model`, `distortion_coeffs`, `resolution` [width, height],
  `T_cam_imu` (4x4 rows, maps IMU coordinates to camera coordinates, i.e.
  `cam_from_imu`), `timeshift_cam_imu` (seconds, t_imu = t_cam + shift),
  `rostopic`, `cam_overlaps`, and for cam1.. `T_cn_cnm1` (camera n from
  camera n-1).
- `imu.yaml`: continuous-time noise densities and bias random walks,
  `update_rate` (Hz), `rostopic`, `model`.
- AprilGrid target YAML: `target_type: 'aprilgrid'`, `tagCols`, `tagRows`,
  `tagSize` (m), `tagSpacing` (ratio), plus our optional `tagIdOffset`.

Files are parsed with `yaml.safe_load`; anything missing or malformed raises
`InputError` naming the file, the camera and the key. Written files carry a
comment with the unit of each key and reload with any YAML parser.
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.cameras import CAMERA_MODELS, CameraModel
from shared.errors import InputError
from shared.fsutil import write_text_atomic

FloatArray = NDArray[np.float64]

# Rotation blocks further than this from orthonormal are rejected (Kalibr writes ~1e-15).
_ORTHONORMAL_TOL = 1e-4


@dataclass
class CameraCalibration:
    """One camera of a Kalibr chain: intrinsics plus the IMU extrinsic and time shift.

    cam_from_imu: `T_C_B` (Kalibr `T_cam_imu`), 4x4, metres; maps IMU-frame points
        into the camera frame.
    timeshift_cam_imu_s: Kalibr's `timeshift_cam_imu`: t_imu = t_cam + shift (seconds).
    topic: the image stream (`rostopic`). name: the chain key ("cam0", ...).
    cam_overlaps: indices of cameras sharing field of view with this one.
    """

    camera: CameraModel
    cam_from_imu: FloatArray = field(default_factory=lambda: np.eye(4))
    timeshift_cam_imu_s: float = 0.0
    topic: str = "/cam0/image_raw"
    name: str = "cam0"
    cam_overlaps: list[int] = field(default_factory=list)

    @property
    def imu_from_cam(self) -> FloatArray:
        """`T_B_C` (4x4): camera pose in the IMU (body) frame; inverse of `cam_from_imu`."""
        rotation = self.cam_from_imu[:3, :3]
        result = np.eye(4)
        result[:3, :3] = rotation.T
        result[:3, 3] = -rotation.T @ self.cam_from_imu[:3, 3]
        return result


@dataclass(frozen=True)
class ImuNoise:
    """Kalibr IMU noise model (continuous time, as the datasheet / Allan deviation gives).

    accelerometer_noise_density: white noise, m/s^2/sqrt(Hz).
    accelerometer_random_walk: bias random walk, m/s^3/sqrt(Hz).
    gyroscope_noise_density: white noise, rad/s/sqrt(Hz).
    gyroscope_random_walk: bias random walk, rad/s^2/sqrt(Hz).
    update_rate_hz: sample rate used to discretise the densities.
    """

    accelerometer_noise_density: float
    accelerometer_random_walk: float
    gyroscope_noise_density: float
    gyroscope_random_walk: float
    update_rate_hz: float
    topic: str = "/imu0"


# ---------------------------------------------------------------------------- parsing helpers


def load_yaml_mapping(path: Path) -> dict[str, Any]:
    """A YAML file from outside (Kalibr's, EuRoC's, OpenCV's) whose top level is a mapping;
    InputError naming `path` when it is missing, unreadable, malformed or not a mapping."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read ({error})") from None
    # OpenCV's FileStorage writes a "%YAML:1.0" directive PyYAML rejects; it adds nothing.
    if text.startswith("%YAML:"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    data = safe_load_yaml(text, path)
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a YAML mapping at the top level")
    return data


# Values quoted in error messages are shortened: YAML aliases can make a tiny file hold
# a tree whose full repr is gigabytes (the "billion laughs" of YAML).
_SHORT = reprlib.Repr()
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxdict = 3, 6, 6
_SHORT.maxstring, _SHORT.maxother, _SHORT.maxlong = 60, 60, 40


def _show(value: Any) -> str:
    """A bounded repr of a value read from YAML, for error messages."""
    return _SHORT.repr(value)


MAX_FLOW_NESTING = 64


def safe_load_yaml(text: str, path: Path) -> Any:
    """`yaml.safe_load` for files from outside; InputError naming `path` when malformed.

    Flow collections ("[[[[...") nested deeper than `MAX_FLOW_NESTING` are refused
    before parsing: PyYAML parses them recursively, and a 100 kB file of brackets
    takes seconds to end in a RecursionError (libyaml's C loader crashes outright).
    Calibration files nest three levels.
    """
    depth = 0
    for line_no, line in enumerate(text.splitlines(), start=1):
        for char in line.split("#", 1)[0]:
            if char in "[{":
                depth += 1
                if depth > MAX_FLOW_NESTING:
                    raise InputError(
                        f"{path}:{line_no}: not valid YAML (collections nested deeper than "
                        f"{MAX_FLOW_NESTING} levels)"
                    )
            elif char in "]}":
                depth -= 1
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid YAML ({error})") from None
    except RecursionError:
        raise InputError(f"{path}: not valid YAML (nested too deeply)") from None


def _number(value: Any) -> float | None:
    # PyYAML reads "1e-05" (no dot) as a string; other writers produce it, so accept it.
    if isinstance(value, bool):
        return None
    try:
        if isinstance(value, int | float | str):
            number = float(value)
        else:
            return None
    except (ValueError, OverflowError):  # not a number, or an integer beyond float range
        return None
    return number if math.isfinite(number) else None


def _numbers(value: Any, count: int | None) -> list[float] | None:
    if not isinstance(value, list) or (count is not None and len(value) != count):
        return None
    numbers = [_number(v) for v in value]
    if any(n is None for n in numbers):
        return None
    return [float(n) for n in numbers if n is not None]


def _require_number(data: Mapping[str, Any], key: str, where: str, what: str) -> float:
    if key not in data:
        raise InputError(f"{where}: missing '{key}' ({what})")
    number = _number(data[key])
    if number is None:
        raise InputError(f"{where}: expected '{key}' as a number ({what}), got {_show(data[key])}")
    return number


def _require_str(data: Mapping[str, Any], key: str, where: str) -> str:
    if key not in data:
        raise InputError(f"{where}: missing '{key}'")
    value = data[key]
    if not isinstance(value, str):
        raise InputError(f"{where}: expected '{key}' as a string, got {_show(value)}")
    return value


def _matrix4(value: Any, key: str, where: str) -> FloatArray:
    rows = value if isinstance(value, list) and len(value) == 4 else None
    parsed = [_numbers(row, 4) for row in rows] if rows is not None else None
    if parsed is None or any(row is None for row in parsed):
        raise InputError(f"{where}: expected '{key}' as 4 rows of 4 numbers")
    matrix = np.array(parsed, dtype=np.float64)
    rotation = matrix[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: refused just below
        orthonormal = np.allclose(rotation.T @ rotation, np.eye(3), atol=_ORTHONORMAL_TOL)
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9) or not orthonormal:
        raise InputError(
            f"{where}: expected '{key}' as a rigid transform "
            "(orthonormal rotation, last row [0, 0, 0, 1])"
        )
    if np.linalg.det(rotation) < 0:
        raise InputError(f"{where}: '{key}' is a reflection, not a rotation (determinant < 0)")
    return matrix


def _camera_sort_key(name: str) -> tuple[int, str]:
    digits = name[3:] if name.startswith("cam") else ""
    # isascii: "cam²" passes isdigit() but int() refuses it.
    return (int(digits), name) if digits.isascii() and digits.isdigit() else (1 << 30, name)


# ------------------------------------------------------------------------------- writing helpers


def format_yaml_float(value: float) -> str:
    """Shortest round-trip text of a float that YAML 1.1 (PyYAML) also reads as a float.

    repr() gives "1e-05", which PyYAML reads as a string; this writes "1.0e-05".
    """
    text = repr(float(value))
    if text in ("nan", "inf", "-inf"):
        raise ValueError(f"cannot write non-finite value {value} to a Kalibr file")
    if "e" in text and "." not in text:
        # PyYAML's float pattern needs a dot: "1e-05" would come back as a string.
        mantissa, exponent = text.split("e")
        text = f"{mantissa}.0e{exponent}"
    return text


def _yaml_list(values: list[float]) -> str:
    return "[" + ", ".join(format_yaml_float(v) for v in values) + "]"


def _yaml_str(value: str) -> str:
    # Quote via the YAML emitter so topics with ':' or '#' survive.
    dumped = yaml.safe_dump(value, default_style=None).strip()
    return dumped.removesuffix("\n...").removesuffix("...").strip()


def _yaml_matrix(matrix: FloatArray, indent: str) -> list[str]:
    return [f"{indent}- {_yaml_list([float(v) for v in row])}" for row in matrix]


def _kalibr_distortion(camera: CameraModel) -> list[float]:
    coeffs = [float(c) for c in np.asarray(camera.opencv_distortion, dtype=np.float64)]
    # Kalibr's radtan has 4 coefficients; OpenCV's plumb-bob vector carries k3 = 0 in 5th place.
    return coeffs[:4]


# ----------------------------------------------------------------------------------- camchain


def _parse_camera(entry: Any, name: str, where: str) -> CameraCalibration:
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected a mapping of camera parameters")
    camera_model = _require_str(entry, "camera_model", where)
    distortion_model = _require_str(entry, "distortion_model", where)
    camera_class = CAMERA_MODELS.get((camera_model, distortion_model))
    if camera_class is None:
        known = ", ".join(f"{c}+{d}" for c, d in CAMERA_MODELS)
        raise InputError(
            f"{where}: unsupported camera_model/distortion_model "
            f"'{camera_model}'+'{distortion_model}' (supported: {known})"
        )
    intrinsics = _numbers(entry.get("intrinsics"), 4)
    if intrinsics is None:
        raise InputError(f"{where}: expected 'intrinsics' as 4 numbers [fu, fv, pu, pv]")
    if intrinsics[0] <= 0 or intrinsics[1] <= 0:
        raise InputError(f"{where}: 'intrinsics' focal lengths fu, fv must be positive")
    coeffs = _numbers(entry.get("distortion_coeffs"), 4)
    if coeffs is None:
        raise InputError(
            f"{where}: expected 'distortion_coeffs' as 4 numbers for '{distortion_model}'"
        )
    resolution = entry.get("resolution")
    if not (
        isinstance(resolution, list)
        and len(resolution) == 2
        and all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in resolution)
    ):
        raise InputError(f"{where}: expected 'resolution' as 2 positive integers [width, height]")
    camera = camera_class.from_kalibr((int(resolution[0]), int(resolution[1])), intrinsics, coeffs)
    calibration = CameraCalibration(camera=camera, name=name)
    if "T_cam_imu" in entry:
        calibration.cam_from_imu = _matrix4(entry["T_cam_imu"], "T_cam_imu", where)
    if "timeshift_cam_imu" in entry:
        calibration.timeshift_cam_imu_s = _require_number(
            entry, "timeshift_cam_imu", where, "seconds"
        )
    if "rostopic" in entry:
        calibration.topic = _require_str(entry, "rostopic", where)
    else:
        calibration.topic = f"/{name}/image_raw"
    if "cam_overlaps" in entry:
        overlaps = entry["cam_overlaps"]
        if not isinstance(overlaps, list) or not all(
            isinstance(o, int) and not isinstance(o, bool) for o in overlaps
        ):
            raise InputError(f"{where}: expected 'cam_overlaps' as a list of camera indices")
        calibration.cam_overlaps = list(overlaps)
    return calibration


def read_camchain(path: Path | str) -> list[CameraCalibration]:
    """Read a Kalibr camchain YAML (`camchain.yaml` or `camchain-imucam.yaml`).

    Cameras come back in index order (cam0, cam1, ...). A camera without
    `T_cam_imu` but with `T_cn_cnm1` gets `cam_from_imu` chained from the
    previous camera; with neither it keeps the identity (camera-only chain).
    """
    path = Path(path)
    data = load_yaml_mapping(path)
    names = sorted(data, key=lambda n: _camera_sort_key(str(n)))
    if not names:
        raise InputError(f"{path}: no cameras (expected keys cam0, cam1, ...)")
    cameras: list[CameraCalibration] = []
    for name in names:
        where = f"{path}: {name}"
        if not str(name).startswith("cam"):
            raise InputError(f"{where}: unexpected top-level key (expected cam0, cam1, ...)")
        entry = data[name]
        calibration = _parse_camera(entry, str(name), where)
        if "T_cam_imu" not in entry and "T_cn_cnm1" in entry and cameras:
            cam_from_previous = _matrix4(entry["T_cn_cnm1"], "T_cn_cnm1", where)
            calibration.cam_from_imu = cam_from_previous @ cameras[-1].cam_from_imu
        cameras.append(calibration)
    return cameras


def format_camchain(cameras: list[CameraCalibration]) -> str:
    """The camchain YAML text for `cameras` (keys as Kalibr writes them, with unit comments)."""
    if not cameras:
        raise ValueError("a camchain needs at least one camera")
    lines: list[str] = []
    for index, calibration in enumerate(cameras):
        camera = calibration.camera
        camera_model, distortion_model = camera.kalibr_model
        K = camera.intrinsic_matrix
        intrinsics = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
        lines += [
            f"{calibration.name}:",
            "  # T_cam_imu: maps IMU-frame points into this camera's frame (rigid, metres)",
            "  T_cam_imu:",
            *_yaml_matrix(calibration.cam_from_imu, "  "),
        ]
        if index > 0:
            previous = cameras[index - 1].cam_from_imu
            inverse_previous = np.eye(4)
            inverse_previous[:3, :3] = previous[:3, :3].T
            inverse_previous[:3, 3] = -previous[:3, :3].T @ previous[:3, 3]
            lines += [
                "  # T_cn_cnm1: maps the previous camera's frame into this one (metres)",
                "  T_cn_cnm1:",
                *_yaml_matrix(calibration.cam_from_imu @ inverse_previous, "  "),
            ]
        overlaps = "[" + ", ".join(str(o) for o in calibration.cam_overlaps) + "]"
        lines += [
            f"  cam_overlaps: {overlaps}",
            f"  camera_model: {camera_model}",
            f"  distortion_coeffs: {_yaml_list(_kalibr_distortion(camera))}"
            f"  # {distortion_model}, dimensionless",
            f"  distortion_model: {distortion_model}",
            f"  intrinsics: {_yaml_list(intrinsics)}  # [fu, fv, pu, pv], pixels",
            f"  resolution: [{camera.width}, {camera.height}]  # [width, height], pixels",
            f"  rostopic: {_yaml_str(calibration.topic)}",
            f"  timeshift_cam_imu: {format_yaml_float(calibration.timeshift_cam_imu_s)}"
            "  # seconds, t_imu = t_cam + shift",
        ]
    return "\n".join(lines) + "\n"


def write_camchain(
    path: Path | str, cameras: list[CameraCalibration], *, overwrite: bool = False
) -> Path:
    """Write `cameras` as a Kalibr camchain YAML (atomic; refuses to overwrite unless asked)."""
    return write_text_atomic(path, format_camchain(cameras), overwrite=overwrite)


# ---------------------------------------------------------------------------------------- imu

_IMU_KEYS = (
    ("accelerometer_noise_density", "m/s^2/sqrt(Hz), white noise (continuous time)"),
    ("accelerometer_random_walk", "m/s^3/sqrt(Hz), bias random walk"),
    ("gyroscope_noise_density", "rad/s/sqrt(Hz), white noise (continuous time)"),
    ("gyroscope_random_walk", "rad/s^2/sqrt(Hz), bias random walk"),
)


def read_imu_yaml(path: Path | str) -> ImuNoise:
    """Read a Kalibr `imu.yaml` (noise densities, random walks, `update_rate` in Hz)."""
    path = Path(path)
    data = load_yaml_mapping(path)
    where = str(path)
    values = {key: _require_number(data, key, where, unit.split(",")[0]) for key, unit in _IMU_KEYS}
    for key, value in values.items():
        if value < 0:
            raise InputError(f"{where}: '{key}' must not be negative, got {value}")
    rate = _require_number(data, "update_rate", where, "Hz")
    if rate <= 0:
        raise InputError(f"{where}: 'update_rate' must be positive (Hz), got {rate}")
    topic = _require_str(data, "rostopic", where) if "rostopic" in data else "/imu0"
    return ImuNoise(
        accelerometer_noise_density=values["accelerometer_noise_density"],
        accelerometer_random_walk=values["accelerometer_random_walk"],
        gyroscope_noise_density=values["gyroscope_noise_density"],
        gyroscope_random_walk=values["gyroscope_random_walk"],
        update_rate_hz=rate,
        topic=topic,
    )


def format_imu_yaml(noise: ImuNoise) -> str:
    """The Kalibr imu.yaml text for `noise`, one commented key a line."""
    lines = [
        f"{key}: {format_yaml_float(getattr(noise, key))}  # {unit}" for key, unit in _IMU_KEYS
    ]
    lines += [
        f"update_rate: {format_yaml_float(noise.update_rate_hz)}  # Hz, to discretise the above",
        f"rostopic: {_yaml_str(noise.topic)}",
        "model: calibrated  # Kalibr IMU model (scale/misalignment not estimated separately)",
    ]
    return "\n".join(lines) + "\n"


def write_imu_yaml(path: Path | str, noise: ImuNoise, *, overwrite: bool = False) -> Path:
    """Write `noise` as a Kalibr imu.yaml (atomic; refuses to overwrite unless asked)."""
    return write_text_atomic(path, format_imu_yaml(noise), overwrite=overwrite)


# ------------------------------------------------------------------------------------- target


def read_target_yaml(path: Path | str) -> AprilGridTarget:
    """Read a Kalibr AprilGrid target YAML (plus our optional `tagIdOffset`, default 0)."""
    path = Path(path)
    data = load_yaml_mapping(path)
    where = str(path)
    target_type = _require_str(data, "target_type", where)
    if target_type != "aprilgrid":
        raise InputError(f"{where}: unsupported target_type '{target_type}' (expected 'aprilgrid')")
    counts: dict[str, int] = {}
    for key in ("tagCols", "tagRows", "tagIdOffset"):
        if key not in data:
            if key == "tagIdOffset":
                counts[key] = 0
                continue
            raise InputError(f"{where}: missing '{key}' (number of tags)")
        value = data[key]
        minimum = 0 if key == "tagIdOffset" else 1
        if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
            raise InputError(
                f"{where}: expected '{key}' as an integer >= {minimum}, got {_show(value)}"
            )
        counts[key] = value
    tag_size = _require_number(data, "tagSize", where, "edge of the tag's black square, metres")
    spacing = _require_number(data, "tagSpacing", where, "gap between tags / tagSize")
    if tag_size <= 0 or spacing <= 0:
        raise InputError(f"{where}: 'tagSize' and 'tagSpacing' must be positive")
    try:
        return AprilGridTarget(
            tag_rows=counts["tagRows"],
            tag_cols=counts["tagCols"],
            tag_size_m=tag_size,
            tag_spacing_ratio=spacing,
            tag_id_offset=counts["tagIdOffset"],
        )
    except ValueError as error:
        raise InputError(f"{where}: 'tagRows', 'tagCols', 'tagIdOffset': {error}") from None


def format_target_yaml(target: AprilGridTarget) -> str:
    """The Kalibr target YAML text for `target`, one commented key a line."""
    size = format_yaml_float(target.tag_size_m)
    spacing = format_yaml_float(target.tag_spacing_ratio)
    lines = [
        "target_type: 'aprilgrid'  # Kalibr grid type",
        f"tagCols: {target.tag_cols}  # number of tags along x",
        f"tagRows: {target.tag_rows}  # number of tags along y",
        f"tagSize: {size}  # edge of a tag's black square (2-cell border included), metres",
        f"tagSpacing: {spacing}  # gap between tags as a fraction of tagSize",
        f"tagIdOffset: {target.tag_id_offset}  # id of the first tag (wreckmap extension)",
    ]
    return "\n".join(lines) + "\n"


def write_target_yaml(
    path: Path | str, target: AprilGridTarget, *, overwrite: bool = False
) -> Path:
    """Write `target` as a Kalibr AprilGrid YAML (atomic; refuses to overwrite unless asked)."""
    return write_text_atomic(path, format_target_yaml(target), overwrite=overwrite)
