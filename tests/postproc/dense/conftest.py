"""Fixtures for the dense tests: a coarse simulated wreck and tiny SfM folders rendered
from known poses (the COLMAP model the SfM stage would write, with its sparse points)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from postproc.dense.colmap_io import write_known_pose_model
from shared.calibration.cameras import PinholeRadtan
from shared.geometry import look_at
from sim.render import Renderer, WaterModel
from sim.scene import WreckScene, build_wreck_scene

# A small wide camera with barrel distortion, like a scaled-down GoPro.
CAMERA = PinholeRadtan(
    width=256, height=192, fx=150.0, fy=150.0, cx=129.0, cy=95.0, k1=-0.12, k2=0.02,
    p1=2e-4, p2=-1e-4,
)  # fmt: skip


def hull_poses(count: int, *, step_m: float = 0.3) -> list[np.ndarray]:
    """Cameras 2.5 m off the starboard side of the fore hull, moving along it, looking
    slightly down at the hull side (plane y = 3.5)."""
    return [
        look_at(np.array([2.0 + step_m * i, 6.0, -13.6]), np.array([2.0 + step_m * i, 3.5, -14.4]))
        for i in range(count)
    ]


@dataclass
class SyntheticSfm:
    """A rendered SfM folder: `folder/sparse` model, `folder/images`, and the truth."""

    folder: Path
    names: list[str]
    worlds_from_cam: list[np.ndarray]
    depths_m: list[np.ndarray]  # true camera-z depth of each (distorted) image


@pytest.fixture(scope="session")
def coarse_scene() -> WreckScene:
    """The wreck with coarse textures (about 2 s to build)."""
    return build_wreck_scene(seed=3, texel_m=0.02, seafloor_texel_m=0.06)


def build_sfm(
    folder: Path,
    scene: WreckScene,
    worlds_from_cam: list[np.ndarray],
    *,
    camera: PinholeRadtan = CAMERA,
    water: WaterModel | None = None,
    point_step_px: int = 12,
) -> SyntheticSfm:
    """Render the views, then write images and a COLMAP model with the true poses and
    sparse points (a pixel grid of every image back-projected, kept in each image where
    the true depth confirms it is visible)."""
    renderer = Renderer(scene, camera, water if water is not None else WaterModel())
    (folder / "images").mkdir(parents=True)
    names, depths, images = [], [], []
    for k, pose in enumerate(worlds_from_cam):
        frame = renderer.render(pose, rng=np.random.default_rng(k))
        name = f"{k:04d}.png"
        cv2.imwrite(str(folder / "images" / name), frame.image_rgb[..., ::-1])
        names.append(name)
        depths.append(frame.depth_m)
        images.append(frame.image_rgb)
    points: list[np.ndarray] = []
    for k, pose in enumerate(worlds_from_cam):
        vv, uu = np.mgrid[
            4 : camera.height - 4 : point_step_px, 4 : camera.width - 4 : point_step_px
        ]
        z = depths[k][vv, uu]
        ok = np.isfinite(z)
        rays = camera.unproject(np.column_stack((uu[ok], vv[ok])).astype(float))
        cam_points = rays / rays[:, 2:3] * z[ok, None]
        points.append(cam_points @ pose[:3, :3].T + pose[:3, 3])
    all_points = np.concatenate(points)
    observations: list[list[tuple[int, float, float]]] = []
    for k, pose in enumerate(worlds_from_cam):
        cam_from_world = np.linalg.inv(pose)
        pc = all_points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        seen: list[tuple[int, float, float]] = []
        front = pc[:, 2] > 0.1
        uv = np.full((len(pc), 2), -1.0)
        uv[front] = camera.project(pc[front])
        for p in np.flatnonzero(front):
            u, v = uv[p]
            if not (0 <= u < camera.width - 1 and 0 <= v < camera.height - 1):
                continue
            true_z = depths[k][round(v), round(u)]
            if np.isfinite(true_z) and abs(true_z - pc[p, 2]) < 0.01 * pc[p, 2]:
                seen.append((int(p), float(u), float(v)))
        observations.append(seen)
    write_known_pose_model(
        folder / "sparse",
        camera_model="OPENCV",
        camera_params=[camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2,
                       camera.p1, camera.p2],
        size=(camera.width, camera.height),
        image_names=names,
        cams_from_world=[np.linalg.inv(p) for p in worlds_from_cam],
        points_m=all_points,
        observations=observations,
    )  # fmt: skip
    return SyntheticSfm(
        folder=folder, names=names, worlds_from_cam=worlds_from_cam, depths_m=depths
    )


@pytest.fixture
def make_sfm(coarse_scene: WreckScene) -> Callable[..., SyntheticSfm]:
    """`make_sfm(folder, poses, **kw)` -> a rendered SfM folder of the coarse scene."""

    def make(folder: Path, poses: list[np.ndarray], **kwargs: object) -> SyntheticSfm:
        return build_sfm(folder, coarse_scene, poses, **kwargs)  # type: ignore[arg-type]

    return make
