"""A tiny EuRoC folder rendered from a textured wall, with IMU and ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.calibration.kalibr import CameraCalibration, ImuNoise
from shared.formats.euroc import EurocWriter
from shared.geometry import invert_pose
from shared.trajectory import Trajectory
from sim.features import (
    DiverMotion,
    SyntheticOptions,
    WallRenderer,
    default_camera,
    default_imu_from_cam,
    make_wall_texture,
    sequence_imu,
)


def write_wall_euroc(
    folder: Path, *, duration_s: float, fps: float, scale: float, seed: int
) -> Path:
    """Render `duration_s` of the default diver motion in front of a wall into `folder`."""
    motion = DiverMotion()
    camera = default_camera().scaled(scale)
    imu_from_cam = default_imu_from_cam()
    options = SyntheticOptions(seed=seed)
    rng = np.random.default_rng(seed)
    renderer = WallRenderer(camera, make_wall_texture(rng))
    frame_dt_ns = round(1e9 / fps)
    frames = motion.start_ns + np.arange(0, round(duration_s * 1e9), frame_dt_ns, dtype=np.int64)
    imu_dt_ns = round(1e9 / options.imu_rate_hz)
    imu_stamps = motion.start_ns + np.arange(
        -40 * imu_dt_ns, round(duration_s * 1e9) + 40 * imu_dt_ns, imu_dt_ns, dtype=np.int64
    )
    imu = sequence_imu(motion, imu_stamps, options, rng)
    noise = ImuNoise(
        accelerometer_noise_density=options.accelerometer_noise_density,
        accelerometer_random_walk=options.accelerometer_random_walk,
        gyroscope_noise_density=options.gyroscope_noise_density,
        gyroscope_random_walk=options.gyroscope_random_walk,
        update_rate_hz=options.imu_rate_hz,
    )
    calibration = CameraCalibration(camera=camera, cam_from_imu=invert_pose(imu_from_cam))
    world_from_body = motion.world_from_body(frames)
    with EurocWriter(folder, camera=calibration, imu_noise=noise) as writer:
        for stamp, T_W_B in zip(frames, world_from_body, strict=True):
            writer.add_image(int(stamp), renderer.render(T_W_B @ imu_from_cam))
        writer.add_imu(imu.stamps_ns, imu.gyro_rad_s, imu.accel_m_s2)
        writer.set_groundtruth(Trajectory(frames, world_from_body))
    return folder


@pytest.fixture(scope="session")
def wall_euroc(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 s at 10 fps, 320x180 px: enough for the visual-inertial start and a few keyframes."""
    folder = tmp_path_factory.mktemp("slam") / "wall_euroc"
    return write_wall_euroc(folder, duration_s=8.0, fps=10.0, scale=1 / 3, seed=11)
