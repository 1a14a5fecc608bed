"""Synthetic AprilGrid views and SLAM-like result folders: surveys for the merge stage.

`render_view` ray-casts every pixel of a camera (distortion included,
through `CameraModel.unproject`) onto the planes of one or more targets and
samples their printed textures, so tag corners land exactly where the camera
model projects them. Blur, contrast loss and noise imitate murky water.

`write_slam_folder` writes the part of the SLAM result folder contract that
merging reads: `keyframes.tum` (camera poses `T_S_C`), `keyframes/<ns>.png`
and `calib/camchain.yaml`.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Protocol, cast

import numpy as np
import numpy.typing as npt

from shared.calibration.aprilgrid import (
    AprilGridTarget,
    render_target_texture,
    texture_pixel_from_target,
)
from shared.calibration.cameras import CameraModel, PinholeRadtan
from shared.calibration.kalibr import CameraCalibration
from shared.clock import ns_from_seconds
from shared.folders import SlamFolder
from shared.geometry import invert_pose, look_at, make_pose
from shared.trajectory import Trajectory

FloatArray = npt.NDArray[np.float64]


def default_camera() -> PinholeRadtan:
    """A GoPro-like wide camera at SVIn2's 960x540 with strong barrel distortion."""
    return PinholeRadtan(960, 540, 560.0, 560.0, 481.3, 268.7, -0.24, 0.06, 0.0008, -0.0005)


@dataclass(frozen=True)
class PlacedTarget:
    """A target and its pose in the rendering frame (`T_X_m`, 4x4, metres)."""

    target: AprilGridTarget
    frame_from_target: FloatArray


@cache
def _texture(target: AprilGridTarget, pixels_per_m: float) -> npt.NDArray[np.uint8]:
    return render_target_texture(target, pixels_per_m)


class _HashableCamera(CameraModel, Hashable, Protocol):
    """A camera model that can be a cache key (the models are frozen dataclasses)."""


@cache
def _rays(camera: _HashableCamera) -> FloatArray:
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    pixels = np.column_stack((u.ravel(), v.ravel())).astype(np.float64)
    return camera.unproject(pixels)


