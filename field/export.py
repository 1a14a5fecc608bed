"""Export a session folder for other tools: EuRoC, ROS 1 bag, ROS 2 bag.

    export_session(ExportOptions(format="euroc"), Path("sessions/dive1"), Path("dive1_euroc"))

- `euroc`: an EuRoC ASL folder (`mav0/cam0` PNG images named by their stamp,
  `mav0/imu0/data.csv`, sensor.yaml files) via `shared.formats.euroc`; images
  decoded from the video (grey by default), optionally downscaled (the
  intrinsics are scaled to match). Intrinsics and `T_BS` come from the
  session's `calib/camchain.yaml`, the IMU noise from `calib/imu.yaml`.
- `rosbag1`: a ROS 1 bag (`rosbags.rosbag1`) with `sensor_msgs/Image`
  (mono8/bgr8) or, with `compressed`, `sensor_msgs/CompressedImage` (JPEG)
  on `<video topic>/image_raw[/compressed]`, and `sensor_msgs/Imu` on the
  IMU topic; bag time = header.stamp.
- `rosbag2`: the session is already a rosbag2 bag (MCAP + metadata.yaml):
  the MCAP files and metadata.yaml are hard-linked (copied across file
  systems) into the output folder.

Stamps stay the session's (`header.stamp`, ns since epoch, camera clock).
Every export writes to a temporary name and renames it when complete;
an existing output is refused unless `overwrite`.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from shared.archive import ArchiveReader
from shared.archive.video import SessionVideo, session_archives
from shared.clock import NS_PER_S
from shared.errors import InputError, OutputExistsError
from shared.folders import SessionFolder
from shared.fsutil import atomic_path
from shared.progress import progress

ExportFormat = Literal["euroc", "rosbag1", "rosbag2"]


@dataclass(kw_only=True)
class ExportOptions:
    """What to export.

    format: "euroc", "rosbag1" or "rosbag2".
    video_topic / imu_topic: the session topics to export.
    grayscale: images as mono8 (default, what VIO tools want) or BGR.
    scale: image resize factor (area averaging); intrinsics scaled to match.
    compressed: rosbag1 only: JPEG CompressedImage instead of raw Image.
    jpeg_quality: 1-100, for `compressed`.
    """

    format: ExportFormat
    video_topic: str = "/cam0/video"
    imu_topic: str = "/imu0"
    grayscale: bool = True
    scale: float = 1.0
    compressed: bool = False
    jpeg_quality: int = 95


def _check_session(session_dir: Path) -> None:
    if not session_dir.is_dir():
        raise InputError(f"{session_dir}: not a session folder (no such folder)")
    session_archives(session_dir)


def _read_imu(session_dir: Path, topic: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(stamps_ns, gyro, accel) of the IMU topic across the session's archives; None if absent."""
    parts = []
    for path in session_archives(session_dir):
        with ArchiveReader(path) as reader:
            if topic not in reader.topics():
                continue
            parts.append(reader.read_imu(topic))
    if not parts:
        return None
    return (
        np.concatenate([p.stamps_ns for p in parts]),
        np.concatenate([p.gyro_rad_s for p in parts]),
        np.concatenate([p.accel_m_s2 for p in parts]),
    )


def export_euroc(options: ExportOptions, session_dir: Path, out: Path, *, overwrite: bool) -> Path:
    """The session as an EuRoC folder at `out` (see the module docstring)."""
    from shared.formats.euroc import EurocWriter

    folder = SessionFolder(session_dir)
    camchain = folder.camchain
    if not camchain.is_file():
        raise InputError(
            f"{session_dir}: no {folder.relative(camchain)} (EuRoC needs the intrinsics)"
        )
    calibration = folder.read_camchain()[0]
    if options.scale != 1.0:
        calibration.camera = calibration.camera.scaled(options.scale)
    noise = folder.read_imu_noise() if folder.imu_yaml.is_file() else None
    imu = _read_imu(session_dir, options.imu_topic)
    with (
        SessionVideo(
            session_dir,
            topic=options.video_topic,
            scale=options.scale,
            grayscale=options.grayscale,
        ) as video,
        EurocWriter(out, camera=calibration, imu_noise=noise, overwrite=overwrite) as writer,
    ):
        for frame in progress(video.frames(), total=video.frame_count, desc="euroc", unit="frame"):
            writer.add_image(frame.stamp_ns, frame.image)
        if imu is not None:
            writer.add_imu(*imu)
    return out


