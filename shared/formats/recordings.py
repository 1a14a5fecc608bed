"""One reader for every kind of recording the post-processor takes (I/O).

    recording = open_recording("dives/d1/session")     # picks the kind from the path
    for frame in recording.frames(grayscale=True):     # images in time order
        frame.index, frame.stamp_ns, frame.image
    if recording.has_imu:
        imu, cleaning = recording.imu()                # one strictly increasing stream

SLAM, calibration and SfM ask `open_recording` for a recording; `RECORDING_KINDS`
maps each kind's name to its detector and reader, tried in this order:

- "euroc": an EuRoC ASL folder (the one holding `mav0/`, or `mav0` itself), read
  as a real recorder writes it (`shared.formats.euroc.read_euroc(as_recorded=True)`):
  cam0 stamps from `cam0/data.csv` (ns, irregular gaps kept), the IMU from
  `imu0/data.csv`, camera model and IMU noise from the sensor.yaml files.
  Either of cam0 and imu0 may be missing (a camera-only cut, an IMU-only set).
- "session": a field session folder (`recording.mcap` or `recording_NNN.mcap`,
  `calib/camchain.yaml`, `calib/imu.yaml`, `session.yaml`) or one `.mcap` archive
  (calib/ is then looked for beside it). Frames from a CompressedImage topic
  (`/cam0/image`) or a CompressedVideo topic (`/cam0/video`, decoded by
  `shared.archive.video.SessionVideo`); the IMU from an Imu topic (`/imu0`).
  Stamps are `header.stamp`, the sensor clock (docs/conventions.md).
- "images": a folder of images in name order; files named by integers of 16 digits
  or more (ns since the epoch, as EuRoC names them) are stamped with them, otherwise
  the images are one second apart from 0. No IMU.
- "video": a video file decoded with PyAV; stamps are the media time (ns from the
  first frame). No IMU.

IMU rows of every kind go through `shared.imu.clean_imu_rows`: repeated stamps are
merged, rows out of order dropped, gyro and accelerometer rows of separate sensors
merged into one stream, each with one warning naming the file.

Images are uint8 arrays as decoded (grey (H, W) or BGR (H, W, 3)), or the grey
(H, W) luma with `grayscale=True`. `frames(min_step_ns=...)` thins them by time (the
first image, then each one at least that long after the last one given), or
`frames(keep=...)` by any test of the stamps (`Keep`): image files and stills are then
not even read or decoded, a video decodes every frame (each
depends on the ones before) but converts only those it gives. A path that is no
recording raises one InputError naming the path and the kinds expected.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from shared.calibration.kalibr import CameraCalibration, ImuNoise
from shared.clock import NS_PER_S
from shared.errors import InputError
from shared.folders import SessionFolder
from shared.imu import ImuCleaning, ImuSamples, clean_imu_rows

Image = npt.NDArray[np.uint8]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".m4v")
#: The camera topic named for a recording that has no topics (EuRoC, Kalibr's name).
DEFAULT_CAMERA_TOPIC = "/cam0/image_raw"
#: Session camera topics tried when none is asked for, in this order.
SESSION_CAMERA_TOPICS = ("/cam0/image", "/cam0/video")
DEFAULT_IMU_TOPIC = "/imu0"
_VIDEO_SCHEMA = "foxglove_msgs/msg/CompressedVideo"
_IMU_SCHEMA = "sensor_msgs/msg/Imu"


class PlanarYuv:
    """A decoded 8-bit 4:2:0 video frame kept as its planes (1.5 bytes a pixel, against 3
    for BGR): the grey image costs nothing and BGR is made only when asked for.

    H.264 and H.265 video decode to 4:2:0 planes; converting every frame to BGR took
    1.2 ms at 960x540 (PyAV, one core) and making grey of that BGR 0.5 ms more, while
    SLAM wants grey of every frame and colour of its keyframes only (one in 15).
    `bgr` converts as PyAV converts the decoded frame itself (the same matrix and range:
    equal pixel for pixel); `luma` is the luma plane, in full range (0-255) as a grey
    image file holds it (limited-range video, 16-235, is stretched: equal to PyAV's
    "gray" conversion of such a frame).
    """

    __slots__ = ("_color_range", "_colorspace", "_format", "_height", "_planes")

    FORMATS = ("yuv420p", "yuvj420p")
    """The pixel formats kept as planes (others are converted to BGR at once)."""

    def __init__(
        self, planes: Image, pixel_format: str, *, colorspace: int = 0, color_range: int = 0
    ) -> None:
        if pixel_format not in self.FORMATS:
            raise ValueError(f"pixel format {pixel_format!r}: expected one of {self.FORMATS}")
        if planes.ndim != 2 or planes.shape[0] % 3 or planes.shape[1] % 2:
            raise ValueError(f"planes of shape {planes.shape}: expected (3 H / 2, W), W even")
        self._planes = planes
        self._format = pixel_format
        self._colorspace = colorspace
        self._color_range = color_range
        self._height = planes.shape[0] * 2 // 3

    @classmethod
    def of(cls, frame: Any) -> PlanarYuv | None:
        """The planes of a PyAV VideoFrame, or None when it is not 8-bit 4:2:0 with an
        even width and height."""
        name = frame.format.name
        if name not in cls.FORMATS or frame.width % 2 or frame.height % 2:
            return None
        return cls(
            np.ascontiguousarray(frame.to_ndarray(format=name), dtype=np.uint8),
            name,
            colorspace=int(frame.colorspace),
            color_range=int(frame.color_range),
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image."""
        return self._height, self._planes.shape[1]

    def luma(self) -> Image:
        """The grey (H, W) image: the luma plane, full range."""
        luma = self._planes[: self._height]
        if self._format == "yuv420p" and self._color_range != _JPEG_RANGE:
            import cv2

            return np.asarray(cv2.LUT(luma, _LIMITED_TO_FULL), dtype=np.uint8)
        return luma

    def bgr(self) -> Image:
        """The BGR (H, W, 3) image, converted by PyAV."""
        import av

        frame = av.VideoFrame.from_ndarray(self._planes, format=self._format)
        frame.colorspace = self._colorspace
        frame.color_range = self._color_range
        return np.ascontiguousarray(frame.to_ndarray(format="bgr24"), dtype=np.uint8)