def render_view(
    camera: CameraModel,
    frame_from_cam: FloatArray,
    targets: Sequence[PlacedTarget],
    *,
    rng: np.random.Generator,
    noise_sigma: float = 2.0,
    blur_sigma_px: float = 0.6,
    ink_level: float = 40.0,
    paper_level: float = 200.0,
    pixels_per_m: float | None = None,
) -> npt.NDArray[np.uint8]:
    """An 8-bit grayscale image (height, width) of `targets` seen from `T_X_C`.

    The background is smooth random gray; the targets are printed with
    `ink_level` black and `paper_level` white (gray levels).
    """
    import cv2

    h, w = camera.height, camera.width
    low = rng.uniform(60, 140, size=(max(h // 60, 2), max(w // 60, 2)))
    image = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    depth = np.full(h * w, np.inf)
    # mypy does not count a Protocol type as Hashable; every camera model is.
    rays = _rays(cast(_HashableCamera, camera))
    flat = image.reshape(-1)
    for placed in targets:
        target_from_cam = invert_pose(placed.frame_from_target) @ frame_from_cam
        R, t = target_from_cam[:3, :3], target_from_cam[:3, 3]
        region = _image_region(camera, invert_pose(target_from_cam), placed.target)
        if region is None:
            continue
        index = np.flatnonzero(region)
        directions = rays[index] @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -t[2] / directions[:, 2]
        hit = np.isfinite(lam) & (lam > 0) & (lam < depth[index])
        points = t[None, :2] + lam[:, None] * directions[:, :2]
        ppm = pixels_per_m or 40.0 / placed.target.tag_size_m
        texture = _texture(placed.target, float(ppm)).astype(np.float32)
        tex_px = texture_pixel_from_target(placed.target, ppm, points)
        inside = (
            hit
            & (tex_px[:, 0] >= 0)
            & (tex_px[:, 1] >= 0)
            & (tex_px[:, 0] <= texture.shape[1] - 1)
            & (tex_px[:, 1] <= texture.shape[0] - 1)
        )
        if not np.any(inside):
            continue
        # Pre-blur the texture to the footprint of one image pixel to avoid aliasing.
        distance = float(np.median(lam[inside]))
        footprint = ppm * distance / float(camera.intrinsic_matrix[0, 0])
        if footprint > 1.0:
            texture = np.asarray(
                cv2.GaussianBlur(texture, (0, 0), 0.5 * footprint), dtype=np.float32
            )
        # remap wants 2-D maps under 32767 a side: fold the pixel list into rows of 1024.
        count = int(np.count_nonzero(inside))
        padded = -(-count // 1024) * 1024
        maps = np.zeros((2, padded), dtype=np.float32)
        maps[:, :count] = tex_px[inside].T
        sampled = cv2.remap(
            texture, maps[0].reshape(-1, 1024), maps[1].reshape(-1, 1024), cv2.INTER_LINEAR
        ).reshape(-1)[:count]
        chosen = index[inside]
        flat[chosen] = ink_level + (paper_level - ink_level) * sampled / 255.0
        depth[chosen] = lam[inside]
    image = flat.reshape(h, w)
    if blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma_px)
    image = image + rng.normal(0.0, noise_sigma, size=image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _image_region(
    camera: CameraModel, cam_from_target: FloatArray, target: AprilGridTarget
) -> npt.NDArray[np.bool_] | None:
    """(H*W,) pixels that may see the target (its projected bounding box, padded).

    All pixels when part of the target is behind the camera; None when all of it is.
    """
    margin = 2.0 * target.tag_spacing_m
    w, h = target.extent_m
    xs = np.linspace(-margin, w + margin, 9)
    ys = np.linspace(-margin, h + margin, 9)
    gx, gy = np.meshgrid(xs, ys)
    outline = np.column_stack((gx.ravel(), gy.ravel(), np.zeros(gx.size)))
    points = outline @ cam_from_target[:3, :3].T + cam_from_target[:3, 3]
    full = np.ones(camera.width * camera.height, dtype=bool)
    if np.all(points[:, 2] <= 0):
        return None
    if np.any(points[:, 2] <= 0.05):
        return full
    pixels = camera.project(points)
    if not np.all(np.isfinite(pixels)):
        return full
    lo = np.floor(pixels.min(axis=0)) - 8
    hi = np.ceil(pixels.max(axis=0)) + 8
    if hi[0] < 0 or hi[1] < 0 or lo[0] >= camera.width or lo[1] >= camera.height:
        return None
    u = np.arange(camera.width)
    v = np.arange(camera.height)
    inside_u = (u >= lo[0]) & (u <= hi[0])
    inside_v = (v >= lo[1]) & (v <= hi[1])
    result: npt.NDArray[np.bool_] = (inside_v[:, None] & inside_u[None, :]).ravel()
    return result


def write_slam_folder(
    folder: Path,
    camera: CameraModel,
    stamps_ns: npt.ArrayLike,
    session_from_cam: FloatArray,
    images: Sequence[npt.NDArray[np.uint8]],
) -> Path:
    """Write keyframes.tum, keyframes/<ns>.png and calib/camchain.yaml into `folder`."""
    import cv2

    stamps = np.asarray(stamps_ns, dtype=np.int64)
    slam = SlamFolder(folder)
    folder.mkdir(parents=True, exist_ok=True)
    slam.keyframes.mkdir(exist_ok=True)
    slam.write_keyframes(Trajectory(stamps, np.asarray(session_from_cam)))
    for stamp, image in zip(stamps, images, strict=True):
        cv2.imwrite(str(slam.keyframe_image(int(stamp))), image)
    slam.write_camchain([CameraCalibration(camera=camera)])
    return folder


@dataclass(frozen=True)
class SurveyTruth:
    """Ground truth of a synthetic survey.

    world_from_session: session folder name -> true `T_W_S`.
    world_from_target: target name -> true `T_W_m`.
    outlier_stamps_ns: session name -> keyframe stamps whose SLAM pose was corrupted.
    """

    world_from_session: dict[str, FloatArray]
    world_from_target: dict[str, FloatArray]
    outlier_stamps_ns: dict[str, list[int]]


@dataclass(kw_only=True)
class SurveyOptions:
    """A synthetic multi-session survey around AprilGrid targets.

    sessions: number of dives. targets: name -> (grid, `T_W_m`) (None: two
        grids, 4x2 and 5x4 tags, 10 m apart on a tilted deck, as on the Pamir).
    passes_per_target / keyframes_per_pass: how often each dive films each target.
    distance_m: (min, max) camera distance from a target's centre.
    view_angle_deg: largest angle between the viewing ray and the target normal.
    jitter_rotation_deg / jitter_translation_m: per-keyframe SLAM pose noise (1 sigma).
    drift_rotation_deg / drift_translation_m: SLAM error shared by one pass (1 sigma).
    tilt_deg: error of each session's gravity direction (1 sigma).
    outlier_fraction: share of keyframes whose SLAM pose is wrong by
        `outlier_rotation_deg` and `outlier_translation_m` (uniform ranges).
    session_yaw_deg: largest yaw of a session frame in W (sessions start near the bow).
    camera: the camera (None: `default_camera()`).
    pass_gap_s: time between the end of one pass and the start of the next (s);
        keyframes inside a pass are 0.5 s apart.
    skip_targets: session index -> target names that dive never films.
    """

    sessions: int = 2
    targets: dict[str, tuple[AprilGridTarget, FloatArray]] | None = None
    passes_per_target: int = 2
    keyframes_per_pass: int = 10
    distance_m: tuple[float, float] = (0.8, 2.0)
    view_angle_deg: float = 55.0
    jitter_rotation_deg: float = 0.15
    jitter_translation_m: float = 0.01
    drift_rotation_deg: float = 0.2
    drift_translation_m: float = 0.02
    tilt_deg: float = 0.05
    outlier_fraction: float = 0.1
    outlier_rotation_deg: tuple[float, float] = (3.0, 12.0)
    outlier_translation_m: tuple[float, float] = (0.15, 0.6)
    session_yaw_deg: float = 60.0
    noise_sigma: float = 2.5
    blur_sigma_px: float = 0.8
    camera: CameraModel | None = None
    pass_gap_s: float = 0.0
    skip_targets: dict[int, tuple[str, ...]] = field(default_factory=dict)


def _rot(axis: int, angle: float) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def default_targets() -> dict[str, tuple[AprilGridTarget, FloatArray]]:
    """Two grids like the Pamir's (4x2 and 5x4 tags, ids 0.. and 8..) 10 m apart on a deck."""
    small = AprilGridTarget(tag_rows=2, tag_cols=4, tag_size_m=0.088, tag_spacing_ratio=0.3)
    large = AprilGridTarget(
        tag_rows=4, tag_cols=5, tag_size_m=0.088, tag_spacing_ratio=0.3, tag_id_offset=8
    )
    bow = make_pose(_rot(2, np.deg2rad(20)) @ _rot(0, np.deg2rad(12)), [0.0, 0.0, -9.0])
    mid = make_pose(_rot(2, np.deg2rad(-15)) @ _rot(1, np.deg2rad(-18)), [9.5, 3.0, -11.5])
    return {"bow": (small, bow), "midship": (large, mid)}


def make_survey(
    root: Path, options: SurveyOptions, *, seed: int
) -> tuple[list[Path], list[Path], SurveyTruth]:
    """Render keyframes of every dive and write SLAM-like folders and target YAMLs.

    Returns (SLAM folders `root/dive<k>`, target YAMLs `root/targets/<name>.yaml`, truth).
    Session frames are gravity-aligned (up to `tilt_deg`) with a random yaw and origin.
    """
    from shared.calibration.kalibr import write_target_yaml
    from shared.geometry import so3_exp

    rng = np.random.default_rng(seed)
    camera = options.camera or default_camera()
    targets = options.targets or default_targets()
    placed = [PlacedTarget(grid, pose) for grid, pose in targets.values()]
    target_paths = []
    for name, (grid, _) in targets.items():
        target_paths.append(
            write_target_yaml(root / "targets" / f"{name}.yaml", grid, overwrite=True)
        )
    truth_sessions: dict[str, FloatArray] = {}
    outliers: dict[str, list[int]] = {}
    folders = []
    for k in range(options.sessions):
        name = f"dive{k + 1}"
        tilt = so3_exp(np.r_[rng.normal(0, np.deg2rad(options.tilt_deg), 2), 0.0])
        yaw = rng.uniform(-1, 1) * np.deg2rad(options.session_yaw_deg)
        world_from_session = make_pose(
            tilt @ _rot(2, yaw), [rng.uniform(-3, 3), rng.uniform(-3, 3), -9 + rng.normal(0, 1)]
        )
        truth_sessions[name] = world_from_session
        session_from_world = invert_pose(world_from_session)
        stamps: list[int] = []
        estimated: list[FloatArray] = []
        images = []
        outliers[name] = []
        stamp = 1_700_000_000_000_000_000 + k * 10_000_000_000_000
        for target_name, (grid, world_from_target) in targets.items():
            if target_name in options.skip_targets.get(k, ()):
                continue
            w, h = grid.extent_m
            centre = world_from_target @ np.array([w / 2, h / 2, 0.0, 1.0])
            normal = world_from_target[:3, 2]
            for _ in range(options.passes_per_target):
                drift = random_pose_error(
                    rng, options.drift_rotation_deg, options.drift_translation_m
                )
                # A pass: the diver swims along a line past the target, camera on it.
                side = rng.normal(size=3)
                side -= (side @ normal) * normal
                side /= np.linalg.norm(side)
                angle = np.deg2rad(rng.uniform(0, options.view_angle_deg))
                distance = rng.uniform(*options.distance_m)
                for i in range(options.keyframes_per_pass):
                    frac = (i / max(options.keyframes_per_pass - 1, 1)) - 0.5
                    a = angle + 0.4 * frac
                    d = distance * (1 + 0.2 * frac)
                    direction = np.cos(a) * normal + np.sin(a) * side
                    eye = centre[:3] + d * direction
                    aim = centre[:3] + rng.normal(0, 0.05, 3)
                    world_from_cam = look_at(eye, aim, np.array([0.0, 0.0, 1.0]))
                    # Roll the camera about its axis a little (the diver's hand).
                    world_from_cam[:3, :3] = world_from_cam[:3, :3] @ _rot(2, rng.normal(0, 0.3))
                    image = render_view(
                        camera,
                        world_from_cam,
                        placed,
                        rng=rng,
                        noise_sigma=options.noise_sigma,
                        blur_sigma_px=options.blur_sigma_px,
                    )
                    session_from_cam = session_from_world @ world_from_cam
                    error = drift @ random_pose_error(
                        rng, options.jitter_rotation_deg, options.jitter_translation_m
                    )
                    if rng.uniform() < options.outlier_fraction:
                        error = outlier_pose_error(
                            rng, options.outlier_rotation_deg, options.outlier_translation_m
                        )
                        outliers[name].append(stamp)
                    estimate = apply_slam_error(session_from_cam, error)
                    stamps.append(stamp)
                    estimated.append(estimate)
                    images.append(image)
                    stamp += 500_000_000
                stamp += ns_from_seconds(options.pass_gap_s)
        folders.append(write_slam_folder(root / name, camera, stamps, np.array(estimated), images))
    truth = SurveyTruth(
        world_from_session=truth_sessions,
        world_from_target={name: pose for name, (_, pose) in targets.items()},
        outlier_stamps_ns=outliers,
    )
    return folders, target_paths, truth


def random_pose_error(
    rng: np.random.Generator, rotation_sigma_deg: float, translation_sigma_m: float
) -> FloatArray:
    """A random small pose error (4, 4): rotation vector and translation, normal per axis."""
    from shared.geometry import so3_exp

    return make_pose(
        so3_exp(rng.normal(0, np.deg2rad(rotation_sigma_deg), 3)),
        rng.normal(0, translation_sigma_m, 3),
    )


def outlier_pose_error(
    rng: np.random.Generator,
    rotation_deg: tuple[float, float],
    translation_m: tuple[float, float],
) -> FloatArray:
    """A gross pose error: random axis and direction, sizes uniform in the given ranges."""
    from shared.geometry import so3_exp

    axis = rng.normal(size=3)
    offset = rng.normal(size=3)
    return make_pose(
        so3_exp(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(*rotation_deg))),
        offset / np.linalg.norm(offset) * rng.uniform(*translation_m),
    )


def apply_slam_error(session_from_cam: FloatArray, error: FloatArray) -> FloatArray:
    """A SLAM estimate of `T_S_C`: rotated by `error` about the camera centre, then shifted."""
    estimate = session_from_cam.copy()
    estimate[:3, :3] = error[:3, :3] @ session_from_cam[:3, :3]
    estimate[:3, 3] = session_from_cam[:3, 3] + error[:3, 3]
    return estimate