def export_rosbag1(
    options: ExportOptions, session_dir: Path, out: Path, *, overwrite: bool
) -> Path:
    """The session as a ROS 1 bag file at `out` (see the module docstring)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    if not 1 <= options.jpeg_quality <= 100:
        raise InputError(f"jpeg_quality {options.jpeg_quality}: expected 1..100")
    typestore = get_typestore(Stores.ROS1_NOETIC)
    types = typestore.types
    Header = types["std_msgs/msg/Header"]
    Time = types["builtin_interfaces/msg/Time"]
    Vector3 = types["geometry_msgs/msg/Vector3"]
    Quaternion = types["geometry_msgs/msg/Quaternion"]
    image_topic = options.video_topic.rsplit("/", 1)[0] + "/image_raw"
    imu = _read_imu(session_dir, options.imu_topic)

    def header(stamp_ns: int, seq: int, frame_id: str) -> Any:
        return Header(
            seq=seq,
            stamp=Time(sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S),
            frame_id=frame_id,
        )

    with atomic_path(out, overwrite=overwrite) as tmp:
        writer = Writer(tmp)
        writer.open()
        try:
            if options.compressed:
                image_type = "sensor_msgs/msg/CompressedImage"
                image_conn = writer.add_connection(
                    image_topic + "/compressed", image_type, typestore=typestore
                )
            else:
                image_type = "sensor_msgs/msg/Image"
                image_conn = writer.add_connection(image_topic, image_type, typestore=typestore)
            imu_conn = (
                writer.add_connection(options.imu_topic, "sensor_msgs/msg/Imu", typestore=typestore)
                if imu is not None
                else None
            )
            frame_id = options.video_topic.strip("/").split("/")[0]
            # Merge images and IMU in time order (a bag is read in time order anyway;
            # writing in order keeps its chunks small in time).
            imu_pos = 0
            imu_count = 0 if imu is None else int(imu[0].shape[0])
            zero9 = np.zeros(9)
            orientation_cov = np.zeros(9)
            orientation_cov[0] = -1.0

            def write_imu_until(limit_ns: int | None) -> None:
                nonlocal imu_pos
                if imu is None or imu_conn is None:
                    return
                stamps, gyro, accel = imu
                while imu_pos < imu_count and (limit_ns is None or stamps[imu_pos] <= limit_ns):
                    stamp = int(stamps[imu_pos])
                    message = types["sensor_msgs/msg/Imu"](
                        header=header(stamp, imu_pos, options.imu_topic.strip("/")),
                        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                        orientation_covariance=orientation_cov,
                        angular_velocity=Vector3(
                            x=float(gyro[imu_pos, 0]),
                            y=float(gyro[imu_pos, 1]),
                            z=float(gyro[imu_pos, 2]),
                        ),
                        angular_velocity_covariance=zero9,
                        linear_acceleration=Vector3(
                            x=float(accel[imu_pos, 0]),
                            y=float(accel[imu_pos, 1]),
                            z=float(accel[imu_pos, 2]),
                        ),
                        linear_acceleration_covariance=zero9,
                    )
                    writer.write(
                        imu_conn,
                        stamp,
                        typestore.serialize_ros1(message, "sensor_msgs/msg/Imu"),
                    )
                    imu_pos += 1

            with SessionVideo(
                session_dir,
                topic=options.video_topic,
                scale=options.scale,
                grayscale=options.grayscale,
            ) as video:
                for seq, frame in enumerate(
                    progress(video.frames(), total=video.frame_count, desc="rosbag1", unit="frame")
                ):
                    write_imu_until(frame.stamp_ns)
                    image = frame.image
                    if options.compressed:
                        import cv2

                        ok, encoded = cv2.imencode(
                            ".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality]
                        )
                        if not ok:
                            raise InputError(f"{session_dir}: JPEG encoding failed")
                        message = types[image_type](
                            header=header(frame.stamp_ns, seq, frame_id),
                            format="jpeg",
                            data=np.frombuffer(encoded.tobytes(), dtype=np.uint8),
                        )
                    else:
                        height, width = image.shape[:2]
                        channels = 1 if image.ndim == 2 else image.shape[2]
                        message = types[image_type](
                            header=header(frame.stamp_ns, seq, frame_id),
                            height=height,
                            width=width,
                            encoding="mono8" if channels == 1 else "bgr8",
                            is_bigendian=0,
                            step=width * channels,
                            data=image.reshape(-1),
                        )
                    writer.write(
                        image_conn, frame.stamp_ns, typestore.serialize_ros1(message, image_type)
                    )
            write_imu_until(None)
        finally:
            writer.close()
    return out


def export_rosbag2(
    options: ExportOptions, session_dir: Path, out: Path, *, overwrite: bool
) -> Path:
    """The session's MCAP files + metadata.yaml, hard-linked (or copied) into folder `out`."""
    del options  # the bag is the session's archive as it is
    metadata = SessionFolder(session_dir).bag_metadata
    if not metadata.is_file():
        raise InputError(f"{session_dir}: no {metadata.name} (not a complete session folder)")
    files = [*session_archives(session_dir), metadata]
    with atomic_path(out, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        for path in progress(files, total=len(files), desc="rosbag2", unit="file"):
            target = tmp / path.name
            try:
                os.link(path, target)
            except OSError:
                shutil.copy2(path, target)  # another file system, or links not allowed
    return out


EXPORTERS = {"euroc": export_euroc, "rosbag1": export_rosbag1, "rosbag2": export_rosbag2}
"""Format name -> exporter(options, session_dir, out, *, overwrite)."""


def export_session(
    options: ExportOptions, session_dir: Path, out: Path, *, overwrite: bool = False
) -> Path:
    """Export `session_dir` in `options.format` to `out`; returns `out`.

    InputError for an unknown format or a folder that is not a session;
    OutputExistsError when `out` exists and `overwrite` is false.
    """
    session_dir = Path(session_dir)
    out = Path(out)
    exporter = EXPORTERS.get(options.format)
    if exporter is None:
        raise InputError(
            f"export format {options.format!r}: expected one of {', '.join(EXPORTERS)}"
        )
    if not 0.0 < options.scale <= 1.0:
        raise InputError(f"scale {options.scale}: expected 0 < scale <= 1")
    _check_session(session_dir)
    if out.exists() and not overwrite:
        raise OutputExistsError(f"{out}: already exists (refusing to overwrite)")
    return exporter(options, session_dir, out, overwrite=overwrite)
