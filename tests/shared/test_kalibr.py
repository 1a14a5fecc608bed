"""Kalibr YAML files: round trips, files as Kalibr writes them, and every error path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.cameras import PinholeEquidistant, PinholeRadtan
from shared.calibration.kalibr import (
    CameraCalibration,
    ImuNoise,
    read_camchain,
    read_imu_yaml,
    read_target_yaml,
    write_camchain,
    write_imu_yaml,
    write_target_yaml,
)
from shared.errors import InputError, OutputExistsError
from shared.geometry import make_pose, so3_exp

# Shaped like Kalibr's output for the EuRoC cameras (keys sorted, flow lists, 4x4 rows).
KALIBR_CAMCHAIN = """\
cam0:
  T_cam_imu:
  - [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
  - [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768]
  - [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
  timeshift_cam_imu: -8.121e-05
cam1:
  T_cam_imu:
  - [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556]
  - [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024]
  - [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038]
  - [0.0, 0.0, 0.0, 1.0]
  T_cn_cnm1:
  - [0.9999972564, 0.0023120, 0.0003418, -0.1100740]
  - [-0.0023171, 0.9998992, 0.0140211, 0.0003993]
  - [-0.0003094, -0.0140218, 0.9999016, -0.0008539]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [0]
  camera_model: pinhole
  distortion_coeffs: [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
    0.00020293673591811182]
  distortion_model: equidistant
  intrinsics: [457.587, 456.134, 379.999, 255.238]
  resolution: [752, 480]
  rostopic: /cam1/image_raw
  timeshift_cam_imu: 0.0
"""

KALIBR_IMU = """\
#Accelerometers
accelerometer_noise_density: 2.0000e-3   #Noise density (continuous-time)
accelerometer_random_walk:   3.0000e-3   #Bias random walk

#Gyroscopes
gyroscope_noise_density:     1.6968e-04   #Noise density (continuous-time)
gyroscope_random_walk:       1.9393e-05   #Bias random walk

rostopic:                    /imu0      #the IMU ROS topic
update_rate:                 200.0      #Hz (for discretization of the values above)
"""

KALIBR_TARGET = """\
target_type: 'aprilgrid' #gridtype
tagCols: 6               #number of apriltags
tagRows: 6               #number of apriltags
tagSize: 0.088           #size of apriltag, edge to edge [m]
tagSpacing: 0.3          #ratio of space between tags to tagSize
"""


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_reads_camchain_as_kalibr_writes_it(tmp_path: Path) -> None:
    cameras = read_camchain(_write(tmp_path, "camchain-imucam.yaml", KALIBR_CAMCHAIN))
    assert [c.name for c in cameras] == ["cam0", "cam1"]
    cam0, cam1 = cameras
    assert isinstance(cam0.camera, PinholeRadtan)
    assert cam0.camera.fx == 458.654 and cam0.camera.cy == 248.375
    assert cam0.camera.p2 == pytest.approx(1.76187114e-05)
    assert (cam0.camera.width, cam0.camera.height) == (752, 480)
    assert cam0.timeshift_cam_imu_s == pytest.approx(-8.121e-05)
    assert cam0.cam_from_imu[0, 3] == pytest.approx(-0.0216401454975)
    assert cam0.cam_overlaps == [1]
    np.testing.assert_allclose(cam0.imu_from_cam @ cam0.cam_from_imu, np.eye(4), atol=1e-9)
    assert isinstance(cam1.camera, PinholeEquidistant)
    assert cam1.camera.k4 == pytest.approx(0.00020293673591811182)
    assert cam1.topic == "/cam1/image_raw"


@pytest.mark.parametrize("count", [1, 3])
def test_camchain_round_trip(tmp_path: Path, count: int) -> None:
    rng = np.random.default_rng(count)
    cameras = []
    for index in range(count):
        model = PinholeRadtan if index % 2 == 0 else PinholeEquidistant
        camera = model(
            640 + index, 480, *rng.uniform(300, 600, 2), *rng.uniform(200, 400, 2),
            *rng.normal(0, 0.05, 4),
        )  # fmt: skip
        pose = make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 0.1)
        cameras.append(
            CameraCalibration(
                camera=camera,
                cam_from_imu=pose,
                timeshift_cam_imu_s=float(rng.normal() * 1e-5),
                topic=f"/oak/cam{index}: left #1",
                name=f"cam{index}",
                cam_overlaps=[i for i in range(count) if i != index],
            )
        )
    path = write_camchain(tmp_path / "calib" / "camchain.yaml", cameras)
    text = path.read_text()
    assert "# [fu, fv, pu, pv], pixels" in text
    loaded = read_camchain(path)
    assert len(loaded) == count
    for original, read in zip(cameras, loaded, strict=True):
        assert read.camera == original.camera  # exact: floats written with repr
        np.testing.assert_array_equal(read.cam_from_imu, original.cam_from_imu)
        assert read.timeshift_cam_imu_s == original.timeshift_cam_imu_s
        assert (read.topic, read.name, read.cam_overlaps) == (
            original.topic,
            original.name,
            original.cam_overlaps,
        )
    if count > 1:
        # T_cn_cnm1 is written consistently with the T_cam_imu pair.
        raw = yaml.safe_load(text)
        chained = np.array(raw["cam1"]["T_cn_cnm1"]) @ cameras[0].cam_from_imu
        np.testing.assert_allclose(chained, cameras[1].cam_from_imu, atol=1e-12)


def test_camchain_without_imu_chains_from_previous_camera(tmp_path: Path) -> None:
    data = yaml.safe_load(KALIBR_CAMCHAIN)
    for entry in data.values():
        entry.pop("T_cam_imu")
    cameras = read_camchain(_write(tmp_path, "camchain.yaml", yaml.safe_dump(data)))
    np.testing.assert_array_equal(cameras[0].cam_from_imu, np.eye(4))
    np.testing.assert_allclose(cameras[1].cam_from_imu, data["cam1"]["T_cn_cnm1"])


def test_small_floats_survive_pyyaml(tmp_path: Path) -> None:
    camera = PinholeRadtan(10, 10, 1.0, 1.0, 5.0, 5.0, 1e-05, -3e-20, 0.0, 2.5e-7)
    path = write_camchain(tmp_path / "c.yaml", [CameraCalibration(camera=camera)])
    assert read_camchain(path)[0].camera == camera


def test_write_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "camchain.yaml"
    calibration = CameraCalibration(camera=PinholeRadtan(10, 10, 1.0, 1.0, 5.0, 5.0))
    write_camchain(path, [calibration])
    with pytest.raises(OutputExistsError):
        write_camchain(path, [calibration])
    write_camchain(path, [calibration], overwrite=True)
    with pytest.raises(ValueError, match="at least one camera"):
        write_camchain(tmp_path / "empty.yaml", [])


def _broken(key: str, value: object) -> str:
    data = yaml.safe_load(KALIBR_CAMCHAIN)
    if value is None:
        data["cam1"].pop(key)
    else:
        data["cam1"][key] = value
    return yaml.safe_dump(data)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (_broken("intrinsics", [1.0, 2.0, 3.0]), "cam1: expected 'intrinsics' as 4 numbers"),
        (_broken("intrinsics", None), "cam1: expected 'intrinsics' as 4 numbers"),
        (_broken("intrinsics", [-1.0, 2.0, 3.0, 4.0]), "focal lengths"),
        (_broken("camera_model", None), "cam1: missing 'camera_model'"),
        (_broken("distortion_model", "fov"), "unsupported camera_model/distortion_model"),
        (_broken("camera_model", "omni"), "supported: pinhole\\+radtan"),
        (_broken("distortion_coeffs", [0.1, "x", 0.0, 0.0]), "'distortion_coeffs' as 4"),
        (_broken("resolution", [752.5, 480]), "'resolution' as 2 positive integers"),
        (_broken("resolution", [752]), "'resolution' as 2 positive integers"),
        (_broken("T_cam_imu", [[1, 0, 0, 0]] * 4), "'T_cam_imu' as a rigid transform"),
        (_broken("T_cam_imu", [[1, 0, 0]] * 4), "'T_cam_imu' as 4 rows of 4 numbers"),
        (
            _broken("T_cam_imu", [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
            "reflection",
        ),
        (_broken("timeshift_cam_imu", "soon"), "'timeshift_cam_imu' as a number"),
        (_broken("rostopic", 5), "'rostopic' as a string"),
        (_broken("cam_overlaps", "all"), "'cam_overlaps' as a list"),
        ("cam0: 5\n", "cam0: expected a mapping"),
        ("imu0: {}\n", "imu0: unexpected top-level key"),
        ("{}\n", "no cameras"),
        ("- a\n- b\n", "expected a YAML mapping"),
        ("cam0: [\n", "not valid YAML"),
    ],
)
def test_camchain_errors_name_file_camera_and_key(tmp_path: Path, text: str, message: str) -> None:
    path = _write(tmp_path, "camchain.yaml", text)
    with pytest.raises(InputError, match=message) as info:
        read_camchain(path)
    assert "camchain.yaml" in str(info.value)


def test_missing_and_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nothere\.yaml: no such file"):
        read_camchain(tmp_path / "nothere.yaml")
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match=r"binary\.yaml: cannot read"):
        read_imu_yaml(tmp_path / "binary.yaml")


def test_opencv_yaml_directive_and_dotless_exponents_are_accepted(tmp_path: Path) -> None:
    text = "%YAML:1.0\n" + KALIBR_CAMCHAIN.replace("1.76187114e-05", "1.76187114e-5")
    cameras = read_camchain(_write(tmp_path, "camchain.yaml", text))
    assert isinstance(cameras[0].camera, PinholeRadtan)
    assert cameras[0].camera.p2 == pytest.approx(1.76187114e-05)


def test_reads_imu_yaml_as_kalibr_writes_it(tmp_path: Path) -> None:
    noise = read_imu_yaml(_write(tmp_path, "imu.yaml", KALIBR_IMU))
    assert noise == ImuNoise(2.0e-3, 3.0e-3, 1.6968e-04, 1.9393e-05, 200.0, "/imu0")


def test_imu_round_trip(tmp_path: Path) -> None:
    noise = ImuNoise(1.1e-2, 4.3e-4, 1.87e-04, 2.66e-05, 397.5, topic="/gopro/imu")
    path = write_imu_yaml(tmp_path / "imu.yaml", noise)
    assert "rad/s/sqrt(Hz)" in path.read_text()
    assert read_imu_yaml(path) == noise
    with pytest.raises(OutputExistsError):
        write_imu_yaml(path, noise)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("gyroscope_random_walk:", "gyro_walk:", "missing 'gyroscope_random_walk'"),
        ("200.0", "-5", "'update_rate' must be positive"),
        ("2.0000e-3", "-1.0", "'accelerometer_noise_density' must not be negative"),
        ("1.6968e-04", "lots", "'gyroscope_noise_density' as a number"),
    ],
)
def test_imu_errors(tmp_path: Path, old: str, new: str, message: str) -> None:
    path = _write(tmp_path, "imu.yaml", KALIBR_IMU.replace(old, new))
    with pytest.raises(InputError, match=message) as info:
        read_imu_yaml(path)
    assert "imu.yaml" in str(info.value)


def test_reads_target_as_kalibr_writes_it(tmp_path: Path) -> None:
    target = read_target_yaml(_write(tmp_path, "april_6x6.yaml", KALIBR_TARGET))
    assert target == AprilGridTarget(6, 6, 0.088, 0.3, 0)


def test_target_round_trip(tmp_path: Path) -> None:
    target = AprilGridTarget(tag_rows=5, tag_cols=7, tag_size_m=0.0301, tag_spacing_ratio=0.25,
                             tag_id_offset=100)  # fmt: skip
    path = write_target_yaml(tmp_path / "target.yaml", target)
    assert yaml.safe_load(path.read_text())["target_type"] == "aprilgrid"
    assert read_target_yaml(path) == target
    with pytest.raises(OutputExistsError):
        write_target_yaml(path, target)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("'aprilgrid'", "'checkerboard'", "unsupported target_type 'checkerboard'"),
        ("tagCols: 6", "tagCols: 6.5", "'tagCols' as an integer >= 1"),
        ("tagRows: 6", "", "missing 'tagRows'"),
        ("tagSize: 0.088", "tagSize: -0.088", "must be positive"),
        ("tagSpacing: 0.3", "tagSpacing: wide", "'tagSpacing' as a number"),
        ("tagRows: 6", "tagRows: 6\ntagIdOffset: -1", "'tagIdOffset' as an integer >= 0"),
        ("tagRows: 6", "tagRows: 6\ntagIdOffset: 560", "outside the 36h11 family"),
        ("target_type: 'aprilgrid' #gridtype", "", "missing 'target_type'"),
    ],
)
def test_target_errors(tmp_path: Path, old: str, new: str, message: str) -> None:
    path = _write(tmp_path, "target.yaml", KALIBR_TARGET.replace(old, new))
    with pytest.raises(InputError, match=message) as info:
        read_target_yaml(path)
    assert "target.yaml" in str(info.value)


def test_non_finite_values_are_not_written(tmp_path: Path) -> None:
    noise = ImuNoise(float("nan"), 1.0, 1.0, 1.0, 200.0)
    with pytest.raises(ValueError, match="non-finite"):
        write_imu_yaml(tmp_path / "imu.yaml", noise)
    assert not (tmp_path / "imu.yaml").exists()
