"""Export round trips: EuRoC (read back with read_euroc), ROS 1 bags and ROS 2 bags (rosbags)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from field.export import ExportOptions, export_session
from field.gopro.importer import ImportOptions, import_recording
from shared.archive import ArchiveReader
from shared.archive.video import SessionVideo
from shared.calibration.kalibr import read_camchain
from shared.errors import InputError, OutputExistsError
from shared.formats.euroc import read_euroc

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def session(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("export") / "karma"
    import_recording(ImportOptions(), [shared_data / "gopro" / "karma.mp4"], folder)
    return folder


@pytest.fixture(scope="module")
def truth(session: Path) -> dict[str, np.ndarray]:
    with ArchiveReader(session / "recording.mcap") as reader:
        imu = reader.read_imu()
    with SessionVideo(session, grayscale=True, scale=0.5) as video:
        frames = list(video.frames())
    return {
        "imu_stamps": imu.stamps_ns,
        "gyro": imu.gyro_rad_s,
        "accel": imu.accel_m_s2,
        "frame_stamps": np.array([f.stamp_ns for f in frames]),
        "first": frames[0].image,
        "last": frames[-1].image,
    }


def test_euroc_round_trip(session: Path, truth: dict[str, np.ndarray], tmp_path: Path) -> None:
    out = export_session(ExportOptions(format="euroc", scale=0.5), session, tmp_path / "euroc")
    dataset = read_euroc(out)
    assert np.array_equal(dataset.image_stamps_ns, truth["frame_stamps"])
    assert np.array_equal(dataset.imu_stamps_ns, truth["imu_stamps"])
    assert np.allclose(dataset.gyro_rad_s, truth["gyro"], atol=1e-9)
    assert np.allclose(dataset.accel_m_s2, truth["accel"], atol=1e-9)
    first = cv2.imread(str(dataset.image_paths[0]), cv2.IMREAD_UNCHANGED)
    assert first is not None
    assert np.array_equal(first, truth["first"])  # PNG is lossless
    assert dataset.camera is not None
    full = read_camchain(session / "calib" / "camchain.yaml")[0].camera
    assert dataset.camera.camera.width == round(full.width * 0.5)
    assert dataset.camera.camera.intrinsic_matrix[0, 0] == pytest.approx(
        full.intrinsic_matrix[0, 0] * 0.5
    )
    assert dataset.imu_noise is not None
    with pytest.raises(OutputExistsError):
        export_session(ExportOptions(format="euroc"), session, out)


@pytest.mark.parametrize("compressed", [False, True])
def test_rosbag1_round_trip(
    session: Path, truth: dict[str, np.ndarray], tmp_path: Path, compressed: bool
) -> None:
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_typestore

    options = ExportOptions(format="rosbag1", scale=0.5, compressed=compressed, jpeg_quality=100)
    bag = export_session(options, session, tmp_path / "karma.bag")
    typestore = get_typestore(Stores.ROS1_NOETIC)
    image_topic = "/cam0/image_raw/compressed" if compressed else "/cam0/image_raw"
    stamps: dict[str, list[int]] = {image_topic: [], "/imu0": []}
    first_image = None
    gyro = []
    with Reader(bag) as reader:
        for connection, timestamp, raw in reader.messages():
            message: Any = typestore.deserialize_ros1(raw, connection.msgtype)
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            assert stamp == timestamp
            stamps[connection.topic].append(stamp)
            if connection.topic == "/imu0":
                gyro.append(
                    [
                        message.angular_velocity.x,
                        message.angular_velocity.y,
                        message.angular_velocity.z,
                    ]
                )
            elif first_image is None:
                if compressed:
                    first_image = cv2.imdecode(message.data, cv2.IMREAD_UNCHANGED)
                else:
                    assert message.encoding == "mono8"
                    first_image = message.data.reshape(message.height, message.width)
    assert np.array_equal(stamps[image_topic], truth["frame_stamps"])
    assert np.array_equal(stamps["/imu0"], truth["imu_stamps"])
    assert np.allclose(gyro, truth["gyro"])
    assert first_image is not None
    if compressed:
        assert np.abs(first_image.astype(int) - truth["first"]).mean() < 2.0  # JPEG q100
    else:
        assert np.array_equal(first_image, truth["first"])


def test_rosbag2_is_a_linked_copy(session: Path, tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader

    out = export_session(ExportOptions(format="rosbag2"), session, tmp_path / "bag2")
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "recording.mcap"]
    assert (out / "recording.mcap").stat().st_ino == (session / "recording.mcap").stat().st_ino
    with Reader(out) as bag:
        assert {c.topic: c.msgcount for c in bag.connections}["/cam0/video"] == 362


def test_bad_requests(session: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="export format 'avi'"):
        export_session(ExportOptions(format="avi"), session, tmp_path / "x")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="not a session folder"):
        export_session(ExportOptions(format="euroc"), tmp_path / "missing", tmp_path / "x")
    with pytest.raises(InputError, match="scale 2"):
        export_session(ExportOptions(format="euroc", scale=2), session, tmp_path / "x")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "recording.mcap").write_bytes((session / "recording.mcap").read_bytes())
    with pytest.raises(InputError, match=r"no calib/camchain\.yaml"):
        export_session(ExportOptions(format="euroc"), empty, tmp_path / "x")
    with pytest.raises(InputError, match=r"no metadata\.yaml"):
        export_session(ExportOptions(format="rosbag2"), empty, tmp_path / "x")
    with pytest.raises(InputError, match="jpeg_quality 0"):
        export_session(ExportOptions(format="rosbag1", jpeg_quality=0), session, tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_cli_export_as_a_subprocess(session: Path, tmp_path: Path) -> None:
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    command = [sys.executable, "-m", "field.cli", "export", str(session), "--format", "rosbag2"]
    done = subprocess.run(
        [*command, "--out", str(tmp_path / "b")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "b" / "metadata.yaml").is_file()
    again = subprocess.run(
        [*command, "--out", str(tmp_path / "b")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert again.returncode == 1 and "already exists" in again.stderr