_JPEG_RANGE = 2
"""FFmpeg's AVCOL_RANGE_JPEG: full-range (0-255) samples."""
_LIMITED_TO_FULL = np.clip(np.round((np.arange(256) - 16) * 255 / 219), 0, 255).astype(np.uint8)
"""Limited-range luma (16-235) to full range, as FFmpeg's swscale makes grey of it."""


class Frame:
    """One recorded image.

    index: its position in the recording (from 0). stamp_ns: camera clock, int64 ns.
    image: uint8 pixels (see the module docstring); a video frame kept as `PlanarYuv`
    makes them (BGR) on first use only. luma: that frame's grey image, free (None for
    other frames: make grey of `image`). encoded_png: the PNG bytes as recorded when the
    image is stored as a PNG (kept byte for byte for keyframes).
    """

    __slots__ = ("_image", "_planes", "encoded_png", "index", "stamp_ns")

    def __init__(
        self,
        index: int,
        stamp_ns: int,
        image: Image | PlanarYuv,
        encoded_png: bytes | None = None,
    ) -> None:
        self.index = index
        self.stamp_ns = stamp_ns
        self.encoded_png = encoded_png
        self._planes = image if isinstance(image, PlanarYuv) else None
        self._image = None if isinstance(image, PlanarYuv) else image

    @property
    def image(self) -> Image:
        """The pixels: grey (H, W) or BGR (H, W, 3), uint8."""
        if self._image is None:
            assert self._planes is not None
            self._image = self._planes.bgr()
        return self._image

    @property
    def luma(self) -> Image | None:
        """The grey (H, W) image of a frame kept as `PlanarYuv` (None for others)."""
        return None if self._planes is None else self._planes.luma()

    def __repr__(self) -> str:
        shape = self._planes.shape if self._planes is not None else self.image.shape
        return f"Frame(index={self.index}, stamp_ns={self.stamp_ns}, shape={shape})"


@dataclass(frozen=True, kw_only=True)
class RecordingRequest:
    """What a caller asks of a recording (see `open_recording`)."""

    camera_topic: str | None = None
    imu_topic: str = DEFAULT_IMU_TOPIC
    need_camera: bool = True


ANY_CAMERA = RecordingRequest()


