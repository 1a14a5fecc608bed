"""SLAM inputs: a session folder (MCAP + calib/) reads like the EuRoC folder it came from
(the readers themselves: tests/shared/test_recordings.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from postproc.slam.frontend import FrontendOptions
from postproc.slam.inputs import open_input
from postproc.slam.stage import SlamOptions, run
from shared.archive import ArchiveWriter, CompressedImage, Imu
from shared.calibration.kalibr import write_camchain, write_imu_yaml
from shared.errors import InputError
from shared.formats.euroc import read_euroc
from shared.formats.tum import read_tum


def _session_from_euroc(euroc: Path, folder: Path, *, frames: int) -> Path:
    data = read_euroc(euroc)
    assert data.camera is not None and data.imu_noise is not None
    folder.mkdir()
    with ArchiveWriter(folder / "recording.mcap") as writer:
        for stamp, gyro, accel in zip(
            data.imu_stamps_ns, data.gyro_rad_s, data.accel_m_s2, strict=True
        ):
            writer.write("/imu0", Imu(int(stamp), "imu0", gyro, accel))
        for stamp, path in list(zip(data.image_stamps_ns, data.image_paths, strict=True))[:frames]:
            writer.write(
                "/cam0/image", CompressedImage(int(stamp), "cam0", "png", path.read_bytes())
            )
    write_camchain(folder / "calib" / "camchain.yaml", [data.camera])
    write_imu_yaml(folder / "calib" / "imu.yaml", data.imu_noise)
    return folder


def test_session_folder_matches_the_euroc_folder(wall_euroc: Path, tmp_path: Path) -> None:
    session = _session_from_euroc(wall_euroc, tmp_path / "session", frames=60)
    source = open_input(session)
    assert source.recording.kind == "session"
    reference = open_input(wall_euroc)
    assert reference.recording.kind == "euroc"
    assert source.frame_count == 60
    np.testing.assert_array_equal(source.imu.stamps_ns, reference.imu.stamps_ns)
    np.testing.assert_allclose(source.imu.gyro_rad_s, reference.imu.gyro_rad_s)
    assert source.calibration is not None and reference.calibration is not None
    assert source.calibration.camera == reference.calibration.camera
    assert source.imu_noise == reference.imu_noise
    ours = list(source.frames())
    theirs = list(reference.frames())[:60]
    assert [f.stamp_ns for f in ours] == [f.stamp_ns for f in theirs]
    np.testing.assert_array_equal(ours[7].image, theirs[7].image)
    assert ours[7].encoded_png == theirs[7].encoded_png
    # The stage runs on it and writes the same kind of result.
    out = run(SlamOptions(frontend=FrontendOptions(width_px=0)), session, tmp_path / "slam")
    assert len(read_tum(out / "trajectory.tum")) == 60


def test_session_errors(tmp_path: Path) -> None:
    empty = tmp_path / "nothing"
    empty.mkdir()
    with pytest.raises(InputError, match="not a recording"):
        open_input(empty)
    imu_only = tmp_path / "imu_only"
    imu_only.mkdir()
    with ArchiveWriter(imu_only / "recording.mcap") as writer:
        for k in range(5):
            writer.write("/imu0", Imu(k * 5_000_000, "imu0", np.zeros(3), np.array([0, 0, 9.81])))
    wanted = r"no camera topic '/cam0/image' or '/cam0/video' \(topics: /imu0\)"
    with pytest.raises(InputError, match=wanted):
        open_input(imu_only)
    no_imu = tmp_path / "no_imu"
    no_imu.mkdir()
    with ArchiveWriter(no_imu / "recording.mcap") as writer:
        writer.write("/cam0/image", CompressedImage(0, "cam0", "png", b"not a png"))
    # No IMU: only the visual-only path runs, and the stage says so.
    assert len(open_input(no_imu).imu) == 0
    with pytest.raises(InputError, match="no IMU data in the input"):
        run(SlamOptions(), no_imu, tmp_path / "out")
    # A frame that does not decode names the recording and the time.
    broken = tmp_path / "broken"
    broken.mkdir()
    with ArchiveWriter(broken / "recording.mcap") as writer:
        for k in range(5):
            writer.write("/imu0", Imu(k * 5_000_000, "imu0", np.zeros(3), np.array([0, 0, 9.81])))
        writer.write("/cam0/image", CompressedImage(1_000_000, "cam0", "png", b"not a png"))
    with pytest.raises(InputError, match=r"/cam0/image at 1000000 ns .*cannot be read"):
        list(open_input(broken).frames())


def test_euroc_errors(tmp_path: Path) -> None:
    folder = tmp_path / "euroc" / "mav0"
    (folder / "cam0" / "data").mkdir(parents=True)
    (folder / "imu0").mkdir()
    (folder / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n1000,1000.png\n")
    (folder / "cam0" / "data" / "1000.png").write_bytes(b"garbage")
    (folder / "imu0" / "data.csv").write_text(
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n0,0,0,0,0,0,9.81\n"
    )
    with pytest.raises(InputError, match="fewer than 2 IMU samples"):
        open_input(tmp_path / "euroc")
    with (folder / "imu0" / "data.csv").open("a") as f:
        f.write("5000000,0,0,0,0,0,9.81\n")
    source = open_input(tmp_path / "euroc")
    with pytest.raises(InputError, match="cannot be read as an image"):
        list(source.frames())
    (folder / "cam0" / "data" / "1000.png").unlink()  # vanished after the folder was read
    with pytest.raises(InputError, match="cannot read image"):
        list(source.frames())


def _tiny_session(folder: Path, session_yaml: str | None) -> Path:
    folder.mkdir()
    with ArchiveWriter(folder / "recording.mcap") as writer:
        for k in range(3):
            writer.write("/imu0", Imu(10**9 + k * 5_000_000, "imu0", np.zeros(3), np.ones(3)))
        writer.write("/cam0/image", CompressedImage(10**9, "cam0", "png", b"not decoded here"))
    if session_yaml is not None:
        (folder / "session.yaml").write_text(session_yaml, encoding="utf-8")
    return folder


@pytest.mark.parametrize(
    ("session_yaml", "expected"),
    [
        ("calibration:\n  camchain_source: 'guess: HERO5 Black Wide FOV 118.2 deg'\n", True),
        ("calibration:\n  camchain_source: given (camchain.yaml)\n", False),
        ("calibration: [unclosed\n", False),  # unreadable: not a guess we know of
        ("- a list, not a mapping\n", False),
        (None, False),
    ],
)
def test_calibration_is_guess_follows_session_yaml(
    tmp_path: Path, session_yaml: str | None, expected: bool
) -> None:
    source = open_input(_tiny_session(tmp_path / "s", session_yaml))
    assert source.calibration_is_guess is expected


def test_a_camera_only_euroc_folder_runs_visual_only(wall_euroc: Path, tmp_path: Path) -> None:
    folder = tmp_path / "cam_only"
    shutil.copytree(wall_euroc / "mav0" / "cam0", folder / "mav0" / "cam0")
    source = open_input(folder)
    assert source.recording.kind == "euroc" and not source.recording.has_imu
    assert len(source.imu) == 0 and source.frame_count == 80
    with pytest.raises(InputError, match=r"cam_only: no IMU data .*--no-imu"):
        run(SlamOptions(), folder, tmp_path / "vio")
    options = SlamOptions(frontend=FrontendOptions(width_px=0), use_imu=False, max_frames=40)
    out = run(options, folder, tmp_path / "vo")
    assert len(read_tum(out / "trajectory.tum")) > 20
