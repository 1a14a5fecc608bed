"""EuRoC folders: write-then-read round trips, files as EuRoC ships them, error paths."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from shared.calibration.cameras import PinholeEquidistant, PinholeRadtan
from shared.calibration.kalibr import CameraCalibration, ImuNoise
from shared.errors import InputError, OutputExistsError
from shared.formats.euroc import EurocWriter, read_euroc
from shared.geometry import make_pose, so3_exp
from shared.trajectory import Trajectory

T0_NS = 1_403_636_579_763_555_584  # an EuRoC stamp: needs all 64 bits, no float survives it

EUROC_CAM0_YAML = """\
%YAML:1.0
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""

EUROC_IMU0_YAML = """\
#Default imu sensor yaml file
sensor_type: imu
comment: VI-Sensor IMU (ADIS16448)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 200

# inertial sensor noise model parameters (static)
gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )
gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )
accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]   ( accel "white noise" )
accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )
"""


def _calibration(model: type = PinholeRadtan) -> CameraCalibration:
    rng = np.random.default_rng(7)
    camera = model(64, 48, 50.5, 50.25, 31.7, 23.9, -0.1, 0.02, 0.001, -0.002)
    pose = make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 0.1)
    return CameraCalibration(
        camera=camera, cam_from_imu=pose, timeshift_cam_imu_s=1.5e-3, topic="/gopro: video #0"
    )


def _trajectory(count: int) -> Trajectory:
    rng = np.random.default_rng(8)
    stamps = T0_NS + np.arange(count, dtype=np.int64) * 5_000_001
    poses = make_pose(so3_exp(rng.normal(size=(count, 3))), rng.normal(size=(count, 3)))
    return Trajectory(stamps_ns=stamps, poses=poses)


def _write_sample(
    folder: Path, *, model: type = PinholeRadtan, noise: bool = True
) -> dict[str, Any]:
    rng = np.random.default_rng(9)
    calibration = _calibration(model)
    imu_noise = ImuNoise(2.0e-3, 3.0e-3, 1.6968e-4, 1.9393e-5, 200.0, "/imu: #1") if noise else None
    images = [rng.integers(0, 256, size=(48, 64), dtype=np.uint8) for _ in range(3)]
    image_stamps = [T0_NS, T0_NS + 50_000_000, T0_NS + 100_000_001]
    imu_stamps = T0_NS - 1 + np.arange(40, dtype=np.int64) * 5_000_000
    gyro = rng.normal(size=(40, 3))
    accel = rng.normal(size=(40, 3)) + np.array([0.0, 0.0, 9.81])
    trajectory = _trajectory(10)
    velocities = rng.normal(size=(10, 3))
    gyro_bias = rng.normal(size=(10, 3)) * 1e-3
    accel_bias = rng.normal(size=(10, 3)) * 1e-2
    with EurocWriter(folder, camera=calibration, imu_noise=imu_noise) as writer:
        for stamp, image in zip(image_stamps, images, strict=True):
            writer.add_image(stamp, image)
        writer.add_imu(imu_stamps[:25], gyro[:25], accel[:25])
        writer.add_imu(imu_stamps[25:], gyro[25:], accel[25:])
        writer.set_groundtruth(trajectory, velocities, gyro_bias, accel_bias)
    return {
        "calibration": calibration,
        "noise": imu_noise,
        "images": images,
        "image_stamps": image_stamps,
        "imu_stamps": imu_stamps,
        "gyro": gyro,
        "accel": accel,
        "trajectory": trajectory,
        "velocities": velocities,
        "gyro_bias": gyro_bias,
        "accel_bias": accel_bias,
    }