class Recording(Protocol):
    """A recording of one camera and, where the kind has one, its IMU."""

    kind: str
    """The `RECORDING_KINDS` name."""
    path: Path
    """What was opened."""
    camera_topic: str
    """Where the frames come from (a session's topic, else `DEFAULT_CAMERA_TOPIC`)."""

    @property
    def name(self) -> str:
        """What to call it in messages (the folder or file name)."""
        ...

    @property
    def frame_count(self) -> int | None:
        """Number of images (None when the container does not say)."""
        ...

    @property
    def calibration(self) -> CameraCalibration | None:
        """Camera model, `cam_from_imu` and time shift, when the recording carries them."""
        ...

    @property
    def imu_noise(self) -> ImuNoise | None:
        """IMU noise densities, when the recording carries them."""
        ...

    @property
    def calibration_is_guess(self) -> bool:
        """Whether the calibration it carries is a nominal guess (not measured)."""
        ...

    @property
    def has_imu(self) -> bool:
        """Whether it holds IMU rows at all."""
        ...

    def frames(
        self, *, grayscale: bool = False, min_step_ns: int = 0, keep: Keep | None = None
    ) -> Iterator[Frame]:
        """The images in time order, none closer than `min_step_ns` to the last one given
        (0: every image); or, with `keep`, those whose stamps it passes (asked once per
        image, in order). Images left out are not decoded where the kind allows."""
        ...

    def imu(self) -> tuple[ImuSamples, ImuCleaning]:
        """All IMU samples (IMU clock), cleaned; InputError when there are fewer than 2."""
        ...


def _decode(data: bytes, where: str, *, grayscale: bool) -> Image:
    import cv2

    flags = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_UNCHANGED
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise InputError(f"{where}: cannot be read as an image (expected PNG or JPEG)")
    return np.asarray(image)


Keep = Callable[[int], bool]
"""A test of each image's stamp (ns), asked once per image in time order: use it?"""


def spaced_by(min_step_ns: int) -> Keep:
    """A test for increasing stamps (ns): true for the first, then for each one at least
    `min_step_ns` after the last one it passed (0: for every stamp)."""
    last: int | None = None

    def keep(stamp_ns: int) -> bool:
        nonlocal last
        if min_step_ns > 0 and last is not None and stamp_ns - last < min_step_ns:
            return False
        last = stamp_ns
        return True

    return keep


def _image_files(
    paths: list[Path], stamps_ns: list[int], grayscale: bool, keep: Keep
) -> Iterator[Frame]:
    for index, (path, stamp) in enumerate(zip(paths, stamps_ns, strict=True)):
        if not keep(int(stamp)):
            continue
        try:
            encoded = path.read_bytes()
        except OSError as error:
            raise InputError(f"{path}: cannot read image ({error})") from None
        png = encoded if path.suffix.lower() == ".png" else None
        yield Frame(index, int(stamp), _decode(encoded, str(path), grayscale=grayscale), png)


def _clean(
    stamps_ns: npt.NDArray[np.int64],
    gyro_rad_s: npt.NDArray[np.float64],
    accel_m_s2: npt.NDArray[np.float64],
    where: str,
) -> tuple[ImuSamples, ImuCleaning]:
    try:
        imu, cleaning = clean_imu_rows(stamps_ns, gyro_rad_s, accel_m_s2, name=where)
    except ValueError as error:
        raise InputError(str(error)) from None
    if len(imu) < 2:
        raise InputError(f"{where}: fewer than 2 IMU samples ({len(imu)} usable)")
    return imu, cleaning


class EurocRecording:
    """An EuRoC ASL folder (see the module docstring)."""

    kind = "euroc"

    def __init__(self, path: Path, request: RecordingRequest = ANY_CAMERA) -> None:
        from shared.formats.euroc import read_euroc

        self.path = path
        self.camera_topic = request.camera_topic or DEFAULT_CAMERA_TOPIC
        self._data = read_euroc(path, as_recorded=True, groundtruth=False)
        self._mav = path / "mav0" if (path / "mav0").is_dir() else path
        if request.need_camera and not (self._mav / "cam0" / "data.csv").is_file():
            raise InputError(f"{path}: no images (expected mav0/cam0/data.csv)")

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def frame_count(self) -> int | None:
        return len(self._data.image_paths)

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
    def has_imu(self) -> bool:
        return (self._mav / "imu0" / "data.csv").is_file()

    def frames(
        self, *, grayscale: bool = False, min_step_ns: int = 0, keep: Keep | None = None
    ) -> Iterator[Frame]:
        stamps = self._data.image_stamps_ns.tolist()
        chosen = keep or spaced_by(min_step_ns)
        yield from _image_files(self._data.image_paths, stamps, grayscale, chosen)

    def imu(self) -> tuple[ImuSamples, ImuCleaning]:
        where = f"{self.path}: mav0/imu0/data.csv"
        if not self.has_imu:
            raise InputError(f"{where}: missing (expected the IMU rows of the recording)")
        data = self._data
        return _clean(data.imu_stamps_ns, data.gyro_rad_s, data.accel_m_s2, where)


