"""Feature-level simulation of a diver survey: landmarks on planes, tracks, IMU.

Pure math, no I/O. Used by the tests and the benchmark to exercise the
backend with known truth, without rendering images. The world frame W is
gravity-aligned (z up, gravity (0, 0, -9.81)).

The diver swims along the starboard side of a hull (a wall at y = 3.5 m
above a seafloor at z = -17 m), facing the wall, bobbing and swaying as
divers do. Body B = IMU frame (x forward, y left, z up); the camera looks
forward (`T_B_C` below). The trajectory is a sum of sinusoids with a
constant drift, so velocity, acceleration and the body angular rate are
exact (no finite differences) and the simulated IMU is consistent with the
poses to machine precision (`sim.imu.simulate_imu` on the same motion).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from postproc.slam.types import FrameTracks
from shared.calibration.cameras import PinholeRadtan
from shared.calibration.kalibr import ImuNoise
from shared.clock import NS_PER_S, ns_from_seconds, seconds_from_ns
from shared.geometry import invert_pose, make_pose
from sim.imu import RandomBias, SimulatedImu, simulate_imu

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def _rot_x(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((*np.shape(a), 3, 3))
    R[..., 0, 0] = 1.0
    R[..., 1, 1], R[..., 1, 2], R[..., 2, 1], R[..., 2, 2] = c, -s, s, c
    return R


def _rot_y(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((*np.shape(a), 3, 3))
    R[..., 1, 1] = 1.0
    R[..., 0, 0], R[..., 0, 2], R[..., 2, 0], R[..., 2, 2] = c, s, -s, c
    return R


def _rot_z(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((*np.shape(a), 3, 3))
    R[..., 2, 2] = 1.0
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    return R


@dataclass(kw_only=True)
class Sinusoids:
    """f(t) = offset + rate * t + sum_k amp_k sin(freq_k t + phase_k) (t in s, freq in rad/s)."""

    offset: float = 0.0
    rate: float = 0.0
    amplitudes: tuple[float, ...] = ()
    frequencies_rad_s: tuple[float, ...] = ()
    phases_rad: tuple[float, ...] = ()

    def __call__(self, t_s: FloatArray, derivative: int = 0) -> FloatArray:
        t = np.asarray(t_s, dtype=np.float64)
        if derivative == 0:
            out = self.offset + self.rate * t
        elif derivative == 1:
            out = np.full_like(t, self.rate)
        else:
            out = np.zeros_like(t)
        for a, w, p in zip(self.amplitudes, self.frequencies_rad_s, self.phases_rad, strict=True):
            # d^n/dt^n sin(wt + p) = w^n sin(wt + p + n pi/2)
            out = out + a * w**derivative * np.sin(w * t + p + derivative * np.pi / 2)
        return out


@dataclass(kw_only=True)
class DiverMotion:
    """A smooth diver trajectory `T_W_B(t)`: positions and Z-Y-X Euler angles as sinusoids.

    R_W_B = Rz(yaw) Ry(pitch) Rx(roll); positive pitch tips the body's x axis
    (forward) downwards. Times are seconds from `start_ns`.
    """

    start_ns: int = 1_700_000_000_000_000_000
    x: Sinusoids = field(
        default_factory=lambda: Sinusoids(
            offset=-4.5, rate=0.3, amplitudes=(0.5,), frequencies_rad_s=(0.27,), phases_rad=(0.0,)
        )
    )
    y: Sinusoids = field(
        default_factory=lambda: Sinusoids(
            offset=6.0, amplitudes=(0.5, 0.1), frequencies_rad_s=(0.31, 1.3), phases_rad=(0.3, 0.0)
        )
    )
    z: Sinusoids = field(
        default_factory=lambda: Sinusoids(
            offset=-14.0,
            amplitudes=(0.4, 0.1),
            frequencies_rad_s=(0.45, 1.1),
            phases_rad=(1.0, 0.5),
        )
    )
    yaw: Sinusoids = field(
        default_factory=lambda: Sinusoids(
            offset=-np.pi / 2, amplitudes=(0.25,), frequencies_rad_s=(0.3,), phases_rad=(0.0,)
        )
    )
    pitch: Sinusoids = field(
        default_factory=lambda: Sinusoids(
            offset=0.35, amplitudes=(0.1,), frequencies_rad_s=(0.5,), phases_rad=(0.5,)
        )
    )
    roll: Sinusoids = field(
        default_factory=lambda: Sinusoids(
            amplitudes=(0.05, 0.02), frequencies_rad_s=(0.7, 2.0), phases_rad=(0.0, 1.0)
        )
    )

    def _t(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        return seconds_from_ns(np.asarray(stamps_ns, dtype=np.int64) - self.start_ns)

    def rotation(self, stamps_ns: IntArray) -> FloatArray:
        """(N, 3, 3) rotations `R_W_B` at the stamps (int64 ns)."""
        t = self._t(stamps_ns)
        rotation: FloatArray = _rot_z(self.yaw(t)) @ _rot_y(self.pitch(t)) @ _rot_x(self.roll(t))
        return rotation

    def world_from_body(self, stamps_ns: IntArray) -> FloatArray:
        """(N, 4, 4) poses `T_W_B` at the stamps (int64 ns)."""
        t = self._t(stamps_ns)
        p = np.stack([self.x(t), self.y(t), self.z(t)], axis=-1)
        return make_pose(self.rotation(stamps_ns), p)

    def rotation_and_rate(self, stamps_ns: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """`R_W_B` (N, 3, 3) and the body angular rate (N, 3) rad/s (`sim.imu.ImuMotion`)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        return self.rotation(stamps), self.angular_rate_body_rad_s(stamps)

    def velocity_m_s(self, stamps_ns: IntArray) -> FloatArray:
        """(N, 3) velocity in W (m/s)."""
        t = self._t(stamps_ns)
        return np.stack([self.x(t, 1), self.y(t, 1), self.z(t, 1)], axis=-1)

    def acceleration_m_s2(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """(N, 3) acceleration in W (m/s^2), gravity not included."""
        t = self._t(stamps_ns)
        return np.stack([self.x(t, 2), self.y(t, 2), self.z(t, 2)], axis=-1)

    def angular_rate_body_rad_s(self, stamps_ns: IntArray) -> FloatArray:
        """(N, 3) body angular velocity in B (rad/s): the Z-Y-X Euler kinematics."""
        t = self._t(stamps_ns)
        roll, pitch = self.roll(t), self.pitch(t)
        droll, dpitch, dyaw = self.roll(t, 1), self.pitch(t, 1), self.yaw(t, 1)
        wx = droll - dyaw * np.sin(pitch)
        wy = dpitch * np.cos(roll) + dyaw * np.sin(roll) * np.cos(pitch)
        wz = -dpitch * np.sin(roll) + dyaw * np.cos(roll) * np.cos(pitch)
        return np.stack([wx, wy, wz], axis=-1)


def default_camera() -> PinholeRadtan:
    """A GoPro-like wide camera at the frontend width of 960 px (about 94 deg across)."""
    return PinholeRadtan(960, 540, 450.0, 450.0, 479.5, 269.5, k1=-0.05, k2=0.01)


def default_imu_from_cam() -> FloatArray:
    """`T_B_C`: camera looking along body +x, 3 cm ahead of and 2 cm above the IMU."""
    # Columns are the camera axes in B: x right = -y_B, y down = -z_B, z forward = x_B.
    R_B_C = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return make_pose(R_B_C, [0.03, 0.0, 0.02])


def wreck_side_landmarks(rng: np.random.Generator, *, density_per_m2: float = 12.0) -> FloatArray:
    """(N, 3) points in W on a hull wall (y = 3.5 m) and the seafloor in front of it (z = -17)."""
    wall_area = 40.0 * 4.85
    floor_area = 40.0 * 8.5
    n_wall = int(wall_area * density_per_m2)
    n_floor = int(floor_area * density_per_m2 * 0.6)
    wall = np.column_stack(
        [
            rng.uniform(-20.0, 20.0, n_wall),
            np.full(n_wall, 3.5),
            rng.uniform(-17.0, -12.15, n_wall),
        ]
    )
    floor = np.column_stack(
        [
            rng.uniform(-20.0, 20.0, n_floor),
            rng.uniform(3.5, 12.0, n_floor),
            np.full(n_floor, -17.0),
        ]
    )
    return np.vstack([wall, floor])


@dataclass(kw_only=True)
class SyntheticOptions:
    """Settings of a feature-level sequence.

    duration_s: length; frame_rate_hz / imu_rate_hz: sensor rates.
    pixel_noise_px: Gaussian noise on every tracked position (pixels).
    outlier_fraction: share of observations replaced by a random pixel.
    gyro/accel noise densities and random walks (continuous time, Kalibr units).
    gyro_bias_rad_s / accel_bias_m_s2: initial biases (random direction, this norm).
    max_range_m: landmarks farther than this are not seen (turbid water).
    seed: everything random derives from it.
    """

    duration_s: float = 30.0
    frame_rate_hz: float = 30.0
    imu_rate_hz: float = 200.0
    pixel_noise_px: float = 0.5
    outlier_fraction: float = 0.0
    gyroscope_noise_density: float = 2.0e-4
    gyroscope_random_walk: float = 2.0e-5
    accelerometer_noise_density: float = 2.0e-3
    accelerometer_random_walk: float = 3.0e-4
    gyro_bias_rad_s: float = 0.003
    accel_bias_m_s2: float = 0.05
    max_range_m: float = 8.0
    landmark_density_per_m2: float = 12.0
    seed: int = 0

    def imu_noise(self) -> ImuNoise:
        """The Kalibr noise model of the simulated IMU."""
        return ImuNoise(
            accelerometer_noise_density=self.accelerometer_noise_density,
            accelerometer_random_walk=self.accelerometer_random_walk,
            gyroscope_noise_density=self.gyroscope_noise_density,
            gyroscope_random_walk=self.gyroscope_random_walk,
            update_rate_hz=self.imu_rate_hz,
        )


@dataclass
class SyntheticSequence:
    """A simulated sequence: per-frame tracks, IMU samples (with their true biases), truth."""

    frames: list[FrameTracks]
    imu: SimulatedImu
    camera: PinholeRadtan
    imu_from_cam: FloatArray
    world_from_body: FloatArray  # (F, 4, 4) truth at the frame stamps
    frame_stamps_ns: IntArray
    landmarks_w: FloatArray
    options: SyntheticOptions
    frame_landmarks: list[IntArray]  # per frame, the landmark index of each track

    @property
    def accel_bias_m_s2(self) -> FloatArray:
        """(M, 3) true accelerometer bias at each IMU sample."""
        return self.imu.accel_bias_m_s2

    @property
    def gyro_bias_rad_s(self) -> FloatArray:
        """(M, 3) true gyro bias at each IMU sample."""
        return self.imu.gyro_bias_rad_s

    def imu_noise(self) -> ImuNoise:
        """The Kalibr noise model the IMU was simulated with."""
        return self.options.imu_noise()


def sequence_imu(
    motion: DiverMotion, stamps_ns: IntArray, options: SyntheticOptions, rng: np.random.Generator
) -> SimulatedImu:
    """The IMU of a feature-level sequence: `sim.imu.simulate_imu` with the options' noise,
    initial biases of the options' norms in random directions, the walks one step in."""
    return simulate_imu(
        motion,
        stamps_ns,
        noise=options.imu_noise(),
        rng=rng,
        gyro_bias0_rad_s=RandomBias(options.gyro_bias_rad_s),
        accel_bias0_m_s2=RandomBias(options.accel_bias_m_s2),
        walk_before_first=True,
    )


def simulate_sequence(
    options: SyntheticOptions | None = None, *, motion: DiverMotion | None = None
) -> SyntheticSequence:
    """Project landmarks into every frame and simulate the IMU along `motion`.

    A landmark gets a fresh track id each time it comes back into view (a
    frame-to-frame tracker does not recognise it), so long-term data
    association is not given away.
    """
    options = options or SyntheticOptions()
    motion = motion or DiverMotion()
    rng = np.random.default_rng(options.seed)
    camera = default_camera()
    imu_from_cam = default_imu_from_cam()
    landmarks = wreck_side_landmarks(rng, density_per_m2=options.landmark_density_per_m2)

    frame_dt_ns = round(NS_PER_S / options.frame_rate_hz)
    imu_dt_ns = round(NS_PER_S / options.imu_rate_hz)
    duration_ns = ns_from_seconds(options.duration_s)
    frame_stamps = motion.start_ns + np.arange(0, duration_ns + 1, frame_dt_ns, dtype=np.int64)
    # IMU starts a little before the first frame and ends after the last, as recorders do.
    imu_stamps = motion.start_ns + np.arange(
        -50 * imu_dt_ns, duration_ns + 50 * imu_dt_ns, imu_dt_ns, dtype=np.int64
    )
    imu = sequence_imu(motion, imu_stamps, options, rng)

    world_from_body = motion.world_from_body(frame_stamps)
    cam_from_world = invert_pose(world_from_body @ imu_from_cam)
    current_track = np.full(len(landmarks), -1, dtype=np.int64)
    next_id = 0
    frames: list[FrameTracks] = []
    frame_landmarks: list[IntArray] = []
    size = (camera.width, camera.height)
    for stamp, T_C_W in zip(frame_stamps, cam_from_world, strict=True):
        p_c = landmarks @ T_C_W[:3, :3].T + T_C_W[:3, 3]
        depth = p_c[:, 2]
        ahead = (depth > 0.2) & (np.linalg.norm(p_c, axis=1) < options.max_range_m)
        pix = np.full((len(landmarks), 2), np.nan)
        pix[ahead] = camera.project(p_c[ahead])
        visible = (
            ahead
            & (pix[:, 0] >= 0.0)
            & (pix[:, 0] <= camera.width - 1.0)
            & (pix[:, 1] >= 0.0)
            & (pix[:, 1] <= camera.height - 1.0)
        )
        lost = ~visible & (current_track >= 0)
        current_track[lost] = -1
        new = visible & (current_track < 0)
        current_track[new] = next_id + np.arange(int(new.sum()))
        next_id += int(new.sum())
        idx = np.flatnonzero(visible)
        measured = pix[idx] + rng.normal(size=(len(idx), 2)) * options.pixel_noise_px
        if options.outlier_fraction > 0:
            bad = rng.random(len(idx)) < options.outlier_fraction
            measured[bad] = rng.uniform(
                [0, 0], [camera.width - 1, camera.height - 1], size=(int(bad.sum()), 2)
            )
        measured = np.clip(measured, 0.0, [camera.width - 1.0, camera.height - 1.0])
        xy = camera.unproject(measured)[:, :2]
        ok = np.all(np.isfinite(xy), axis=1)
        frame_landmarks.append(idx[ok].astype(np.int64))
        frames.append(
            FrameTracks(
                stamp_ns=int(stamp),
                track_ids=current_track[idx][ok],
                xy_normalised=xy[ok],
                pixels=measured[ok],
                image_size=size,
            )
        )
    return SyntheticSequence(
        frames=frames,
        imu=imu,
        camera=camera,
        imu_from_cam=imu_from_cam,
        world_from_body=world_from_body,
        frame_stamps_ns=frame_stamps,
        landmarks_w=landmarks,
        options=options,
        frame_landmarks=frame_landmarks,
    )


# ------------------------------------------------------------------------- rendered images


@dataclass
class WallTexture:
    """A grey texture on the plane y = `plane_y_m` of W, texel (0, 0) at (x_min_m, z_max_m).

    Columns run along +x, rows along -z, `texel_m` metres per texel.
    """

    image: npt.NDArray[np.float32]
    texel_m: float
    x_min_m: float = -20.0
    z_max_m: float = -11.0
    plane_y_m: float = 3.5


def make_wall_texture(
    rng: np.random.Generator, *, texel_m: float = 0.01, width_m: float = 40.0, height_m: float = 7.0
) -> WallTexture:
    """Rusty-plate-like multi-scale noise (features from centimetres to a metre), 0..255."""
    rows, cols = round(height_m / texel_m), round(width_m / texel_m)
    total = np.zeros((rows, cols), dtype=np.float32)
    for cell_m, weight in ((1.0, 0.6), (0.25, 0.8), (0.06, 1.0), (0.02, 0.7)):
        cell = max(cell_m / texel_m, 1.0)
        grid = rng.uniform(-1, 1, size=(int(rows / cell) + 3, int(cols / cell) + 3))
        big = cv2.resize(
            grid.astype(np.float32),
            (round(grid.shape[1] * cell), round(grid.shape[0] * cell)),
            interpolation=cv2.INTER_CUBIC,
        )
        total += weight * big[:rows, :cols]
    total = (total - total.min()) / (total.max() - total.min())
    return WallTexture(image=(40.0 + 190.0 * total).astype(np.float32), texel_m=texel_m)


class WallRenderer:
    """Renders what `camera` sees of a textured wall from a pose `T_W_C` (grey uint8)."""

    def __init__(self, camera: PinholeRadtan, texture: WallTexture) -> None:
        self.camera = camera
        self.texture = texture
        u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
        pixels = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
        self._rays = camera.unproject(pixels)

    def render(self, world_from_cam: FloatArray) -> npt.NDArray[np.uint8]:
        """The image (height, width) uint8; background (no wall) is dark blue-grey 30."""
        t = self.texture
        rays_w = self._rays @ world_from_cam[:3, :3].T
        centre = world_from_cam[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (t.plane_y_m - centre[1]) / rays_w[:, 1]
        hit = np.isfinite(s) & (s > 0)
        s = np.where(hit, s, 0.0)
        points = centre + s[:, None] * rays_w
        col = ((points[:, 0] - t.x_min_m) / t.texel_m).astype(np.float32)
        row = ((t.z_max_m - points[:, 2]) / t.texel_m).astype(np.float32)
        col[~hit] = -10.0
        row[~hit] = -10.0
        shape = (self.camera.height, self.camera.width)
        image = cv2.remap(
            t.image,
            col.reshape(shape),
            row.reshape(shape),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=30.0,
        )
        return np.clip(image, 0, 255).astype(np.uint8)
