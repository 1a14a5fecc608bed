"""EuRoC MAV (ASL) dataset folders, as visual-inertial tools read and write them.

Layout (Burri et al. 2016; also TUM-VI, UZH-FPV exports)::

    <folder>/mav0/
      cam0/data.csv            #timestamp [ns],filename
      cam0/data/<stamp_ns>.png
      cam0/sensor.yaml         T_BS (body from camera), rate_hz, resolution,
                               camera_model, intrinsics, distortion_model,
                               distortion_coefficients
      imu0/data.csv            #timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]
      imu0/sensor.yaml         T_BS, rate_hz, noise densities and random walks
      state_groundtruth_estimate0/data.csv
                               #timestamp, p_RS_R_x [m], ..., q_RS_w [], q_RS_x [], ...,
                               v_RS_R_x [m s^-1], ..., b_w_RS_S_x [rad s^-1], ...,
                               b_a_RS_S_x [m s^-2], ...
      state_groundtruth_estimate0/sensor.yaml

The body frame B is the IMU frame (imu0's T_BS is the identity), so the
camera's T_BS is `imu_from_cam`. Ground truth holds body poses in the
reference frame R (`Trajectory` poses `T_R_B`), quaternions in w, x, y, z
order. Time stamps are int64 nanoseconds, kept exact (never through a float).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.calibration.cameras import CAMERA_MODELS
from shared.calibration.kalibr import (
    CameraCalibration,
    ImuNoise,
    format_yaml_float,
    load_yaml_mapping,
)
from shared.clock import NS_PER_S, seconds_from_ns
from shared.errors import InputError
from shared.fsutil import atomic_path
from shared.geometry import invert_pose, make_pose, matrix_from_quat_wxyz, quat_wxyz_from_matrix
from shared.trajectory import Trajectory

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
LOG = logging.getLogger(__name__)

CAMERA_HEADER = "#timestamp [ns],filename"
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GROUNDTRUTH_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
    "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
    "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
    "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)

# EuRoC spells Kalibr's "radtan" as "radial-tangential"; both are accepted on reading.
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1

_DISTORTION_NAMES = {
    "radial-tangential": "radtan",
    "radtan": "radtan",
    "plumb_bob": "radtan",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
}
_EUROC_DISTORTION = {"radtan": "radial-tangential", "equidistant": "equidistant"}


def _row(values: list[float]) -> str:
    # repr is the shortest text that reads back to the same double.
    return ",".join(repr(v) for v in values)


def _f(value: float) -> str:
    return format_yaml_float(value)


def _flist(values: list[float]) -> str:
    return "[" + ", ".join(format_yaml_float(v) for v in values) + "]"


def _yaml_matrix_block(matrix: FloatArray) -> str:
    rows = [", ".join(format_yaml_float(float(v)) for v in row) for row in matrix]
    body = ",\n         ".join(rows)
    return f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{body}]\n"


def _check_vectors(name: str, values: ArrayLike, count: int) -> FloatArray:
    array = np.asarray(values, dtype=np.float64)
    if array.shape != (count, 3):
        raise ValueError(f"{name}: expected shape ({count}, 3), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: contains non-finite values")
    return array


class EurocWriter:
    """Write an EuRoC folder `<folder>/mav0/...`; use as a context manager.

    Everything goes to a temporary folder beside `folder`, renamed into place
    when the `with` block ends without an exception (or on `close()`); an
    exception discards it. An existing `folder` is refused unless `overwrite`.

    camera: the cam0 calibration (intrinsics and `cam_from_imu` for T_BS).
    imu_noise: written to imu0/sensor.yaml when given (its `update_rate_hz` is
        the IMU `rate_hz`; otherwise the rate is estimated from the stamps).
    """

    def __init__(
        self,
        folder: Path | str,
        *,
        camera: CameraCalibration,
        imu_noise: ImuNoise | None = None,
        overwrite: bool = False,
    ) -> None:
        self.folder = Path(folder)
        self.camera = camera
        self.imu_noise = imu_noise
        self._stack = contextlib.ExitStack()
        self._root = self._stack.enter_context(atomic_path(self.folder, overwrite=overwrite))
        self._mav = self._root / "mav0"
        (self._mav / "cam0" / "data").mkdir(parents=True)
        (self._mav / "imu0").mkdir(parents=True)
        self._camera_csv: IO[str] = self._stack.enter_context(
            (self._mav / "cam0" / "data.csv").open("w", encoding="utf-8", newline="\n")
        )
        self._camera_csv.write(CAMERA_HEADER + "\n")
        self._imu_csv: IO[str] = self._stack.enter_context(
            (self._mav / "imu0" / "data.csv").open("w", encoding="utf-8", newline="\n")
        )
        self._imu_csv.write(IMU_HEADER + "\n")
        self._image_stamps: list[int] = []
        self._imu_first_ns: int | None = None
        self._imu_last_ns: int | None = None
        self._imu_count = 0
        self._closed = False

    def __enter__(self) -> EurocWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
        else:
            self._closed = True
            self._stack.__exit__(exc_type, exc, traceback)

    def add_image(self, stamp_ns: int, image: NDArray[np.uint8]) -> None:
        """Add the cam0 image taken at `stamp_ns` (int ns, increasing), grey or BGR uint8."""
        import cv2

        self._check_open()
        stamp = int(stamp_ns)
        if self._image_stamps and stamp <= self._image_stamps[-1]:
            raise ValueError(
                f"image stamps must increase: {stamp} ns after {self._image_stamps[-1]} ns"
            )
        array = np.asarray(image)
        camera = self.camera.camera
        if array.dtype != np.uint8 or array.shape[:2] != (camera.height, camera.width):
            raise ValueError(
                f"expected a uint8 image of {camera.width}x{camera.height}, "
                f"got {array.dtype} {array.shape}"
            )
        name = f"{stamp}.png"
        if not cv2.imwrite(str(self._mav / "cam0" / "data" / name), array):
            raise OSError(f"cv2.imwrite failed for {name}")
        self._camera_csv.write(f"{stamp},{name}\n")
        self._image_stamps.append(stamp)

    def add_imu(self, stamps_ns: ArrayLike, gyro_rad_s: ArrayLike, accel_m_s2: ArrayLike) -> None:
        """Append IMU samples: stamps (N,) int ns increasing (also across calls), gyro (N,3)
        rad/s and specific force (N,3) m/s^2 in the IMU frame."""
        self._check_open()
        stamps = np.asarray(stamps_ns)
        if stamps.ndim != 1 or (stamps.size and not np.issubdtype(stamps.dtype, np.integer)):
            raise ValueError("stamps_ns must be a 1-D array of integer nanoseconds")
        stamps = stamps.astype(np.int64)
        gyro = _check_vectors("gyro_rad_s", gyro_rad_s, len(stamps))
        accel = _check_vectors("accel_m_s2", accel_m_s2, len(stamps))
        if not len(stamps):
            return
        previous = self._imu_last_ns
        if np.any(np.diff(stamps) <= 0) or (previous is not None and stamps[0] <= previous):
            raise ValueError("IMU stamps must be strictly increasing (also across add_imu calls)")
        buffer = io.StringIO()
        for stamp, g, a in zip(stamps.tolist(), gyro.tolist(), accel.tolist(), strict=True):
            buffer.write(f"{stamp},{_row(g + a)}\n")
        self._imu_csv.write(buffer.getvalue())
        if self._imu_first_ns is None:
            self._imu_first_ns = int(stamps[0])
        self._imu_last_ns = int(stamps[-1])
        self._imu_count += len(stamps)

    def set_groundtruth(
        self,
        trajectory: Trajectory,
        velocities_m_s: ArrayLike | None = None,
        gyro_bias: ArrayLike | None = None,
        accel_bias: ArrayLike | None = None,
    ) -> None:
        """Write state_groundtruth_estimate0 from body poses `T_R_B` (trajectory).

        velocities_m_s: (N,3) body velocity in R; default: finite differences of the
            positions over time (central inside, one-sided at the ends).
        gyro_bias (rad/s), accel_bias (m/s^2): (N,3) IMU biases; default zero.
        """
        self._check_open()
        count = len(trajectory)
        positions = trajectory.poses[:, :3, 3]
        if velocities_m_s is None:
            if count >= 2:
                times_s = seconds_from_ns(trajectory.stamps_ns - trajectory.stamps_ns[0])
                velocities = np.gradient(positions, times_s, axis=0)
            else:
                velocities = np.zeros((count, 3))
        else:
            velocities = _check_vectors("velocities_m_s", velocities_m_s, count)
        zeros = np.zeros((count, 3))
        gyro = zeros if gyro_bias is None else _check_vectors("gyro_bias", gyro_bias, count)
        accel = zeros if accel_bias is None else _check_vectors("accel_bias", accel_bias, count)
        quats = quat_wxyz_from_matrix(trajectory.poses[:, :3, :3])
        folder = self._mav / "state_groundtruth_estimate0"
        folder.mkdir(exist_ok=True)
        columns = np.hstack([positions, quats, velocities, gyro, accel]).tolist()
        lines = [GROUNDTRUTH_HEADER]
        lines += [
            f"{stamp},{_row(values)}"
            for stamp, values in zip(trajectory.stamps_ns.tolist(), columns, strict=True)
        ]
        (folder / "data.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
        (folder / "sensor.yaml").write_text(
            "# Ground truth of the body (IMU) frame in the reference frame R.\n"
            "sensor_type: visual-inertial\n"
            "comment: written by wreckmap\n"
            "# Sensor extrinsics wrt. the body-frame (identity: the estimate is of B itself).\n"
            + _yaml_matrix_block(np.eye(4)),
            encoding="utf-8",
        )

    def close(self) -> Path:
        """Write the sensor.yaml files and move the folder into place; returns `folder`."""
        if self._closed:
            return self.folder
        self._closed = True
        try:
            self._write_camera_yaml()
            self._write_imu_yaml()
        except BaseException as error:
            self._stack.__exit__(type(error), error, error.__traceback__)
            raise
        self._stack.close()
        return self.folder

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self.folder}: EurocWriter already closed")

    def _write_camera_yaml(self) -> None:
        camera = self.camera.camera
        _, distortion = camera.kalibr_model
        K = camera.intrinsic_matrix
        intrinsics = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
        coefficients = [float(c) for c in camera.opencv_distortion[:4]]
        stamps = np.array(self._image_stamps, dtype=np.int64)
        rate = NS_PER_S / float(np.median(np.diff(stamps))) if len(stamps) >= 2 else 0.0
        topic = json.dumps(self.camera.topic)
        lines = [
            "# General sensor definitions.",
            "sensor_type: camera",
            "comment: written by wreckmap",
            f"rostopic: {topic}  # image stream of {self.camera.name}",
            "",
            "# Sensor extrinsics wrt. the body-frame (body = IMU): T_BS = imu_from_cam.",
            _yaml_matrix_block(self.camera.imu_from_cam),
            "# Camera specific definitions.",
            f"rate_hz: {_f(rate)}  # median frame rate of the images, Hz (0: < 2 images)",
            f"resolution: [{camera.width}, {camera.height}]  # [width, height], pixels",
            f"camera_model: {camera.kalibr_model[0]}",
            f"intrinsics: {_flist(intrinsics)}  # fu, fv, cu, cv (pixels)",
            f"distortion_model: {_EUROC_DISTORTION[distortion]}",
            f"distortion_coefficients: {_flist(coefficients)}",
            "# Kalibr's time shift (t_imu = t_cam + shift), seconds; stamps are not shifted.",
            f"timeshift_cam_imu: {_f(self.camera.timeshift_cam_imu_s)}",
        ]
        (self._mav / "cam0" / "sensor.yaml").write_text("\n".join(lines) + "\n", encoding="utf-8")

    def _write_imu_yaml(self) -> None:
        noise = self.imu_noise
        if noise is not None:
            rate = noise.update_rate_hz
        elif self._imu_count >= 2 and self._imu_first_ns is not None:
            span_ns = float((self._imu_last_ns or 0) - self._imu_first_ns)
            rate = (self._imu_count - 1) * NS_PER_S / span_ns
        else:
            rate = 0.0
        lines = [
            "# General sensor definitions.",
            "sensor_type: imu",
            "comment: written by wreckmap",
            "",
            "# Sensor extrinsics wrt. the body-frame (the IMU is the body).",
            _yaml_matrix_block(np.eye(4)),
            f"rate_hz: {_f(rate)}  # Hz",
        ]
        if noise is not None:
            lines += [
                "",
                "# inertial sensor noise model parameters (continuous time)",
                f"gyroscope_noise_density: {_f(noise.gyroscope_noise_density)}"
                "  # rad / s / sqrt(Hz)",
                f"gyroscope_random_walk: {_f(noise.gyroscope_random_walk)}  # rad / s^2 / sqrt(Hz)",
                f"accelerometer_noise_density: {_f(noise.accelerometer_noise_density)}"
                "  # m / s^2 / sqrt(Hz)",
                f"accelerometer_random_walk: {_f(noise.accelerometer_random_walk)}"
                "  # m / s^3 / sqrt(Hz)",
                f"rostopic: {json.dumps(noise.topic)}",
            ]
        (self._mav / "imu0" / "sensor.yaml").write_text("\n".join(lines) + "\n", encoding="utf-8")


@dataclass
class EurocDataset:
    """An EuRoC folder in memory (images stay on disk).

    image_stamps_ns (N,) int64 and image_paths (N,) of cam0; IMU stamps (M,) int64
    with gyro (M,3) rad/s and accel (M,3) m/s^2; ground truth body poses `T_R_B`
    with optional velocities (m/s) and biases (rad/s, m/s^2); camera and IMU noise
    from the sensor.yaml files when present.
    """

    image_stamps_ns: IntArray
    image_paths: list[Path]
    imu_stamps_ns: IntArray
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    groundtruth: Trajectory | None
    camera: CameraCalibration | None
    imu_noise: ImuNoise | None
    groundtruth_velocities_m_s: FloatArray | None = None
    groundtruth_gyro_bias: FloatArray | None = None
    groundtruth_accel_bias: FloatArray | None = None


def _read_lines(path: Path, *, errors: str = "strict") -> list[str]:
    try:
        text = path.read_text(encoding="utf-8", errors=errors)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read ({error})") from None
    return text.splitlines()


def _read_numeric_csv(
    path: Path, columns: int, what: str, *, min_columns: int | None = None
) -> tuple[IntArray, FloatArray]:
    """Stamps (int ns, exact) and up to `columns` float columns after them.

    Rows may carry as few as `min_columns` values (default: all `columns`); the
    first data row fixes the count for the file. '#' lines are comments.
    """
    stamps: list[int] = []
    rows: list[list[float]] = []
    width: int | None = None
    least = columns if min_columns is None else min_columns
    for number, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        if width is None:
            width = min(max(len(fields) - 1, 0), columns)
        if len(fields) - 1 < max(width, least):
            raise InputError(
                f"{path}: line {number}: expected {max(width, least) + 1} comma-separated "
                f"values ({what}), found {len(fields)}"
            )
        try:
            stamp = int(fields[0])
            values = [float(f) for f in fields[1 : width + 1]]
        except ValueError:
            raise InputError(
                f"{path}: line {number}: expected an integer ns stamp and numbers ({what})"
            ) from None
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"{path}: line {number}: non-finite value")
        if not _INT64_MIN <= stamp <= _INT64_MAX:
            raise InputError(f"{path}: line {number}: time stamp {fields[0]} ns outside int64")
        if stamps and stamp <= stamps[-1]:
            raise InputError(
                f"{path}: line {number}: time stamp {stamp} ns not after {stamps[-1]} ns"
            )
        stamps.append(stamp)
        rows.append(values)
    shape = (len(rows), width if width is not None else columns)
    return np.array(stamps, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(shape)


def _read_camera_csv(path: Path) -> tuple[IntArray, list[Path]]:
    stamps: list[int] = []
    paths: list[Path] = []
    data_folder = path.parent / "data"
    for number, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        digits = fields[0].removeprefix("-")
        # isascii: "²" passes isdigit() but int() refuses it.
        if len(fields) != 2 or not (digits.isascii() and digits.isdigit()) or not fields[1]:
            raise InputError(
                f"{path}: line {number}: expected 'timestamp [ns],filename', got {text[:200]!r}"
            )
        stamp = int(fields[0])
        if not _INT64_MIN <= stamp <= _INT64_MAX:
            raise InputError(f"{path}: line {number}: time stamp {fields[0]} ns outside int64")
        if stamps and stamp <= stamps[-1]:
            raise InputError(
                f"{path}: line {number}: time stamp {stamp} ns not after {stamps[-1]} ns"
            )
        image = data_folder / fields[1]
        try:
            present = image.is_file()
        except OSError as error:  # a name too long for the file system, for example
            raise InputError(
                f"{path}: line {number}: image name {fields[1][:80]!r} unusable ({error.strerror})"
            ) from None
        if not present:
            raise InputError(f"{path}: line {number}: image {fields[1]} missing from {data_folder}")
        stamps.append(stamp)
        paths.append(image)
    return np.array(stamps, dtype=np.int64), paths


def _yaml_numbers(data: dict[str, Any], key: str, count: int, path: Path, what: str) -> list[float]:
    value = data.get(key)
    if not isinstance(value, list) or len(value) != count:
        raise InputError(f"{path}: expected '{key}' as {count} numbers ({what})")
    try:
        numbers = [float(v) for v in value]
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float range
        raise InputError(f"{path}: expected '{key}' as {count} numbers ({what})") from None
    if any(isinstance(v, bool) for v in value) or not all(math.isfinite(v) for v in numbers):
        raise InputError(f"{path}: expected '{key}' as {count} numbers ({what})")
    return numbers


def _read_body_from_sensor(data: dict[str, Any], path: Path) -> FloatArray:
    block = data.get("T_BS")
    values = block.get("data") if isinstance(block, dict) else None
    if not isinstance(block, dict) or block.get("rows") != 4 or block.get("cols") != 4:
        raise InputError(f"{path}: expected 'T_BS' with rows: 4, cols: 4 and 16 'data' values")
    numbers = _yaml_numbers({"data": values}, "data", 16, path, "T_BS row-major 4x4")
    matrix = np.array(numbers, dtype=np.float64).reshape(4, 4)
    rotation = matrix[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: refused just below
        orthonormal = np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4)
    if not orthonormal or not np.allclose(matrix[3], [0, 0, 0, 1]):
        raise InputError(f"{path}: 'T_BS' is not a rigid transform")
    return matrix


def _read_camera_yaml(path: Path, imu_T_BS: FloatArray) -> CameraCalibration:
    data = load_yaml_mapping(path)
    camera_model = data.get("camera_model")
    distortion = _DISTORTION_NAMES.get(str(data.get("distortion_model")))
    camera_class = CAMERA_MODELS.get((str(camera_model), str(distortion)))
    if camera_class is None:
        raise InputError(
            f"{path}: unsupported camera_model/distortion_model "
            f"'{camera_model}'/'{data.get('distortion_model')}' "
            "(expected pinhole with radial-tangential or equidistant)"
        )
    intrinsics = _yaml_numbers(data, "intrinsics", 4, path, "fu, fv, cu, cv")
    coefficients = _yaml_numbers(data, "distortion_coefficients", 4, path, "4 coefficients")
    resolution = data.get("resolution")
    if not (
        isinstance(resolution, list)
        and len(resolution) == 2
        and all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in resolution)
    ):
        raise InputError(f"{path}: expected 'resolution' as 2 positive integers [width, height]")
    if intrinsics[0] <= 0 or intrinsics[1] <= 0:
        raise InputError(f"{path}: 'intrinsics' focal lengths must be positive")
    camera = camera_class.from_kalibr((resolution[0], resolution[1]), intrinsics, coefficients)
    body_from_cam = _read_body_from_sensor(data, path)
    # cam_from_imu = (body_from_cam)^-1 @ body_from_imu; the IMU is usually the body itself.
    calibration = CameraCalibration(
        camera=camera, cam_from_imu=invert_pose(body_from_cam) @ imu_T_BS
    )
    topic = data.get("rostopic")
    if isinstance(topic, str):
        calibration.topic = topic
    shift = data.get("timeshift_cam_imu")
    if isinstance(shift, int | float) and not isinstance(shift, bool):
        try:
            calibration.timeshift_cam_imu_s = float(shift)
        except OverflowError:
            raise InputError(f"{path}: 'timeshift_cam_imu' {shift} is out of range") from None
    return calibration


_IMU_NOISE_KEYS = (
    "accelerometer_noise_density",
    "accelerometer_random_walk",
    "gyroscope_noise_density",
    "gyroscope_random_walk",
)


def _read_imu_yaml(path: Path) -> tuple[FloatArray, ImuNoise | None]:
    data = load_yaml_mapping(path)
    body_from_imu = _read_body_from_sensor(data, path) if "T_BS" in data else np.eye(4)
    if not any(key in data for key in _IMU_NOISE_KEYS):
        return body_from_imu, None
    values: dict[str, float] = {}
    for key in (*_IMU_NOISE_KEYS, "rate_hz"):
        value = data.get(key)
        if isinstance(value, str):
            with contextlib.suppress(ValueError):
                value = float(value)
        if isinstance(value, int) and not isinstance(value, bool):
            # An integer beyond float range would overflow float(); NaN is refused below.
            value = float(value) if abs(value) < 2**1023 else math.nan
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not math.isfinite(value)
            or value < 0
        ):
            raise InputError(f"{path}: expected '{key}' as a non-negative number")
        values[key] = float(value)
    topic = data.get("rostopic")
    noise = ImuNoise(
        accelerometer_noise_density=values["accelerometer_noise_density"],
        accelerometer_random_walk=values["accelerometer_random_walk"],
        gyroscope_noise_density=values["gyroscope_noise_density"],
        gyroscope_random_walk=values["gyroscope_random_walk"],
        update_rate_hz=values["rate_hz"],
        topic=topic if isinstance(topic, str) else "/imu0",
    )
    return body_from_imu, noise


def _read_imu_rows_as_recorded(path: Path) -> tuple[IntArray, FloatArray]:
    """imu0 rows in file order as they are: stamps may repeat or go back (left to
    `shared.imu.clean_imu_rows`); a row that is not a stamp and 6 finite numbers is
    skipped with one warning naming its lines."""
    imu_stamps: list[int] = []
    rows: list[list[float]] = []
    skipped: list[int] = []
    for number, line in enumerate(_read_lines(path, errors="replace"), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        try:
            stamp = int(fields[0])
            values = [float(f) for f in fields[1:7]]
        except ValueError:
            skipped.append(number)
            continue
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            skipped.append(number)
            continue
        if not _INT64_MIN <= stamp <= _INT64_MAX:
            skipped.append(number)
            continue
        imu_stamps.append(stamp)
        rows.append(values)
    if skipped:
        LOG.warning(
            "%s: skipped %d rows that are not a stamp and 6 numbers (lines %s)",
            path,
            len(skipped),
            ", ".join(str(n) for n in skipped[:5]) + (", ..." if len(skipped) > 5 else ""),
        )
    return np.array(imu_stamps, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(-1, 6)


def read_euroc(
    folder: Path | str, *, as_recorded: bool = False, groundtruth: bool = True
) -> EurocDataset:
    """Read an EuRoC folder: the one holding `mav0/`, or `mav0` itself.

    cam0/data.csv and imu0/data.csv are required; sensor.yaml files and the
    ground truth are optional (None when absent). Raises InputError naming the
    file (and line) for anything missing or malformed.

    as_recorded: read what a real recorder writes. Either data.csv may be absent
    (empty stamps and arrays), and imu0 rows are taken in file order as they are:
    stamps that repeat or go back are kept for `shared.imu.clean_imu_rows`, and a
    row that is not a stamp and 6 numbers is skipped with a warning.

    groundtruth: False leaves the ground truth unread (None), for readers that never
    use it (a long recording's truth CSV takes seconds to parse).
    """
    folder = Path(folder)
    mav = folder / "mav0" if (folder / "mav0").is_dir() else folder
    if not (mav / "cam0").is_dir() and not (mav / "imu0").is_dir():
        raise InputError(f"{folder}: not an EuRoC folder (expected mav0/cam0 and mav0/imu0)")
    camera_csv = mav / "cam0" / "data.csv"
    imu_csv = mav / "imu0" / "data.csv"
    image_paths: list[Path] = []
    if as_recorded and not camera_csv.is_file():
        image_stamps = np.zeros(0, dtype=np.int64)
    else:
        image_stamps, image_paths = _read_camera_csv(camera_csv)
    if as_recorded and not imu_csv.is_file():
        imu_stamps, imu_values = np.zeros(0, dtype=np.int64), np.zeros((0, 6))
    elif as_recorded:
        imu_stamps, imu_values = _read_imu_rows_as_recorded(imu_csv)
    else:
        imu_stamps, imu_values = _read_numeric_csv(
            imu_csv, 6, "timestamp, gyro xyz rad/s, accel xyz m/s^2"
        )
    body_from_imu, imu_noise = np.eye(4), None
    if (mav / "imu0" / "sensor.yaml").is_file():
        body_from_imu, imu_noise = _read_imu_yaml(mav / "imu0" / "sensor.yaml")
    camera = None
    if (mav / "cam0" / "sensor.yaml").is_file():
        camera = _read_camera_yaml(mav / "cam0" / "sensor.yaml", body_from_imu)
    dataset = EurocDataset(
        image_stamps_ns=image_stamps,
        image_paths=image_paths,
        imu_stamps_ns=imu_stamps,
        gyro_rad_s=imu_values[:, :3].copy(),
        accel_m_s2=imu_values[:, 3:].copy(),
        groundtruth=None,
        camera=camera,
        imu_noise=imu_noise,
    )
    groundtruth_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    if groundtruth and groundtruth_csv.is_file():
        stamps, values = _read_numeric_csv(
            groundtruth_csv,
            16,
            "timestamp, p xyz, q wxyz[, v xyz, gyro bias xyz, accel bias xyz]",
            min_columns=7,
        )
        with np.errstate(over="ignore"):  # 1e308 squared: an infinite norm, refused below
            norms = np.linalg.norm(values[:, 3:7], axis=1)
        unusable = ~np.isfinite(norms) | (norms < 1e-6)
        if np.any(unusable):
            bad = int(np.argmax(unusable))
            raise InputError(
                f"{groundtruth_csv}: data row {bad + 1}: "
                "zero quaternion (or too large to normalise)"
            )
        poses = make_pose(matrix_from_quat_wxyz(values[:, 3:7]), values[:, :3])
        dataset.groundtruth = Trajectory(stamps_ns=stamps, poses=poses)
        # Velocities and biases only when the file carries all 16 values a row.
        if values.shape[1] == 16:
            dataset.groundtruth_velocities_m_s = values[:, 7:10].copy()
            dataset.groundtruth_gyro_bias = values[:, 10:13].copy()
            dataset.groundtruth_accel_bias = values[:, 13:16].copy()
    return dataset