class SessionRecording:
    """A session folder or one `.mcap` archive (see the module docstring)."""

    kind = "session"

    def __init__(self, path: Path, request: RecordingRequest = ANY_CAMERA) -> None:
        from shared.archive import ArchiveReader
        from shared.archive.video import session_archives

        self.path = path
        self.folder = path if path.is_dir() else path.parent
        self._session = SessionFolder(self.folder)
        self.archives = session_archives(path)
        self.imu_topic = request.imu_topic
        self._schemas: dict[str, str] = {}
        self._counts: dict[str, int] = {}
        for archive in self.archives:
            with ArchiveReader(archive) as reader:
                for topic, info in reader.topics().items():
                    self._schemas[topic] = info.schema_name
                    self._counts[topic] = self._counts.get(topic, 0) + info.message_count
        self._asked_topic = request.camera_topic
        self.camera_topic = self._camera_topic(request.camera_topic)
        if request.need_camera and self.camera_topic not in self._schemas:
            raise self._no_camera()

    def _no_camera(self) -> InputError:
        names = ", ".join(sorted(self._schemas)) or "none"
        asked = [self._asked_topic] if self._asked_topic else SESSION_CAMERA_TOPICS
        wanted = " or ".join(repr(t) for t in asked)
        return InputError(f"{self.path}: no camera topic {wanted} (topics: {names})")

    def _camera_topic(self, asked: str | None) -> str:
        if asked is None:
            found = [t for t in SESSION_CAMERA_TOPICS if t in self._schemas]
            return found[0] if found else SESSION_CAMERA_TOPICS[0]
        if asked in self._schemas:
            return asked
        # A camera asked for as video may have been recorded as stills, and back.
        if asked.endswith("/video"):
            swapped = asked.removesuffix("/video") + "/image"
        elif asked.endswith("/image"):
            swapped = asked.removesuffix("/image") + "/video"
        else:
            return asked
        return swapped if swapped in self._schemas else asked

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def frame_count(self) -> int | None:
        return self._counts.get(self.camera_topic, 0)

    @cached_property
    def calibration(self) -> CameraCalibration | None:
        session = self._session
        return session.read_camchain()[0] if session.camchain.is_file() else None

    @cached_property
    def imu_noise(self) -> ImuNoise | None:
        session = self._session
        return session.read_imu_noise() if session.imu_yaml.is_file() else None

    @cached_property
    def calibration_is_guess(self) -> bool:
        """Whether session.yaml says the camchain is a guess (`calibration.camchain_source`
        starting with "guess", as the GoPro importer writes it). False when it cannot tell."""
        import yaml

        try:
            text = self._session.session_yaml.read_text(encoding="utf-8")
            document = yaml.safe_load(text)
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            return False
        calibration = document.get("calibration") if isinstance(document, dict) else None
        source = calibration.get("camchain_source") if isinstance(calibration, dict) else None
        return isinstance(source, str) and source.strip().lower().startswith("guess")

    @property
    def has_imu(self) -> bool:
        return self._schemas.get(self.imu_topic) == _IMU_SCHEMA

    def frames(
        self, *, grayscale: bool = False, min_step_ns: int = 0, keep: Keep | None = None
    ) -> Iterator[Frame]:
        if self.camera_topic not in self._schemas:
            raise self._no_camera()
        if self._schemas[self.camera_topic] == _VIDEO_SCHEMA:
            from shared.archive.video import SessionVideo

            chosen = keep or spaced_by(min_step_ns)
            index = -1  # of the last frame `counted` was asked about: the one given next

            def counted(stamp_ns: int) -> bool:
                nonlocal index
                index += 1
                return chosen(stamp_ns)

            with SessionVideo(self.path, topic=self.camera_topic, grayscale=grayscale) as video:
                if grayscale:
                    for frame in video.frames(keep=counted):
                        yield Frame(index, frame.stamp_ns, frame.image)
                else:
                    for stamp, _, decoded in video.decoded(keep=counted):
                        yield Frame(index, stamp, _colour(decoded))
            return
        yield from self._stills(grayscale, keep or spaced_by(min_step_ns))

    def _stills(self, grayscale: bool, keep: Keep) -> Iterator[Frame]:
        from shared.archive import ArchiveReader, CompressedImage

        index = -1
        for archive in self.archives:
            with ArchiveReader(archive) as reader:
                for _, _, message in reader.messages([self.camera_topic]):
                    if not isinstance(message, CompressedImage):
                        raise InputError(
                            f"{archive}: topic {self.camera_topic!r} holds "
                            f"{self._schemas[self.camera_topic]}, not CompressedVideo or "
                            "CompressedImage"
                        )
                    index += 1
                    if not keep(message.stamp_ns):
                        continue
                    where = (
                        f"{archive}: {self.camera_topic} at {message.stamp_ns} ns "
                        f"({message.format!r} image)"
                    )
                    image = _decode(message.data, where, grayscale=grayscale)
                    png = message.data if message.format.lower() == "png" else None
                    yield Frame(index, message.stamp_ns, image, png)

    def imu(self) -> tuple[ImuSamples, ImuCleaning]:
        from shared.archive import ArchiveReader

        where = f"{self.path}: {self.imu_topic}"
        if not self.has_imu:
            names = ", ".join(sorted(self._schemas)) or "none"
            raise InputError(f"{where}: no IMU topic (topics: {names})")
        stamps, gyro, accel = [], [], []
        for archive in self.archives:
            with ArchiveReader(archive) as reader:
                if self.imu_topic not in reader.topics():
                    continue
                series = reader.read_imu(self.imu_topic)
            stamps.append(series.stamps_ns)
            gyro.append(series.gyro_rad_s)
            accel.append(series.accel_m_s2)
        # Rotated recordings follow each other in time: one stream, cleaned as a whole.
        return _clean(np.concatenate(stamps), np.concatenate(gyro), np.concatenate(accel), where)


