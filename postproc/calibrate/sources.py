"""Where calibration images and gyro samples come from (I/O).

Frame sources (`FRAME_SOURCES`, chosen by `source_kind`):

- "session": a session folder or `.mcap` archive; frames from a CompressedVideo topic
  (`/cam0/video`, decoded with `shared.archive.video`) or a CompressedImage topic
  (`/cam0/image`); stamps are `header.stamp` (camera clock, ns since epoch).
- "euroc": an EuRoC folder (`mav0/cam0`); stamps from `cam0/data.csv` (ns).
- "images": a folder of `.png`/`.jpg` files in name order; files named by integers of
  16 digits or more (ns since the epoch, as EuRoC names them) are stamped with them,
  otherwise images are one second apart from 0.
- "video": a video file (`.mp4`, `.mov`, ...) decoded with PyAV; stamps are the media
  time (ns from the first frame).

Gyro sources (`read_gyro`): a session folder / archive (an Imu topic) or an EuRoC folder.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np
import numpy.typing as npt

from shared.errors import InputError

GrayImage = npt.NDArray[np.uint8]
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".m4v")
NS_PER_S = 1_000_000_000


class FrameSource(Protocol):
    """Grey frames in time order: `frames()` yields (index, stamp_ns, image (H, W) uint8)."""

    path: Path
    topic: str

    def frames(self) -> Iterator[tuple[int, int, GrayImage]]: ...

    def frame_count(self) -> int | None: ...


def _read_gray(path: Path) -> GrayImage:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: cannot be read as an image (expected PNG or JPEG)")
    return np.asarray(image)


class ImageFolderSource:
    """Images of a folder in name order (see the module docstring for the stamps)."""

    def __init__(self, path: Path, topic: str = "/cam0/image_raw") -> None:
        self.path = path
        self.topic = topic
        self.files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise InputError(f"{path}: no images (expected {', '.join(IMAGE_SUFFIXES)} files)")
        stems = [p.stem for p in self.files]
        # EuRoC-style names are ns since the epoch (16+ digits); "000.png" is a counter.
        if all(s.isdigit() and len(s) >= 16 for s in stems) and len(set(stems)) == len(stems):
            self.stamps_ns = [int(s) for s in stems]
        else:
            self.stamps_ns = [i * NS_PER_S for i in range(len(self.files))]

    def frame_count(self) -> int | None:
        return len(self.files)

    def frames(self) -> Iterator[tuple[int, int, GrayImage]]:
        for index, (file, stamp) in enumerate(zip(self.files, self.stamps_ns, strict=True)):
            yield index, stamp, _read_gray(file)


class EurocSource:
    """cam0 of an EuRoC folder."""

    def __init__(self, path: Path, topic: str = "/cam0/image_raw") -> None:
        from shared.formats.euroc import read_euroc

        self.path = path
        self.topic = topic
        dataset = read_euroc(path)
        self.stamps_ns = [int(s) for s in dataset.image_stamps_ns]
        self.files = list(dataset.image_paths)

    def frame_count(self) -> int | None:
        return len(self.files)

    def frames(self) -> Iterator[tuple[int, int, GrayImage]]:
        for index, (file, stamp) in enumerate(zip(self.files, self.stamps_ns, strict=True)):
            yield index, stamp, _read_gray(file)


class SessionSource:
    """A camera topic of a session folder or archive: video packets or compressed stills."""

    def __init__(self, path: Path, topic: str = "/cam0/video") -> None:
        from shared.archive import ArchiveReader
        from shared.archive.video import session_archives

        self.path = path
        self.archives = session_archives(path)
        schemas: dict[str, str] = {}
        counts: dict[str, int] = {}
        for archive in self.archives:
            with ArchiveReader(archive) as reader:
                for name, info in reader.topics().items():
                    schemas[name] = info.schema_name
                    counts[name] = counts.get(name, 0) + info.message_count
        if topic not in schemas:
            # A camera asked for as video may have been recorded as stills, and back.
            swapped = (
                topic.replace("/video", "/image")
                if topic.endswith("/video")
                else topic.replace("/image", "/video")
            )
            if swapped not in schemas:
                names = ", ".join(sorted(schemas)) or "none"
                raise InputError(f"{path}: no camera topic {topic!r} (topics: {names})")
            topic = swapped
        self.topic = topic
        self.schema = schemas[topic]
        self.count = counts[topic]

    def frame_count(self) -> int | None:
        return self.count

    def frames(self) -> Iterator[tuple[int, int, GrayImage]]:
        if self.schema == "foxglove_msgs/msg/CompressedVideo":
            from shared.archive.video import SessionVideo

            with SessionVideo(self.path, topic=self.topic, grayscale=True) as video:
                for index, frame in enumerate(video.frames()):
                    yield index, frame.stamp_ns, frame.image
            return
        import cv2

        from shared.archive import ArchiveReader, CompressedImage

        index = 0
        for archive in self.archives:
            with ArchiveReader(archive) as reader:
                for _, _, message in reader.messages([self.topic]):
                    if not isinstance(message, CompressedImage):
                        raise InputError(
                            f"{archive}: topic {self.topic!r} holds {self.schema}, "
                            "not CompressedVideo or CompressedImage"
                        )
                    buffer = np.frombuffer(message.data, dtype=np.uint8)
                    image = cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE)
                    if image is None:
                        raise InputError(
                            f"{archive}: {self.topic} image at {message.stamp_ns} ns cannot be "
                            f"decoded (format {message.format!r})"
                        )
                    yield index, message.stamp_ns, np.asarray(image)
                    index += 1


class VideoFileSource:
    """A plain video file decoded with PyAV; stamps are media time from the first frame."""

    def __init__(self, path: Path, topic: str = "/cam0/image_raw") -> None:
        self.path = path
        self.topic = topic

    def frame_count(self) -> int | None:
        import av

        try:
            with av.open(str(self.path)) as container:
                return int(container.streams.video[0].frames) or None
        except (av.error.FFmpegError, IndexError):
            raise InputError(f"{self.path}: no video stream PyAV can open") from None

    def frames(self) -> Iterator[tuple[int, int, GrayImage]]:
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
            for index, frame in enumerate(container.decode(stream)):
                if frame.pts is None or frame.time_base is None:
                    raise InputError(f"{self.path}: frame {index} has no time stamp")
                stamp = round(frame.pts * frame.time_base * NS_PER_S)
                first = stamp if first is None else first
                yield index, int(stamp - first), frame.to_ndarray(format="gray")


FRAME_SOURCES: dict[
    str, type[ImageFolderSource | EurocSource | SessionSource | VideoFileSource]
] = {
    "session": SessionSource,
    "euroc": EurocSource,
    "images": ImageFolderSource,
    "video": VideoFileSource,
}


def source_kind(path: Path | str) -> str:
    """ "session", "euroc", "images" or "video" for `path`; InputError when none fits."""
    path = Path(path)
    if path.is_file():
        if path.suffix == ".mcap":
            return "session"
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return "video"
        raise InputError(
            f"{path}: not a recording (expected a session folder, an .mcap archive, an "
            f"EuRoC folder, a folder of images or a video file {', '.join(VIDEO_SUFFIXES)})"
        )
    if not path.is_dir():
        raise InputError(f"{path}: no such file or folder")
    if (path / "mav0").is_dir() or ((path / "cam0").is_dir() and (path / "imu0").is_dir()):
        return "euroc"
    if any(path.glob("*.mcap")):
        return "session"
    if any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
        return "images"
    raise InputError(
        f"{path}: no recording found (expected recording*.mcap, mav0/ of EuRoC, or images)"
    )


def open_frames(path: Path | str, *, topic: str | None = None) -> FrameSource:
    """The frame source for `path`; `topic` picks the camera of a session (default cam0)."""
    path = Path(path)
    kind = source_kind(path)
    source_class = FRAME_SOURCES[kind]
    if topic is None:
        return source_class(path)
    return source_class(path, topic)


def read_gyro(
    path: Path | str, *, topic: str = "/imu0"
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """(stamps_ns (N,) int64 sensor clock, gyro (N,3) rad/s) of a session or EuRoC folder."""
    path = Path(path)
    kind = source_kind(path)
    if kind == "euroc":
        from shared.formats.euroc import read_euroc

        dataset = read_euroc(path)
        return dataset.imu_stamps_ns.astype(np.int64), dataset.gyro_rad_s.astype(np.float64)
    if kind != "session":
        raise InputError(
            f"{path}: holds no IMU samples (expected a session folder, an .mcap archive or "
            "an EuRoC folder)"
        )
    from shared.archive import ArchiveReader
    from shared.archive.video import session_archives

    stamps: list[npt.NDArray[np.int64]] = []
    rates: list[npt.NDArray[np.float64]] = []
    for archive in session_archives(path):
        with ArchiveReader(archive) as reader:
            series = reader.read_imu(topic)
        stamps.append(series.stamps_ns)
        rates.append(series.gyro_rad_s)
    all_stamps = np.concatenate(stamps).astype(np.int64)
    all_rates = np.concatenate(rates).astype(np.float64)
    if len(all_stamps) < 2:
        raise InputError(f"{path}: topic {topic!r} has {len(all_stamps)} IMU sample(s)")
    order = np.argsort(all_stamps, kind="stable")
    return all_stamps[order], all_rates[order]
