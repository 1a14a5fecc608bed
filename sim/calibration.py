"""Calibration recordings with exact truth, rendered by the survey simulator's renderer.

A single AprilGrid board in an empty scene (the simulator's renderer and IMU model, not
the wreck): `board_views` gives well-spread still views for intrinsics; `recording`
gives a hand-held sweep in front of the board as camera frames (camera clock) plus a
200 Hz IMU (true time) with a known `cam_from_imu` and Kalibr time shift
(t_imu = t_cam + shift); `two_gyros` gives two rigs' gyros on one motion, each on its
own clock. Tests and the bench import this; postproc code never does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.cameras import CameraModel, PinholeEquidistant, PinholeRadtan
from shared.clock import NS_PER_S, ns_from_seconds, seconds_from_ns
from shared.geometry import look_at, so3_exp
from sim.imu import simulate_imu
from sim.render import Renderer, WaterModel
from sim.scene import TargetPlacement, WreckScene
from sim.spline import SplineTrajectory
from sim.survey import default_cam_from_imu, default_camera, default_imu_noise

FloatArray = npt.NDArray[np.float64]

TARGET = AprilGridTarget(tag_rows=6, tag_cols=6, tag_size_m=0.088, tag_spacing_ratio=0.3)
START_NS = 1_700_000_000_000_000_000


def radtan_camera(width: int = 640, height: int = 480) -> PinholeRadtan:
    """A GoPro-like wide camera with barrel distortion (about 80 degrees across)."""
    return default_camera(width, height, focal_per_width=0.6, fy_per_fx=1.002, k1=-0.20, k2=0.045)


def equidistant_camera(width: int = 640, height: int = 480) -> PinholeEquidistant:
    """A fisheye-like camera (Kannala-Brandt), about 110 degrees across."""
    f = 0.36 * width
    return PinholeEquidistant(
        width=width,
        height=height,
        fx=f,
        fy=f,
        cx=(width - 1) / 2.0 + 0.008 * width,
        cy=(height - 1) / 2.0 + 0.006 * height,
        k1=0.03,
        k2=-0.01,
        k3=0.004,
        k4=-0.001,
    )


def board_scene(target: AprilGridTarget = TARGET) -> WreckScene:
    """The board in the plane z = 0 of the world, printed side facing +z, on a grey floor."""
    floor = np.full((2, 2, 3), 90, dtype=np.uint8)
    return WreckScene(
        boxes=[],
        seafloor_z_m=-3.0,
        targets=[TargetPlacement("board", target, np.eye(4))],
        textures=[floor],
        texel_m=[1.0],
    )


def board_centre(target: AprilGridTarget = TARGET) -> FloatArray:
    width, height = target.extent_m
    return np.array([width / 2.0, height / 2.0, 0.0])


def _view_rotation(eye: FloatArray, point: FloatArray, roll_rad: float) -> FloatArray:
    """`world_from_cam` rotation: camera z from `eye` towards `point`, then rolled."""
    base = look_at(eye, point, up=(0.0, 1.0, 0.0))[:3, :3]
    rotation: FloatArray = base @ so3_exp(np.array([0.0, 0.0, roll_rad]))
    return rotation


def _random_view(
    rng: np.random.Generator, distance_m: tuple[float, float] = (0.45, 0.9)
) -> FloatArray:
    """A camera pose looking at the board from `distance_m`, tilted up to ~50 degrees."""
    centre = board_centre()
    tilt = np.deg2rad(rng.uniform(0.0, 50.0))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    distance = rng.uniform(*distance_m)
    direction = np.array(
        [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
    )
    eye = centre + distance * direction
    # Aim off-centre so the board lands in different parts of the image.
    aim = centre + np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.2, 0.2), 0.0])
    pose = np.eye(4)
    pose[:3, :3] = _view_rotation(eye, aim, rng.uniform(-0.6, 0.6))
    pose[:3, 3] = eye
    return pose


def board_views(
    camera: CameraModel,
    count: int,
    *,
    seed: int,
    noise: bool = True,
    distance_m: tuple[float, float] = (0.45, 0.9),
) -> tuple[list[npt.NDArray[np.uint8]], list[FloatArray]]:
    """`count` grey images of the board from random poses, and their `world_from_cam`."""
    rng = np.random.default_rng(seed)
    water = WaterModel.clear()
    if noise:
        water.read_noise_dn = 1.5
    renderer = Renderer(board_scene(), camera, water, target_supersampling=3)
    images, poses = [], []
    for _ in range(count):
        pose = _random_view(rng, distance_m)
        frame = renderer.render(pose, rng=rng)
        images.append(np.ascontiguousarray(frame.image_rgb[:, :, 1]))
        poses.append(pose)
    return images, poses


@dataclass
class Recording:
    """A simulated hand-held sweep: frames on the camera clock, IMU on true time."""

    camera: CameraModel
    cam_from_imu: FloatArray
    timeshift_cam_imu_s: float
    frame_stamps_ns: npt.NDArray[np.int64]
    images: list[npt.NDArray[np.uint8]]
    world_from_cam: FloatArray
    imu_stamps_ns: npt.NDArray[np.int64]
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    trajectory: SplineTrajectory


def sweep_trajectory(
    rng: np.random.Generator,
    cam_from_imu: FloatArray,
    *,
    duration_s: float,
    knot_interval_s: float = 0.25,
    start_ns: int = START_NS,
) -> SplineTrajectory:
    """Body (IMU) poses whose camera keeps the board in view while turning about all axes."""
    order = 6
    count = int(np.ceil(duration_s / knot_interval_s)) + order + 2
    centre = board_centre()
    positions = np.zeros((count, 3))
    rotations = np.zeros((count, 3, 3))
    # A slow random walk of viewpoint, aim and roll: rates of about 1 rad/s, as by hand.
    azimuth = rng.uniform(0.0, 2 * np.pi)
    roll = 0.0
    for i in range(count):
        azimuth += rng.uniform(0.2, 0.6)
        roll = float(np.clip(roll + rng.normal(0.0, 0.25), -0.7, 0.7))
        tilt = np.deg2rad(rng.uniform(10.0, 40.0))
        distance = rng.uniform(0.55, 0.8)
        eye = centre + distance * np.array(
            [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
        )
        aim = centre + np.array([rng.uniform(-0.12, 0.12), rng.uniform(-0.1, 0.1), 0.0])
        positions[i] = eye
        # world_from_body = world_from_cam @ cam_from_body (the lever arm is a few cm).
        rotations[i] = _view_rotation(eye, aim, roll) @ cam_from_imu[:3, :3]
    start = start_ns - ns_from_seconds(2 * knot_interval_s)
    return SplineTrajectory(
        start_ns=start,
        knot_interval_s=knot_interval_s,
        position_ctrl_m=positions,
        rotation_ctrl=rotations,
        order=order,
    )


def recording(
    *,
    seed: int,
    duration_s: float = 6.0,
    fps: float = 30.0,
    timeshift_cam_imu_s: float = 0.0237,
    camera: CameraModel | None = None,
    imu_noise: bool = True,
    render: bool = True,
) -> Recording:
    """A sweep in front of the board: frames at `fps` on the camera clock, IMU at 200 Hz.

    A frame stamped t_cam was exposed at true time t_cam + `timeshift_cam_imu_s`; the IMU
    is stamped in true time (Kalibr's t_imu = t_cam + shift). With `render=False` the
    images list is empty (poses only, for the pure-math tests).
    """
    rng = np.random.default_rng(seed)
    camera = camera or radtan_camera(480, 360)
    cam_from_imu = default_cam_from_imu()
    trajectory = sweep_trajectory(rng, cam_from_imu, duration_s=duration_s + 1.0)
    imu_from_cam = np.linalg.inv(cam_from_imu)
    frame_count = int(duration_s * fps)
    shift_ns = ns_from_seconds(timeshift_cam_imu_s)
    frame_stamps = START_NS + ns_from_seconds(np.arange(frame_count) / fps)
    world_from_body = trajectory.world_from_body(frame_stamps + shift_ns)
    world_from_cam = world_from_body @ imu_from_cam
    imu_stamps = START_NS - 200_000_000 + np.arange(int((duration_s + 0.4) * 200)) * 5_000_000
    noise = default_imu_noise(200.0) if imu_noise else None
    samples = simulate_imu(
        trajectory,
        imu_stamps.astype(np.int64),
        noise=noise,
        rng=rng,
        gyro_bias0_rad_s=(0.004, -0.003, 0.002) if imu_noise else (0.0, 0.0, 0.0),
    )
    images: list[npt.NDArray[np.uint8]] = []
    if render:
        water = WaterModel.clear()
        water.read_noise_dn = 1.5
        renderer = Renderer(board_scene(), camera, water, target_supersampling=2)
        for pose in world_from_cam:
            images.append(np.ascontiguousarray(renderer.render(pose, rng=rng).image_rgb[:, :, 1]))
    return Recording(
        camera=camera,
        cam_from_imu=cam_from_imu,
        timeshift_cam_imu_s=seconds_from_ns(shift_ns),
        frame_stamps_ns=frame_stamps,
        images=images,
        world_from_cam=world_from_cam,
        imu_stamps_ns=samples.stamps_ns,
        gyro_rad_s=samples.gyro_rad_s,
        accel_m_s2=samples.accel_m_s2,
        trajectory=trajectory,
    )


def two_gyros(
    seed: int, offset_s: float, duration_s: float = 20.0, duration1_s: float | None = None
) -> tuple[npt.NDArray[np.int64], FloatArray, npt.NDArray[np.int64], FloatArray, FloatArray]:
    """Two rigs' gyros on one hand-held sweep: rig 0 at 200 Hz on true time; rig 1 at 197 Hz
    starting 1 s later for `duration1_s` (default `duration_s` - 2 s), rotated, on a clock
    `offset_s` ahead.

    Returns (stamps0 ns, gyro0 (N,3) rad/s, stamps1 ns, gyro1 (M,3) rad/s in rig 1's frame,
    the true `imu1_from_imu0` rotation).
    """
    rng = np.random.default_rng(seed)
    trajectory = sweep_trajectory(rng, default_cam_from_imu(), duration_s=duration_s + 5.0)
    true0 = START_NS + np.arange(int(duration_s * 200)) * 5_000_000
    imu0 = simulate_imu(trajectory, true0, noise=default_imu_noise(200.0), rng=rng)
    true1 = (
        START_NS
        + NS_PER_S
        + ns_from_seconds(np.arange(int((duration1_s or duration_s - 2.0) * 197)) / 197.0)
    )
    imu1 = simulate_imu(
        trajectory,
        true1,
        noise=default_imu_noise(197.0),
        rng=rng,
        gyro_bias0_rad_s=(0.01, 0.0, -0.01),
    )
    imu1_from_imu0 = so3_exp(rng.normal(0.0, 1.0, 3))
    stamps1 = true1 + ns_from_seconds(offset_s)
    return true0, imu0.gyro_rad_s, stamps1, imu1.gyro_rad_s @ imu1_from_imu0.T, imu1_from_imu0