class _NoImu:
    """For the kinds that hold images only (and no topics: `DEFAULT_CAMERA_TOPIC`)."""

    def __init__(self, path: Path, request: RecordingRequest = ANY_CAMERA) -> None:
        self.path = path
        self.camera_topic = request.camera_topic or DEFAULT_CAMERA_TOPIC

    @property
    def has_imu(self) -> bool:
        return False

    def imu(self) -> tuple[ImuSamples, ImuCleaning]:
        raise InputError(
            f"{self.path}: holds no IMU samples (expected a session folder, an .mcap archive "
            "or an EuRoC folder with mav0/imu0)"
        )

    @property
    def calibration(self) -> CameraCalibration | None:
        return None

    @property
    def imu_noise(self) -> ImuNoise | None:
        return None

    @property
    def calibration_is_guess(self) -> bool:
        return False

    @property
    def name(self) -> str:
        return self.path.name


class ImageFolderRecording(_NoImu):
    """A folder of images in name order (see the module docstring for the stamps)."""

    kind = "images"

    def __init__(self, path: Path, request: RecordingRequest = ANY_CAMERA) -> None:
        super().__init__(path, request)
        self.files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise InputError(f"{path}: no images (expected {', '.join(IMAGE_SUFFIXES)} files)")
        stems = [p.stem for p in self.files]
        # EuRoC-style names are ns since the epoch (16+ digits); "000.png" is a counter.
        if all(s.isdigit() and len(s) >= 16 for s in stems) and len(set(stems)) == len(stems):
            self.stamps_ns = [int(s) for s in stems]
        else:
            self.stamps_ns = [i * NS_PER_S for i in range(len(self.files))]

    @property
    def frame_count(self) -> int | None:
        return len(self.files)

    def frames(
        self, *, grayscale: bool = False, min_step_ns: int = 0, keep: Keep | None = None
    ) -> Iterator[Frame]:
        yield from _image_files(
            self.files, self.stamps_ns, grayscale, keep or spaced_by(min_step_ns)
        )