@pytest.mark.parametrize("model", [PinholeRadtan, PinholeEquidistant])
def test_round_trip(tmp_path: Path, model: type) -> None:
    folder = tmp_path / "dive1_euroc"
    sample = _write_sample(folder, model=model)
    assert sorted(p.name for p in folder.parent.iterdir()) == ["dive1_euroc"]  # no temporaries
    for root in (folder, folder / "mav0"):
        dataset = read_euroc(root)
        assert dataset.image_stamps_ns.dtype == np.int64
        assert dataset.image_stamps_ns.tolist() == sample["image_stamps"]
        for path, image in zip(dataset.image_paths, sample["images"], strict=True):
            np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), image)
        assert dataset.imu_stamps_ns.tolist() == sample["imu_stamps"].tolist()
        np.testing.assert_array_equal(dataset.gyro_rad_s, sample["gyro"])
        np.testing.assert_array_equal(dataset.accel_m_s2, sample["accel"])
        assert dataset.groundtruth is not None
        truth = sample["trajectory"]
        assert dataset.groundtruth.stamps_ns.tolist() == truth.stamps_ns.tolist()
        np.testing.assert_allclose(dataset.groundtruth.poses, truth.poses, atol=1e-12)
        np.testing.assert_array_equal(dataset.groundtruth_velocities_m_s, sample["velocities"])
        np.testing.assert_array_equal(dataset.groundtruth_gyro_bias, sample["gyro_bias"])
        np.testing.assert_array_equal(dataset.groundtruth_accel_bias, sample["accel_bias"])
        assert dataset.camera is not None
        assert dataset.camera.camera == sample["calibration"].camera
        np.testing.assert_allclose(
            dataset.camera.cam_from_imu, sample["calibration"].cam_from_imu, atol=1e-12
        )
        assert dataset.camera.timeshift_cam_imu_s == 1.5e-3
        assert dataset.camera.topic == "/gopro: video #0"
        assert dataset.imu_noise == sample["noise"]


def test_sensor_yaml_follows_euroc(tmp_path: Path) -> None:
    _write_sample(tmp_path / "d")
    cam_yaml = (tmp_path / "d" / "mav0" / "cam0" / "sensor.yaml").read_text()
    assert "distortion_model: radial-tangential" in cam_yaml
    assert yaml.safe_load(cam_yaml)["rate_hz"] == pytest.approx(20.0, rel=1e-7)
    # Plain PyYAML must see numbers (it reads "1.9393e-05" as a float, "1.9393e-5" not).
    imu_yaml = yaml.safe_load((tmp_path / "d" / "mav0" / "imu0" / "sensor.yaml").read_text())
    assert imu_yaml["gyroscope_random_walk"] == 1.9393e-5
    assert yaml.safe_load(cam_yaml)["distortion_coefficients"][3] == -0.002
    header = (tmp_path / "d" / "mav0" / "imu0" / "data.csv").read_text().splitlines()[0]
    assert header.startswith("#timestamp [ns],w_RS_S_x [rad s^-1]")
    truth = tmp_path / "d" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    assert truth.read_text().startswith("#timestamp, p_RS_R_x [m]")


def test_defaults_without_noise_velocities_or_biases(tmp_path: Path) -> None:
    trajectory = _trajectory(5)
    with EurocWriter(tmp_path / "d", camera=_calibration()) as writer:
        writer.add_imu(np.array([10, 20, 30]), np.zeros((3, 3)), np.ones((3, 3)))
        writer.set_groundtruth(trajectory)
    dataset = read_euroc(tmp_path / "d")
    assert dataset.imu_noise is None
    assert dataset.image_stamps_ns.shape == (0,)
    assert "rate_hz: 100000000.0" in (tmp_path / "d/mav0/imu0/sensor.yaml").read_text()
    expected = np.gradient(
        trajectory.poses[:, :3, 3], (trajectory.stamps_ns - trajectory.stamps_ns[0]) * 1e-9, axis=0
    )
    assert dataset.groundtruth_velocities_m_s is not None
    np.testing.assert_allclose(dataset.groundtruth_velocities_m_s, expected)
    np.testing.assert_array_equal(dataset.groundtruth_gyro_bias, 0.0)


