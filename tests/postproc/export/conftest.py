"""A tiny run folder written with the stages' own writers: an SfM model (OPENCV camera,
six cameras over a plank on the seabed, sparse points observed with 0.3 px noise), its
images, and dense/ (fused.ply, mesh.ply), merge/targets.json; the truth beside it."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from postproc.dense.colmap_io import write_known_pose_model
from shared.formats.ply import PlyData, write_ply
from shared.geometry import look_at

WIDTH, HEIGHT = 256, 192
PARAMS = [150.0, 152.0, 129.0, 95.0, -0.12, 0.02, 2e-4, -1e-4]  # OPENCV fx fy cx cy k1 k2 p1 p2
SEABED_Z = -12.0
# The plank: a box 2.0 m along x, 0.5 m along y, its top 0.3 m above the seabed.
BOX_MIN, BOX_MAX = np.array([-1.0, -0.25]), np.array([1.0, 0.25])
BOX_TOP_Z = SEABED_Z + 0.3
TARGET_M = np.array([1.5, 0.8, SEABED_Z])


def heightfield_mesh(step_m: float = 0.05) -> PlyData:
    """The seabed 4 x 3 m around the plank (a grid), the plank's top raised; red plank
    top, a grey checker seabed."""
    xs = np.arange(-2.0, 2.0 + 1e-9, step_m)
    ys = np.arange(-1.5, 1.5 + 1e-9, step_m)
    # Put grid lines on the plank's edges so its top is exactly flat and square.
    xs = np.unique(np.round(np.r_[xs, BOX_MIN[0], BOX_MAX[0]], 9))
    ys = np.unique(np.round(np.r_[ys, BOX_MIN[1], BOX_MAX[1]], 9))
    gx, gy = np.meshgrid(xs, ys)
    on_box = (gx >= BOX_MIN[0]) & (gx <= BOX_MAX[0]) & (gy >= BOX_MIN[1]) & (gy <= BOX_MAX[1])
    gz = np.where(on_box, BOX_TOP_Z, SEABED_Z)
    vertices = np.column_stack((gx.ravel(), gy.ravel(), gz.ravel()))
    checker = ((np.floor(gx / 0.25) + np.floor(gy / 0.25)) % 2).ravel()
    colors = np.where(checker[:, None] > 0, [90, 90, 90], [170, 170, 170])
    colors[on_box.ravel()] = [200, 30, 30]
    nx = len(xs)
    faces = []
    for j in range(len(ys) - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            faces += [(a, b, d), (a, d, c)]
    return PlyData(vertices=vertices, colors=colors.astype(np.uint8), faces=np.array(faces))


@dataclass
class RunFixture:
    """The run folder and its truth."""

    root: Path
    names: list[str]
    worlds_from_cam: list[np.ndarray]
    points_m: np.ndarray
    mesh: PlyData
    fused: PlyData


def build_run(root: Path) -> RunFixture:
    import pycolmap

    rng = np.random.default_rng(7)
    camera = pycolmap.Camera.create_from_model_name(1, "OPENCV", 1.0, WIDTH, HEIGHT)
    camera.params = np.array(PARAMS)  # type: ignore[assignment]  # pycolmap stubs: a Sequence; an array is taken
    poses = [
        look_at(np.array([x, y, SEABED_Z + 2.5]), np.array([x * 0.5, 0.0, SEABED_Z]),
                np.array([0.0, 1.0, 0.0]))
        for x in (-1.2, 0.0, 1.2) for y in (-0.4, 0.4)
    ]  # fmt: skip
    points = np.column_stack(
        (rng.uniform(-1.8, 1.8, 400), rng.uniform(-1.2, 1.2, 400), np.full(400, SEABED_Z))
    )
    top = (points[:, 0] > BOX_MIN[0]) & (points[:, 0] < BOX_MAX[0])
    top &= (points[:, 1] > BOX_MIN[1]) & (points[:, 1] < BOX_MAX[1])
    points[top, 2] = BOX_TOP_Z
    names, observations = [], []
    (root / "sfm" / "images").mkdir(parents=True)
    for k, pose in enumerate(poses):
        cam_from_world = np.linalg.inv(pose)
        pc = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        uv = np.asarray(camera.img_from_cam(pc))
        seen = [
            (p, float(u + rng.normal(0, 0.3)), float(v + rng.normal(0, 0.3)))
            for p, (u, v) in enumerate(uv)
            if pc[p, 2] > 0 and 2 <= u < WIDTH - 2 and 2 <= v < HEIGHT - 2
        ]
        observations.append(seen)
        # As the stages lay them out: the keyframe in the SLAM folder, and a link to it
        # named <session>/<stamp>.png in sfm/images.
        stamp = 1_700_000_000_000_000_000 + k * 100_000_000
        name = f"s1/{stamp}.png"
        names.append(name)
        image = rng.integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        keyframe = root / "sessions" / "s1" / "keyframes" / f"{stamp}.png"
        keyframe.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(keyframe), image)
        (root / "sfm" / "images" / name).parent.mkdir(exist_ok=True)
        (root / "sfm" / "images" / name).symlink_to(keyframe.resolve())
    write_known_pose_model(
        root / "sfm" / "sparse" / "0", camera_model="OPENCV", camera_params=PARAMS,
        size=(WIDTH, HEIGHT), image_names=names,
        cams_from_world=[np.asarray(np.linalg.inv(p), dtype=np.float64) for p in poses],
        points_m=points,
        observations=observations,
    )  # fmt: skip
    mesh = heightfield_mesh()
    fused = PlyData(
        vertices=points + rng.normal(0, 1e-4, points.shape),
        colors=rng.integers(0, 255, points.shape, dtype=np.uint8),
    )
    write_ply(root / "dense" / "mesh.ply", mesh)
    write_ply(root / "dense" / "fused.ply", fused)
    target = np.eye(4)
    target[:3, 3] = TARGET_M
    (root / "merge").mkdir()
    (root / "merge" / "targets.json").write_text(
        json.dumps({"grid_a": {"file": "grid_a.yaml", "T_W_m": target.tolist()}})
    )
    return RunFixture(root=root, names=names, worlds_from_cam=poses, points_m=points,
                      mesh=mesh, fused=fused)  # fmt: skip


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory: pytest.TempPathFactory) -> RunFixture:
    return build_run(tmp_path_factory.mktemp("run") / "run")
