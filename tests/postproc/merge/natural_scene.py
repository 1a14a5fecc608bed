"""A fast textured scene for natural-feature tests: two planes (a wall and the seabed).

Each "wreck" is a wall at y = 0 (normal +y) and a seabed at z = -3, both with a
random multi-scale texture drawn from `texture_seed`: two sessions filming the
same wreck share structure, a session filming a wreck with another seed shares
none. Cameras swim along the wall at y = `distance_m` looking at it; images are
rendered by ray casting at 320x240 (a few ms each).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.calibration.cameras import PinholeRadtan
from shared.geometry import invert_pose, make_pose, so3_exp
from shared.trajectory import Trajectory
from sim.targets import write_slam_folder

FloatArray = npt.NDArray[np.float64]
PIXELS_PER_M = 120.0
EXTENT_M = 12.0


def camera() -> PinholeRadtan:
    """A small camera with mild barrel distortion."""
    return PinholeRadtan(320, 240, 220.0, 220.0, 160.3, 119.6, -0.05, 0.01, 0.0, 0.0)


@cache
def texture(seed: int) -> npt.NDArray[np.float32]:
    """A (N, N) float texture of blobs at several scales (gray levels 0-255)."""
    import cv2

    rng = np.random.default_rng(seed)
    size = int(EXTENT_M * PIXELS_PER_M)
    out = np.zeros((size, size), dtype=np.float32)
    for cells, weight in ((12, 0.6), (48, 0.8), (192, 1.0), (480, 0.7)):
        low = rng.uniform(0, 1, size=(cells, cells)).astype(np.float32)
        out += weight * cv2.resize(low, (size, size), interpolation=cv2.INTER_CUBIC)
    out -= out.min()
    return np.asarray(255 * out / out.max(), dtype=np.float32)


def render(
    cam: PinholeRadtan,
    world_from_cam: FloatArray,
    textures: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]],
    rng: np.random.Generator,
) -> npt.NDArray[np.uint8]:
    """Grayscale image of the wall (y = 0, texture 0) and seabed (z = -3, texture 1)."""
    import cv2

    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    rays = cam.unproject(np.column_stack((u.ravel(), v.ravel())).astype(np.float64))
    directions = rays @ world_from_cam[:3, :3].T
    origin = world_from_cam[:3, 3]
    image = np.full(rays.shape[0], 90.0, dtype=np.float32)
    depth = np.full(rays.shape[0], np.inf)
    for axis, level, coords, tex in ((1, 0.0, (0, 2), textures[0]), (2, -3.0, (0, 1), textures[1])):
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (level - origin[axis]) / directions[:, axis]
        hit = np.isfinite(lam) & (lam > 0) & (lam < depth)
        points = origin + lam[:, None] * directions
        px = (points[:, coords[0]] + EXTENT_M / 2) * PIXELS_PER_M
        py = (points[:, coords[1]] + EXTENT_M / 2) * PIXELS_PER_M
        hit &= (px >= 0) & (py >= 0) & (px < tex.shape[1] - 1) & (py < tex.shape[0] - 1)
        if not np.any(hit):
            continue
        maps = np.zeros((2, rays.shape[0]), dtype=np.float32)
        maps[0, hit], maps[1, hit] = px[hit], py[hit]
        sampled = cv2.remap(
            tex, maps[0].reshape(cam.height, -1), maps[1].reshape(cam.height, -1), cv2.INTER_LINEAR
        ).reshape(-1)
        image[hit] = sampled[hit]
        depth[hit] = lam[hit]
    noisy = image.reshape(cam.height, cam.width) + rng.normal(0, 1.5, (cam.height, cam.width))
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def look_at_wall(x_m: float, distance_m: float, yaw_offset_rad: float) -> FloatArray:
    """`T_W_C` of a camera at (x, distance, -1.5) looking at the wall (-y), turned by yaw."""
    forward = np.array([np.sin(yaw_offset_rad), -np.cos(yaw_offset_rad), -0.25])
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_pose(np.column_stack((right, down, forward)), [x_m, distance_m, -1.5])


def write_session(
    folder: Path,
    *,
    texture_seeds: tuple[int, int],
    xs_m: FloatArray,
    distance_m: float,
    world_from_session: FloatArray,
    seed: int,
    start_ns: int = 1_700_000_000 * 10**9,
    jitter_rotation_deg: float = 0.03,
    jitter_translation_m: float = 0.003,
) -> Path:
    """A SLAM-like folder: keyframes at 1 s along the wall, poses in the session frame
    with small per-keyframe noise, trajectory.tum starting at the first keyframe."""
    rng = np.random.default_rng(seed)
    cam = camera()
    textures = (texture(texture_seeds[0]), texture(texture_seeds[1]))
    stamps, poses, images = [], [], []
    session_from_world = invert_pose(world_from_session)
    for i, x in enumerate(xs_m):
        world_from_cam = look_at_wall(float(x), distance_m, 0.15 * np.sin(0.7 * i))
        images.append(render(cam, world_from_cam, textures, rng))
        noise = make_pose(
            so3_exp(rng.normal(0, np.deg2rad(jitter_rotation_deg), 3)),
            rng.normal(0, jitter_translation_m, 3),
        )
        session_from_cam = session_from_world @ world_from_cam
        session_from_cam[:3, :3] = noise[:3, :3] @ session_from_cam[:3, :3]
        session_from_cam[:3, 3] += noise[:3, 3]
        poses.append(session_from_cam)
        stamps.append(start_ns + i * 10**9)
    write_slam_folder(folder, cam, stamps, np.array(poses), images)
    from shared.formats.tum import write_tum

    write_tum(folder / "trajectory.tum", Trajectory(np.array(stamps), np.array(poses)))
    return folder