def test_ground_truth_left_unread_when_not_wanted(tmp_path: Path) -> None:
    with EurocWriter(tmp_path / "d", camera=_calibration()) as writer:
        writer.add_imu(np.array([10, 20, 30]), np.zeros((3, 3)), np.ones((3, 3)))
        writer.set_groundtruth(_trajectory(5))
    truth = tmp_path / "d" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    truth.write_text("not, a, truth file\n")  # would be refused if it were read
    dataset = read_euroc(tmp_path / "d", groundtruth=False)
    assert dataset.groundtruth is None and dataset.groundtruth_velocities_m_s is None
    assert dataset.imu_stamps_ns.tolist() == [10, 20, 30]
    with pytest.raises(InputError, match=r"data\.csv"):
        read_euroc(tmp_path / "d")


def test_reads_euroc_as_shipped(tmp_path: Path) -> None:
    mav = tmp_path / "MH_01_easy" / "mav0"
    (mav / "cam0" / "data").mkdir(parents=True)
    (mav / "imu0").mkdir()
    (mav / "state_groundtruth_estimate0").mkdir()
    cv2.imwrite(str(mav / "cam0" / "data" / "1403636579763555584.png"), np.zeros((480, 752)))
    (mav / "cam0" / "data.csv").write_text(
        "#timestamp [ns],filename\r\n1403636579763555584,1403636579763555584.png\r\n"
    )
    (mav / "cam0" / "sensor.yaml").write_text(EUROC_CAM0_YAML)
    (mav / "imu0" / "data.csv").write_text(
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
        "1403636579758555392,-0.099134701513277898,0.14730578886832138,0.02722713633111154,"
        "8.1476917083333333,-0.37592158333333331,-2.4026292499999999\n"
    )
    (mav / "imu0" / "sensor.yaml").write_text(EUROC_IMU0_YAML)
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [],"
        " q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x "
        "[rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], "
        "b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]\n"
        "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,"
        "-0.082152,-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,"
        "0.136696,0.075593\n"
    )
    dataset = read_euroc(tmp_path / "MH_01_easy")
    assert dataset.image_stamps_ns.tolist() == [1403636579763555584]
    assert dataset.imu_stamps_ns.tolist() == [1403636579758555392]
    assert dataset.accel_m_s2[0, 0] == pytest.approx(8.1476917083333333)
    assert dataset.camera is not None and isinstance(dataset.camera.camera, PinholeRadtan)
    assert dataset.camera.camera.k1 == pytest.approx(-0.28340811)
    np.testing.assert_allclose(
        dataset.camera.imu_from_cam[:3, 3], [-0.0216401454975, -0.064676986768, 0.00981073058949]
    )
    assert dataset.imu_noise == ImuNoise(2.0e-3, 3.0e-3, 1.6968e-4, 1.9393e-5, 200.0)
    assert dataset.groundtruth is not None
    assert dataset.groundtruth.positions[0] == pytest.approx([4.688319, -1.786938, 0.783338])
    assert dataset.groundtruth_accel_bias is not None
    assert dataset.groundtruth_accel_bias[0, 2] == pytest.approx(0.075593)


def test_pose_only_groundtruth_is_accepted(tmp_path: Path) -> None:
    _write_sample(tmp_path / "d")
    truth = tmp_path / "d" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = truth.read_text().splitlines()
    truth.write_text("\n".join([lines[0]] + [",".join(x.split(",")[:8]) for x in lines[1:]]))
    dataset = read_euroc(tmp_path / "d")
    assert dataset.groundtruth is not None and len(dataset.groundtruth) == 10
    assert dataset.groundtruth_velocities_m_s is None