class VideoFileRecording(_NoImu):
    """A plain video file decoded with PyAV; stamps are media time from the first frame."""

    kind = "video"

    @cached_property
    def frame_count(self) -> int | None:
        import av

        try:
            with av.open(str(self.path)) as container:
                return int(container.streams.video[0].frames) or None
        except (av.error.FFmpegError, IndexError):
            raise InputError(f"{self.path}: no video stream PyAV can open") from None

    def frames(
        self, *, grayscale: bool = False, min_step_ns: int = 0, keep: Keep | None = None
    ) -> Iterator[Frame]:
        import av

        try:
            container = av.open(str(self.path))
        except av.error.FFmpegError as error:
            raise InputError(f"{self.path}: cannot open as a video ({error})") from None
        with container:
            if not container.streams.video:
                raise InputError(f"{self.path}: no video stream")
            stream = container.streams.video[0]
            first: int | None = None
            chosen = keep or spaced_by(min_step_ns)
            for index, frame in enumerate(container.decode(stream)):
                if frame.pts is None or frame.time_base is None:
                    raise InputError(f"{self.path}: frame {index} has no time stamp")
                stamp = round(frame.pts * frame.time_base * NS_PER_S)
                first = stamp if first is None else first
                if not chosen(int(stamp - first)):
                    continue
                image = (
                    np.asarray(frame.to_ndarray(format="gray"), dtype=np.uint8)
                    if grayscale
                    else _colour(frame)
                )
                yield Frame(index, int(stamp - first), image)


def _colour(frame: Any) -> Image | PlanarYuv:
    """A decoded PyAV frame as its planes (`PlanarYuv`: BGR when first asked for), or as
    BGR at once when it is not 8-bit 4:2:0."""
    planes = PlanarYuv.of(frame)
    if planes is not None:
        return planes
    return np.ascontiguousarray(frame.to_ndarray(format="bgr24"), dtype=np.uint8)


def _is_euroc(path: Path) -> bool:
    mav = path / "mav0" if (path / "mav0").is_dir() else path
    return path.is_dir() and (
        (path / "mav0").is_dir()
        or (mav / "cam0" / "data.csv").is_file()
        or ((mav / "cam0").is_dir() and (mav / "imu0").is_dir())
    )


def _is_session(path: Path) -> bool:
    if path.is_file():
        return path.suffix == ".mcap"
    return path.is_dir() and any(path.glob("*.mcap"))


def _is_image_folder(path: Path) -> bool:
    return path.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())


def _is_video_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


class RecordingKind(NamedTuple):
    """One entry of `RECORDING_KINDS`: whether a path is of the kind, and its reader."""

    detect: Callable[[Path], bool]
    reader: Callable[[Path, RecordingRequest], Recording]
    expected: str
    """What the kind looks like, for the error message."""


RECORDING_KINDS: dict[str, RecordingKind] = {
    "euroc": RecordingKind(_is_euroc, EurocRecording, "an EuRoC folder (mav0/cam0, mav0/imu0)"),
    "session": RecordingKind(
        _is_session, SessionRecording, "a session folder or .mcap archive (recording*.mcap)"
    ),
    "images": RecordingKind(
        _is_image_folder, ImageFolderRecording, "a folder of images (.png, .jpg, ...)"
    ),
    "video": RecordingKind(
        _is_video_file, VideoFileRecording, f"a video file ({', '.join(VIDEO_SUFFIXES)})"
    ),
}


def _expected() -> str:
    kinds = [kind.expected for kind in RECORDING_KINDS.values()]
    return ", ".join(kinds[:-1]) + " or " + kinds[-1]


def recording_kind(path: Path | str) -> str:
    """The `RECORDING_KINDS` name of `path`; InputError naming the kinds when none fits."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder (expected {_expected()})")
    for name, kind in RECORDING_KINDS.items():
        if kind.detect(path):
            return name
    raise InputError(f"{path}: not a recording (expected {_expected()})")


def open_recording(
    path: Path | str,
    *,
    camera_topic: str | None = None,
    imu_topic: str = DEFAULT_IMU_TOPIC,
    need_camera: bool = True,
) -> Recording:
    """The recording at `path`, of the first kind in `RECORDING_KINDS` that fits.

    camera_topic: a session's camera topic (default: `/cam0/image`, else `/cam0/video`;
    one asked for as video that was recorded as stills is found, and back). imu_topic:
    a session's IMU topic. need_camera: refuse a recording without images (off to read
    only the IMU).
    """
    path = Path(path)
    kind = RECORDING_KINDS[recording_kind(path)]
    request = RecordingRequest(
        camera_topic=camera_topic, imu_topic=imu_topic, need_camera=need_camera
    )
    return kind.reader(path, request)
