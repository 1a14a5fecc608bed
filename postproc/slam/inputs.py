"""Where SLAM gets its images and IMU samples: EuRoC folders and session folders.

Both readers satisfy the small `SlamInput` protocol; `open_input` picks one
from what the folder holds (a registry, not an if-chain at the call site).

- EuRoC ASL folder (`mav0/cam0`, `mav0/imu0`, optional sensor.yaml files):
  images are read from disk one at a time. Without `imu0` (a camera-only cut)
  only the visual-only path (`--no-imu`) can run on it.
- Session folder (field output): `recording.mcap` or `recording_NNN.mcap`,
  with `calib/camchain.yaml` and `calib/imu.yaml`. Images come from
  `/cam0/image` (JPEG/PNG stills) or `/cam0/video` (H.264/H.265 packets,
  decoded with PyAV), the IMU from `/imu0`. Stamps are `header.stamp` (the
  sensor clock), as conventions.md asks.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from postproc.slam.types import ImuSamples
from shared.calibration.kalibr import CameraCalibration, ImuNoise, read_camchain, read_imu_yaml
from shared.errors import InputError
from shared.imu import ImuCleaning, clean_imu_rows

Image = npt.NDArray[np.uint8]
LOG = logging.getLogger(__name__)


@dataclass
class Frame:
    """One recorded image: camera-clock stamp (int64 ns), pixels (grey or BGR) and,
    when the image exists as a file, its encoded bytes (kept as recorded for keyframes)."""

    stamp_ns: int
    image: Image
    encoded_png: bytes | None = None


class SlamInput(Protocol):
    """A recording SLAM can run on."""

    @property
    def name(self) -> str:
        """What to call it in messages (the folder name)."""
        ...

    @property
    def calibration(self) -> CameraCalibration | None:
        """Camera model, `cam_from_imu` and time shift, when the input carries them."""
        ...

    @property
    def imu_noise(self) -> ImuNoise | None:
        """IMU noise densities, when the input carries them."""
        ...

    @property
    def calibration_is_guess(self) -> bool:
        """Whether the calibration it carries is a nominal guess (not measured)."""
        ...

    @property
    def imu(self) -> ImuSamples:
        """All IMU samples (IMU clock), strictly increasing."""
        ...

    @property
    def imu_cleaning(self) -> ImuCleaning:
        """What was merged, dropped or interpolated to make `imu` (shared.imu)."""
        ...

    @property
    def frame_count(self) -> int:
        """Number of images (for the progress bar)."""
        ...

    def frames(self) -> Iterator[Frame]:
        """Images in time order."""
        ...


class EurocInput:
    """An EuRoC ASL folder (the one holding `mav0`, or `mav0` itself)."""

    def __init__(self, folder: Path) -> None:
        from shared.formats.euroc import read_euroc

        self.folder = folder
        try:
            self._data = read_euroc(folder)
        except InputError as error:
            # read_euroc refuses an IMU file whose stamps repeat or go back, and rows
            # that are not numbers; a real recorder writes such rows. Read it row by row.
            if "imu0" not in str(error):
                raise
            self._data = _read_euroc_keeping_odd_imu_rows(folder)
        if len(self._data.imu_stamps_ns) < 2:
            raise InputError(f"{folder}: fewer than 2 IMU samples in mav0/imu0/data.csv")
        self._imu, self.imu_cleaning = clean_imu_rows(
            self._data.imu_stamps_ns,
            self._data.gyro_rad_s,
            self._data.accel_m_s2,
            name=f"{folder}: mav0/imu0/data.csv",
        )

    @property
    def name(self) -> str:
        return self.folder.name

    @property
    def calibration(self) -> CameraCalibration | None:
        return self._data.camera

    @property
    def imu_noise(self) -> ImuNoise | None:
        return self._data.imu_noise

    @property
    def calibration_is_guess(self) -> bool:
        return False

    @property
    def imu(self) -> ImuSamples:
        return self._imu

    @property
    def frame_count(self) -> int:
        return len(self._data.image_stamps_ns)

    def frames(self) -> Iterator[Frame]:
        for stamp, path in zip(self._data.image_stamps_ns, self._data.image_paths, strict=True):
            try:
                encoded = path.read_bytes()
            except OSError as error:
                raise InputError(f"{path}: cannot read image ({error})") from None
            image = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"{path}: not a readable image (expected PNG or JPEG)")
            png = encoded if path.suffix.lower() == ".png" else None
            yield Frame(int(stamp), image, png)


def _read_euroc_keeping_odd_imu_rows(folder: Path) -> Any:
    """An EurocDataset whose imu0 rows are taken in file order as they are (repeated or
    backward stamps left to `clean_imu_rows`); a row that is not 7 numbers is skipped
    with a warning naming its line. No ground truth (SLAM does not read it)."""
    # shared.formats.euroc has the cam0 and sensor.yaml readers; its read_euroc is strict.
    from shared.formats.euroc import (
        EurocDataset,
        _read_camera_csv,
        _read_camera_yaml,
        _read_imu_yaml,
    )

    mav = folder / "mav0" if (folder / "mav0").is_dir() else folder
    stamps, paths = _read_camera_csv(mav / "cam0" / "data.csv")
    body_from_imu, noise = np.eye(4), None
    if (mav / "imu0" / "sensor.yaml").is_file():
        body_from_imu, noise = _read_imu_yaml(mav / "imu0" / "sensor.yaml")
    camera = None
    if (mav / "cam0" / "sensor.yaml").is_file():
        camera = _read_camera_yaml(mav / "cam0" / "sensor.yaml", body_from_imu)
    csv_path = mav / "imu0" / "data.csv"
    try:
        lines = csv_path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as error:
        raise InputError(f"{csv_path}: cannot read ({error})") from None
    imu_stamps: list[int] = []
    rows: list[list[float]] = []
    skipped: list[int] = []
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        try:
            stamp = int(fields[0])
            values = [float(f) for f in fields[1:7]]
        except (ValueError, IndexError):
            skipped.append(number)
            continue
        if len(values) != 6 or not np.all(np.isfinite(values)):
            skipped.append(number)
            continue
        imu_stamps.append(stamp)
        rows.append(values)
    if skipped:
        LOG.warning(
            "%s: skipped %d rows that are not a stamp and 6 numbers (lines %s)",
            csv_path,
            len(skipped),
            ", ".join(str(n) for n in skipped[:5]) + (", ..." if len(skipped) > 5 else ""),
        )
    values_array = np.array(rows, dtype=np.float64).reshape(-1, 6)
    return EurocDataset(
        image_stamps_ns=stamps,
        image_paths=paths,
        imu_stamps_ns=np.array(imu_stamps, dtype=np.int64),
        gyro_rad_s=values_array[:, :3].copy(),
        accel_m_s2=values_array[:, 3:].copy(),
        groundtruth=None,
        camera=camera,
        imu_noise=noise,
    )


class EurocCameraInput(EurocInput):
    """An EuRoC folder with cam0 but no imu0 (a camera-only cut): for the visual-only path.

    Its IMU is empty; the stage refuses it for visual-inertial SLAM with a clear error.
    """

    def __init__(self, folder: Path) -> None:
        # shared.formats.euroc.read_euroc requires imu0; its cam0 readers do not.
        from shared.formats.euroc import (
            EurocDataset,
            _read_camera_csv,
            _read_camera_yaml,
        )

        self.folder = folder
        mav = folder / "mav0" if (folder / "mav0").is_dir() else folder
        stamps, paths = _read_camera_csv(mav / "cam0" / "data.csv")
        yaml_path = mav / "cam0" / "sensor.yaml"
        camera = _read_camera_yaml(yaml_path, np.eye(4)) if yaml_path.is_file() else None
        empty = np.zeros((0, 3))
        self._data = EurocDataset(
            image_stamps_ns=stamps,
            image_paths=paths,
            imu_stamps_ns=np.zeros(0, dtype=np.int64),
            gyro_rad_s=empty,
            accel_m_s2=empty,
            groundtruth=None,
            camera=camera,
            imu_noise=None,
        )
        self._imu = ImuSamples(np.zeros(0, dtype=np.int64), empty, empty)
        self.imu_cleaning = ImuCleaning()


class SessionInput:
    """A field session folder: MCAP recording(s) plus calib/."""

    IMAGE_TOPIC = "/cam0/image"
    VIDEO_TOPIC = "/cam0/video"
    IMU_TOPIC = "/imu0"

    def __init__(self, folder: Path) -> None:
        from shared.archive import ArchiveReader

        self.folder = folder
        self.recordings = sorted(folder.glob("recording*.mcap"))
        if not self.recordings:
            raise InputError(f"{folder}: no recording.mcap (expected a session folder)")
        stamps, gyro, accel = [], [], []
        self._image_topic: str | None = None
        self._count = 0
        for path in self.recordings:
            with ArchiveReader(path) as reader:
                topics = reader.topics()
                if self.IMU_TOPIC in topics:
                    series = reader.read_imu(self.IMU_TOPIC)
                    stamps.append(series.stamps_ns)
                    gyro.append(series.gyro_rad_s)
                    accel.append(series.accel_m_s2)
                for topic in (self.IMAGE_TOPIC, self.VIDEO_TOPIC):
                    if topic in topics:
                        self._image_topic = self._image_topic or topic
                        if topic == self._image_topic:
                            self._count += topics[topic].message_count
        if not stamps or sum(len(s) for s in stamps) < 2:
            raise InputError(f"{folder}: no IMU samples on {self.IMU_TOPIC} in the recording")
        if self._image_topic is None:
            raise InputError(
                f"{folder}: no images (expected {self.IMAGE_TOPIC} or {self.VIDEO_TOPIC})"
            )
        # Rotated recordings follow each other in time; duplicate or out-of-order rows
        # inside them are merged or dropped with a warning (shared.imu).
        try:
            self._imu, self.imu_cleaning = clean_imu_rows(
                np.concatenate(stamps),
                np.concatenate(gyro),
                np.concatenate(accel),
                name=f"{folder}: {self.IMU_TOPIC}",
            )
        except ValueError as error:
            raise InputError(str(error)) from None
        if len(self._imu) < 2:
            raise InputError(f"{folder}: fewer than 2 usable IMU samples on {self.IMU_TOPIC}")
        camchain = folder / "calib" / "camchain.yaml"
        imu_yaml = folder / "calib" / "imu.yaml"
        self._calibration = read_camchain(camchain)[0] if camchain.is_file() else None
        self._noise = read_imu_yaml(imu_yaml) if imu_yaml.is_file() else None
        self._guess = _calibration_is_guess(folder / "session.yaml")

    @property
    def name(self) -> str:
        return self.folder.name

    @property
    def calibration_is_guess(self) -> bool:
        return self._guess

    @property
    def calibration(self) -> CameraCalibration | None:
        return self._calibration

    @property
    def imu_noise(self) -> ImuNoise | None:
        return self._noise

    @property
    def imu(self) -> ImuSamples:
        return self._imu

    @property
    def frame_count(self) -> int:
        return self._count

    def frames(self) -> Iterator[Frame]:
        from shared.archive import ArchiveReader
        from shared.archive.messages import CompressedImage, CompressedVideo

        decoder = _VideoDecoder()
        topic = str(self._image_topic)  # set in __init__ (or it raised)
        for path in self.recordings:
            with ArchiveReader(path) as reader:
                for _, _, message in reader.messages(topics=[topic]):
                    if isinstance(message, CompressedImage):
                        image = cv2.imdecode(
                            np.frombuffer(message.data, np.uint8), cv2.IMREAD_UNCHANGED
                        )
                        if image is None:
                            raise InputError(
                                f"{path}: {self._image_topic} at {message.stamp_ns} ns: "
                                f"cannot decode a {message.format!r} image"
                            )
                        png = message.data if message.format.lower() == "png" else None
                        yield Frame(message.stamp_ns, image, png)
                    elif isinstance(message, CompressedVideo):
                        for image in decoder.decode(message.format, message.data):
                            yield Frame(message.stamp_ns, image)


class _VideoDecoder:
    """H.264/H.265 Annex B access units to BGR images (PyAV), one codec per stream."""

    def __init__(self) -> None:
        self._codec: Any = None

    def decode(self, fmt: str, data: bytes) -> Iterator[Image]:
        import av

        if self._codec is None:
            names = {"h264": "h264", "h265": "hevc", "hevc": "hevc"}
            if fmt.lower() not in names:
                raise InputError(f"unsupported video format {fmt!r} (expected h264 or h265)")
            self._codec = av.CodecContext.create(names[fmt.lower()], "r")
        for frame in self._codec.decode(av.Packet(data)):
            yield frame.to_ndarray(format="bgr24")


def _calibration_is_guess(session_yaml: Path) -> bool:
    """Whether session.yaml says the camchain is a guess (`calibration.camchain_source`
    starting with "guess", as the GoPro importer writes it). False when it cannot tell."""
    import yaml

    try:
        document = yaml.safe_load(session_yaml.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    calibration = document.get("calibration") if isinstance(document, dict) else None
    source = calibration.get("camchain_source") if isinstance(calibration, dict) else None
    return isinstance(source, str) and source.strip().lower().startswith("guess")


def _is_euroc(folder: Path) -> bool:
    mav = folder / "mav0" if (folder / "mav0").is_dir() else folder
    return (mav / "cam0").is_dir() and (mav / "imu0").is_dir()


def _is_euroc_camera_only(folder: Path) -> bool:
    mav = folder / "mav0" if (folder / "mav0").is_dir() else folder
    return (mav / "cam0" / "data.csv").is_file()


def _is_session(folder: Path) -> bool:
    return any(folder.glob("recording*.mcap"))


# Name -> (detector, reader); tried in order.
INPUT_KINDS: dict[str, tuple[Callable[[Path], bool], Callable[[Path], SlamInput]]] = {
    "euroc": (_is_euroc, EurocInput),
    "session": (_is_session, SessionInput),
    "euroc camera only": (_is_euroc_camera_only, EurocCameraInput),
}


def open_input(path: Path | str) -> SlamInput:
    """The reader for `path` (EuRoC folder or session folder); InputError otherwise."""
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder (expected an EuRoC or session folder)")
    for detect, reader in INPUT_KINDS.values():
        if detect(folder):
            return reader(folder)
    raise InputError(
        f"{folder}: neither an EuRoC folder (mav0/cam0, mav0/imu0) nor a session folder "
        "(recording.mcap)"
    )