def test_writer_refuses_existing_folder_and_discards_on_error(tmp_path: Path) -> None:
    _write_sample(tmp_path / "d")
    with pytest.raises(OutputExistsError):
        EurocWriter(tmp_path / "d", camera=_calibration())
    with (
        pytest.raises(RuntimeError, match="boom"),
        EurocWriter(tmp_path / "e", camera=_calibration()) as writer,
    ):
        writer.add_image(T0_NS, np.zeros((48, 64), np.uint8))
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]
    _write_sample(tmp_path / "d2")
    with EurocWriter(tmp_path / "d", camera=_calibration(), overwrite=True) as writer:
        writer.add_image(T0_NS + 7, np.zeros((48, 64), np.uint8))
    assert read_euroc(tmp_path / "d").image_stamps_ns.tolist() == [T0_NS + 7]


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    writer = EurocWriter(tmp_path / "d", camera=_calibration())
    writer.add_image(T0_NS, np.zeros((48, 64), np.uint8))
    with pytest.raises(ValueError, match="must increase"):
        writer.add_image(T0_NS, np.zeros((48, 64), np.uint8))
    with pytest.raises(ValueError, match="uint8 image of 64x48"):
        writer.add_image(T0_NS + 1, np.zeros((48, 65), np.uint8))
    writer.add_imu(np.array([5, 6]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="strictly increasing"):
        writer.add_imu(np.array([6, 7]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="integer nanoseconds"):
        writer.add_imu(np.array([8.0]), np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"gyro_rad_s: expected shape \(1, 3\)"):
        writer.add_imu(np.array([8]), np.zeros((2, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        writer.add_imu(np.array([8]), np.zeros((1, 3)), np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match=r"velocities_m_s: expected shape \(4, 3\)"):
        writer.set_groundtruth(_trajectory(4), velocities_m_s=np.zeros((3, 3)))
    assert writer.close() == tmp_path / "d"
    assert writer.close() == tmp_path / "d"
    with pytest.raises(ValueError, match="already closed"):
        writer.add_image(T0_NS + 5, np.zeros((48, 64), np.uint8))


def _corrupt(tmp_path: Path, relative: str, text: str | None) -> Path:
    _write_sample(tmp_path / "d")
    path = tmp_path / "d" / "mav0" / relative
    if text is None:
        path.unlink()
    else:
        path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("relative", "text", "message"),
    [
        ("cam0/data.csv", None, "no such file"),
        ("imu0/data.csv", None, "no such file"),
        ("cam0/data.csv", "#h\n12,\n", "expected 'timestamp \\[ns\\],filename'"),
        ("cam0/data.csv", "#h\n12,missing.png\n", "image missing.png missing"),
        ("imu0/data.csv", "#h\n1,2,3\n", "line 2: expected 7 comma-separated values"),
        ("imu0/data.csv", "#h\n1.5,0,0,0,0,0,0\n", "line 2: expected an integer ns stamp"),
        ("imu0/data.csv", "#h\n1,0,0,0,0,0,nan\n", "line 2: non-finite"),
        ("imu0/data.csv", "#h\n2,0,0,0,0,0,0\n2,0,0,0,0,0,0\n", "line 3: time stamp 2 ns"),
        ("state_groundtruth_estimate0/data.csv", "#h\n1,0,0,0,0,0,0,0\n", "zero quaternion"),
        ("state_groundtruth_estimate0/data.csv", "#h\n1,0,0,0,1,0\n", "expected 8"),
        ("cam0/sensor.yaml", "camera_model: omni\n", "unsupported camera_model"),
        ("cam0/sensor.yaml", EUROC_CAM0_YAML.replace("[752, 480]", "[752]"), "'resolution'"),
        ("cam0/sensor.yaml", EUROC_CAM0_YAML.replace("458.654, ", ""), "'intrinsics' as 4"),
        ("cam0/sensor.yaml", EUROC_CAM0_YAML.replace("rows: 4", "rows: 3"), "'T_BS' with rows"),
        ("cam0/sensor.yaml", EUROC_CAM0_YAML.replace("0.0148655429818", "2.0"), "not a rigid"),
        ("cam0/sensor.yaml", "- just\n- a list\n", "expected a YAML mapping"),
        ("cam0/sensor.yaml", "a: [\n", "not valid YAML"),
        ("imu0/sensor.yaml", EUROC_IMU0_YAML.replace("rate_hz: 200", ""), "'rate_hz'"),
    ],
)
def test_read_errors_name_the_file(
    tmp_path: Path, relative: str, text: str | None, message: str
) -> None:
    path = _corrupt(tmp_path, relative, text)
    with pytest.raises(InputError, match=message) as info:
        read_euroc(tmp_path / "d")
    assert str(path) in str(info.value)


def test_not_an_euroc_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not an EuRoC folder"):
        read_euroc(tmp_path)


@pytest.mark.parametrize(
    ("relative", "text", "message"),
    [
        ("cam0/data.csv", "#h\n20,a.png\n10,b.png\n", "line 3: time stamp 10 ns not after 20"),
        ("cam0/sensor.yaml", EUROC_CAM0_YAML.replace("[458.654,", "[-458.654,"), "focal"),
    ],
)
def test_more_read_errors(tmp_path: Path, relative: str, text: str, message: str) -> None:
    path = _corrupt(tmp_path, relative, text)
    for name in ("a.png", "b.png"):
        (path.parent / "data" / name).write_bytes(b"")
    with pytest.raises(InputError, match=message) as info:
        read_euroc(tmp_path / "d")
    assert str(path) in str(info.value)


def test_unreadable_files(tmp_path: Path) -> None:
    path = _corrupt(tmp_path, "imu0/data.csv", None)
    path.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match="cannot read"):
        read_euroc(tmp_path / "d")
    path.write_text("#h\n")
    (tmp_path / "d" / "mav0" / "imu0" / "sensor.yaml").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match=r"imu0/sensor\.yaml: cannot read"):
        read_euroc(tmp_path / "d")


def test_failed_image_write_and_failed_close_leave_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    writer = EurocWriter(tmp_path / "d", camera=_calibration())
    monkeypatch.setattr(cv2, "imwrite", lambda *args, **kwargs: False)
    with pytest.raises(OSError, match="imwrite failed"):
        writer.add_image(T0_NS, np.zeros((48, 64), np.uint8))
    monkeypatch.undo()

    def broken() -> None:
        raise RuntimeError("disk full")

    monkeypatch.setattr(writer, "_write_imu_yaml", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        writer.close()
    assert list(tmp_path.iterdir()) == []


def test_as_recorded_keeps_odd_imu_rows_and_allows_a_missing_sensor(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    imu0 = tmp_path / "set" / "mav0" / "imu0"
    imu0.mkdir(parents=True)
    rows = ["10,1,0,0,0,0,9.8", "20,2,0,0,0,0,9.8", "20,2,0,0,0,0,9.8", "15,3,0,0,0,0,9.8"]
    rows += ["30,four,0,0,0,0,9.8", "40,nan,0,0,0,0,9.8", "50,5,0,0"]
    (imu0 / "data.csv").write_text("#timestamp [ns],w,w,w,a,a,a\n" + "\n".join(rows) + "\n")
    with pytest.raises(InputError, match=r"cam0/data\.csv: no such file"):
        read_euroc(tmp_path / "set")
    with caplog.at_level("WARNING"):
        data = read_euroc(tmp_path / "set", as_recorded=True)
    # Repeated and backward stamps stay, in file order; words, NaN, short rows do not.
    np.testing.assert_array_equal(data.imu_stamps_ns, [10, 20, 20, 15])
    np.testing.assert_array_equal(data.gyro_rad_s[:, 0], [1, 2, 2, 3])
    assert "skipped 3 rows that are not a stamp and 6 numbers (lines 6, 7, 8)" in caplog.text
    assert len(data.image_stamps_ns) == 0 and data.image_paths == []
