"""The calibration stage end to end: recordings in, Kalibr YAML, reports and plots out; the CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from postproc.calibrate.sources import open_frames, read_gyro, source_kind
from postproc.calibrate.stage import (
    CameraCalibrationOptions,
    ImuCalibrationOptions,
    RigCalibrationOptions,
    run_camera,
    run_imu,
    run_rig,
)
from shared.archive import ArchiveWriter, CompressedImage, Imu
from shared.calibration.kalibr import (
    CameraCalibration,
    read_camchain,
    write_camchain,
    write_target_yaml,
)
from shared.errors import InputError, StageError
from shared.formats.euroc import EurocWriter
from shared.geometry import rotation_angle_rad
from sim.calibration import TARGET, two_gyros

REPO = Path(__file__).resolve().parents[3]


def _rotation_error_deg(estimate, truth):
    return float(np.degrees(rotation_angle_rad(estimate[:3, :3] @ truth[:3, :3].T)))


def write_image_session(folder: Path, stamps_ns, images, imu_stamps_ns, gyro, accel) -> Path:
    """A session folder: PNG stills on /cam0/image and the IMU on /imu0, in time order."""
    folder.mkdir(parents=True)
    events = [(int(s), "image", i) for i, s in enumerate(stamps_ns)]
    events += [(int(s), "imu", i) for i, s in enumerate(imu_stamps_ns)]
    with ArchiveWriter(folder / "recording.mcap") as writer:
        for stamp, kind, i in sorted(events):
            if kind == "image":
                ok, png = cv2.imencode(".png", images[i])
                assert ok
                writer.write("/cam0/image", CompressedImage(stamp, "cam0", "png", png.tobytes()))
            else:
                writer.write(
                    "/imu0",
                    Imu(stamp, "imu0", np.asarray(gyro[i], float), np.asarray(accel[i], float)),
                )
    return folder


def write_imu_session(folder: Path, stamps_ns, gyro) -> Path:
    folder.mkdir(parents=True)
    with ArchiveWriter(folder / "recording.mcap") as writer:
        for stamp, rate in zip(stamps_ns, gyro, strict=True):
            writer.write("/imu0", Imu(int(stamp), "imu0", np.asarray(rate, float), np.zeros(3)))
    return folder


@pytest.fixture
def target_yaml(tmp_path) -> Path:
    return write_target_yaml(tmp_path / "aprilgrid.yaml", TARGET)


@pytest.fixture
def image_folder(tmp_path, radtan_views) -> Path:
    _, images, _ = radtan_views
    folder: Path = tmp_path / "views"
    folder.mkdir()
    for index, image in enumerate(images):
        cv2.imwrite(str(folder / f"view_{index:03d}.png"), image)
    return folder


# ----------------------------------------------------------------------------- camera


def test_run_camera_on_an_image_folder(tmp_path, radtan_views, image_folder, target_yaml):
    camera, _, _ = radtan_views
    out = tmp_path / "calib"
    path = run_camera(CameraCalibrationOptions(), image_folder, target_yaml, out)
    assert path == out / "camchain.yaml"
    (calibration,) = read_camchain(path)
    estimate = calibration.camera
    for name in ("fx", "fy", "cx", "cy"):
        truth = getattr(camera, name)
        assert abs(getattr(estimate, name) - truth) / truth < 0.005, name
    np.testing.assert_array_equal(calibration.cam_from_imu, np.eye(4))
    report = json.loads((out / "camera_calibration.json").read_text())
    assert report["frames_examined"] == 20
    assert report["views_used"] >= 15
    assert report["coverage_fraction"] > 0.7
    assert report["rms_px"] < 0.3
    assert (out / "coverage.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A second run finds the result and does nothing; overwrite redoes it.
    before = path.stat().st_mtime_ns
    assert run_camera(CameraCalibrationOptions(), image_folder, target_yaml, out) == path
    assert path.stat().st_mtime_ns == before


def test_run_camera_on_a_video_file(tmp_path, radtan_views, target_yaml):
    import av

    _, images, _ = radtan_views
    video = tmp_path / "sweep.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("mpeg4", rate=2)
        stream.width, stream.height = images[0].shape[1], images[0].shape[0]
        stream.pix_fmt = "yuv420p"
        stream.options = {"qscale": "1"}
        for image in images:
            frame = av.VideoFrame.from_ndarray(image, format="gray")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    source = open_frames(video)
    stamps = [stamp for _, stamp, _ in source.frames()]
    np.testing.assert_array_equal(stamps, np.arange(20) * 500_000_000)
    path = run_camera(CameraCalibrationOptions(), video, target_yaml, tmp_path / "calib")
    assert read_camchain(path)[0].camera.width == 320


def test_run_camera_without_the_grid_is_an_error(tmp_path, target_yaml):
    folder = tmp_path / "blank"
    folder.mkdir()
    for index in range(3):
        cv2.imwrite(str(folder / f"{index}.png"), np.full((120, 160), 128, np.uint8))
    with pytest.raises(StageError, match="0 usable view"):
        run_camera(CameraCalibrationOptions(), folder, target_yaml, tmp_path / "calib")
    cv2.imwrite(str(folder / "9.png"), np.full((100, 160), 128, np.uint8))
    with pytest.raises(InputError, match="frame 3 is 160x100, the first was 160x120"):
        run_camera(CameraCalibrationOptions(), folder, target_yaml, tmp_path / "calib")


# ----------------------------------------------------------------------------- camera-IMU


def test_run_imu_on_a_session_with_the_grid(tmp_path, sweep, target_yaml):
    session = write_image_session(
        tmp_path / "session",
        sweep.frame_stamps_ns,
        sweep.images,
        sweep.imu_stamps_ns,
        sweep.gyro_rad_s,
        sweep.accel_m_s2,
    )
    camchain = write_camchain(
        tmp_path / "camchain.yaml", [CameraCalibration(camera=sweep.camera, topic="/cam0/image")]
    )
    out = tmp_path / "calib"
    # Every second frame: half the detection work, pairs 67 ms apart.
    options = ImuCalibrationOptions(use_features=False, frame_stride=2)
    path = run_imu(options, session, camchain, target_yaml, out)
    assert path == out / "camchain-imucam.yaml"
    (calibration,) = read_camchain(path)
    assert _rotation_error_deg(calibration.cam_from_imu, sweep.cam_from_imu) < 0.5
    assert abs(calibration.timeshift_cam_imu_s - sweep.timeshift_cam_imu_s) < 0.002
    np.testing.assert_array_equal(calibration.cam_from_imu[:3, 3], 0.0)
    report = json.loads((out / "camera_imu.json").read_text())
    assert report["frame_pairs_from_grid"] >= 55
    assert report["frame_pairs_from_features"] == 0
    assert report["translation"].startswith("zero")
    assert (out / "camera_imu.png").is_file()


def test_cli_imu_on_euroc_from_features_only(tmp_path, sweep):
    euroc = tmp_path / "euroc"
    with EurocWriter(euroc, camera=CameraCalibration(camera=sweep.camera)) as writer:
        for stamp, image in zip(sweep.frame_stamps_ns, sweep.images, strict=True):
            writer.add_image(int(stamp), image)
        writer.add_imu(sweep.imu_stamps_ns, sweep.gyro_rad_s, sweep.accel_m_s2)
    # The input chain already has a lever arm: it is kept.
    start = np.eye(4)
    start[:3, 3] = (0.01, 0.02, 0.03)
    camchain = write_camchain(
        tmp_path / "camchain.yaml", [CameraCalibration(camera=sweep.camera, cam_from_imu=start)]
    )
    out = tmp_path / "calib"
    done = _cli("imu", str(euroc), "--calib", str(camchain), "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(out / "camchain-imucam.yaml")
    (calibration,) = read_camchain(out / "camchain-imucam.yaml")
    assert _rotation_error_deg(calibration.cam_from_imu, sweep.cam_from_imu) < 0.5
    assert abs(calibration.timeshift_cam_imu_s - sweep.timeshift_cam_imu_s) < 0.002
    np.testing.assert_allclose(calibration.cam_from_imu[:3, 3], (0.01, 0.02, 0.03))
    report = json.loads((out / "camera_imu.json").read_text())
    assert report["frame_pairs_from_grid"] == 0
    assert report["frame_pairs_from_features"] >= 60
    assert report["translation"].startswith("kept")


def test_run_imu_input_errors(tmp_path, sweep, target_yaml):
    camchain = write_camchain(tmp_path / "camchain.yaml", [CameraCalibration(camera=sweep.camera)])
    with pytest.raises(InputError, match="no camera 1"):
        run_imu(ImuCalibrationOptions(camera_index=1), tmp_path, camchain, None, tmp_path / "o")
    with pytest.raises(StageError, match="features disabled"):
        run_imu(ImuCalibrationOptions(use_features=False), tmp_path, camchain, None, tmp_path)
    session = write_imu_session(tmp_path / "imu_only", sweep.imu_stamps_ns, sweep.gyro_rad_s)
    wanted = r"no camera topic '/cam0/image' or '/cam0/video' \(topics: /imu0\)"
    with pytest.raises(InputError, match=wanted):
        run_imu(ImuCalibrationOptions(), session, camchain, target_yaml, tmp_path / "o")
    small = write_camchain(
        tmp_path / "small.yaml",
        [CameraCalibration(camera=sweep.camera.scaled(0.5), topic="/cam0/image")],
    )
    images = write_image_session(
        tmp_path / "with_images",
        sweep.frame_stamps_ns[:3],
        sweep.images[:3],
        sweep.imu_stamps_ns[:50],
        sweep.gyro_rad_s[:50],
        sweep.accel_m_s2[:50],
    )
    with pytest.raises(InputError, match="calibration is for 160x120"):
        run_imu(ImuCalibrationOptions(), images, small, target_yaml, tmp_path / "o")
    with pytest.raises(InputError, match="frame_stride 0"):
        run_imu(ImuCalibrationOptions(frame_stride=0), images, small, target_yaml, tmp_path / "o")


# ----------------------------------------------------------------------------- rig


def test_run_rig_on_two_sessions(tmp_path):
    offset = 2.345
    stamps0, gyro0, stamps1, gyro1, imu1_from_imu0 = two_gyros(8, offset)
    rig0 = write_imu_session(tmp_path / "rig0", stamps0, gyro0)
    rig1 = write_imu_session(tmp_path / "rig1", stamps1, gyro1)
    from sim.calibration import radtan_camera

    cam_from_imu0 = np.eye(4)
    cam_from_imu0[:3, 3] = (0.0, 0.01, 0.0)
    cam_from_imu1 = np.eye(4)
    cam_from_imu1[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], dtype=float)
    chain0 = write_camchain(
        tmp_path / "c0.yaml",
        [
            CameraCalibration(
                camera=radtan_camera(), cam_from_imu=cam_from_imu0, timeshift_cam_imu_s=0.01
            )
        ],
    )
    chain1 = write_camchain(
        tmp_path / "c1.yaml",
        [
            CameraCalibration(
                camera=radtan_camera(), cam_from_imu=cam_from_imu1, timeshift_cam_imu_s=0.02
            )
        ],
    )
    path = run_rig(RigCalibrationOptions(), rig0, rig1, chain0, chain1, tmp_path / "rig")
    first, second = read_camchain(path)
    np.testing.assert_allclose(first.cam_from_imu, cam_from_imu0)
    expected = cam_from_imu1[:3, :3] @ imu1_from_imu0
    assert _rotation_error_deg(second.cam_from_imu, expected) < 0.5
    np.testing.assert_array_equal(second.cam_from_imu[:3, 3], 0.0)
    assert abs(second.timeshift_cam_imu_s - (0.02 - offset)) < 0.002
    report = json.loads((tmp_path / "rig" / "rig.json").read_text())
    assert abs(report["clock_offset_s"] - offset) < 0.002
    with pytest.raises(InputError, match="the same recording and IMU topic"):
        run_rig(RigCalibrationOptions(), rig0, rig0, chain0, chain1, tmp_path / "rig2")


# ----------------------------------------------------------------------------- sources


def test_source_errors(tmp_path):
    with pytest.raises(InputError, match="no such file or folder"):
        source_kind(tmp_path / "missing")
    note = tmp_path / "notes.txt"
    note.write_text("x")
    with pytest.raises(InputError, match="not a recording"):
        source_kind(note)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="empty: not a recording"):
        source_kind(empty)
    images = tmp_path / "images"
    images.mkdir()
    (images / "1000.png").write_bytes(b"not a png")
    assert source_kind(images) == "images"
    with pytest.raises(InputError, match="cannot be read as an image"):
        list(open_frames(images).frames())
    with pytest.raises(InputError, match="holds no IMU samples"):
        read_gyro(images)
    fake = tmp_path / "fake.mp4"
    fake.write_bytes(b"\x00" * 64)
    with pytest.raises(InputError, match="cannot open as a video"):
        list(open_frames(fake).frames())


def test_image_stamps_come_from_integer_names(tmp_path):
    folder = tmp_path / "stamped"
    folder.mkdir()
    for stamp in (1_700_000_000_000_000_000, 1_700_000_000_050_000_000):
        cv2.imwrite(str(folder / f"{stamp}.png"), np.zeros((8, 8), np.uint8))
    assert [s for _, s, _ in open_frames(folder).frames()] == [
        1_700_000_000_000_000_000,
        1_700_000_000_050_000_000,
    ]
    # Short numbers are a counter, not time: the frames are a second apart.
    counted = tmp_path / "counted"
    counted.mkdir()
    for name in ("000", "001", "002"):
        cv2.imwrite(str(counted / f"{name}.jpg"), np.zeros((8, 8), np.uint8))
    assert [s for _, s, _ in open_frames(counted).frames()] == [0, 10**9, 2 * 10**9]


# ----------------------------------------------------------------------------- CLI


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, WRECKMAP_PROGRESS="0")
    return subprocess.run(
        [sys.executable, "-m", "postproc.cli", "calibrate", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_cli_camera_and_rig(tmp_path, image_folder, target_yaml):
    out = tmp_path / "calib"
    done = _cli("camera", str(image_folder), "--target", str(target_yaml), "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(out / "camchain.yaml")
    assert read_camchain(out / "camchain.yaml")[0].camera.width == 320

    stamps0, gyro0, stamps1, gyro1, _ = two_gyros(9, -1.5)
    rig0 = write_imu_session(tmp_path / "rig0", stamps0, gyro0)
    rig1 = write_imu_session(tmp_path / "rig1", stamps1, gyro1)
    done = _cli(
        "rig",
        str(rig0),
        str(rig1),
        "--calib0",
        str(out / "camchain.yaml"),
        "--calib1",
        str(out / "camchain.yaml"),
        "--out",
        str(tmp_path / "rig"),
    )
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "rig" / "rig.json").read_text())
    assert abs(report["clock_offset_s"] + 1.5) < 0.002


def test_cli_reports_errors_in_one_line(tmp_path, target_yaml):
    done = _cli("imu", str(tmp_path / "nowhere"), "--calib", str(target_yaml), "--out", "x")
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("wreckmap-post: error:")
    help_text = _cli("camera", "--help")
    assert help_text.returncode == 0 and "example:" in help_text.stdout


def test_a_gopro_session_gives_video_frames_and_gyro(tmp_path, shared_data):
    from field.gopro.importer import ImportOptions, import_recording

    session = tmp_path / "karma"
    import_recording(ImportOptions(), [shared_data / "gopro" / "karma.mp4"], session)
    assert source_kind(session) == "session"
    source = open_frames(session)
    assert source.topic == "/cam0/video"
    stamps = []
    for index, stamp, image in source.frames():
        assert image.shape == (480, 854) and image.dtype == np.uint8
        stamps.append(stamp)
        if index == 59:
            break
    steps = np.diff(stamps)
    assert np.all(np.abs(steps - 1e9 / 29.97) < 1e5)  # 29.97 fps, within 0.1 ms
    gyro_stamps, gyro = read_gyro(session)
    assert gyro.shape == (len(gyro_stamps), 3) and len(gyro_stamps) > 4000
    assert np.all(np.diff(gyro_stamps) > 0)
    # Asking for stills finds the video topic instead.
    assert open_frames(session, topic="/cam0/image").topic == "/cam0/video"
