"""The COLMAP database: write then read back cameras, rigs, frames, images and priors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from postproc.sfm.database import (
    KeyframeSet,
    colmap_camera,
    pose_from_rigid3d,
    read_image_ids,
    rigid3d_from_pose,
    write_database,
)
from shared.calibration.cameras import PinholeEquidistant, PinholeRadtan
from shared.errors import InputError
from shared.geometry import make_pose, so3_exp

RADTAN = PinholeRadtan(320, 240, 170.0, 171.0, 160.5, 118.0, -0.2, 0.05, 1e-4, -2e-4)
FISHEYE = PinholeEquidistant(640, 480, 300.0, 301.0, 320.0, 240.0, 0.1, -0.01, 0.002, 0.0)


def keyframe_set(n: int = 6) -> KeyframeSet:
    rng = np.random.default_rng(5)
    poses = make_pose(so3_exp(rng.normal(scale=0.5, size=(n, 3))), rng.normal(size=(n, 3)))
    return KeyframeSet(
        names=[f"s{k % 2}/{1000 + k}.png" for k in range(n)],
        sources=[Path(f"/nonexistent/{k}.png") for k in range(n)],
        session=np.arange(n, dtype=np.int64) % 2,
        camera=np.arange(n, dtype=np.int64) % 2,
        stamps_ns=1000 + np.arange(n, dtype=np.int64),
        world_from_cam=poses,
        placed=np.array([True, True, True, True, False, False])[:n],
        prior_sigma_m=np.linspace(0.5, 1.0, n),
    )


def test_database_round_trip(tmp_path: Path) -> None:
    keyframes = keyframe_set()
    path = tmp_path / "database.db"
    ids = write_database(path, [RADTAN, FISHEYE], keyframes)
    assert read_image_ids(path) == ids
    assert sorted(ids) == sorted(keyframes.names)
    with pycolmap.Database.open(path) as db:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        assert len(cameras) == 2 and db.num_rigs() == 2 and db.num_frames() == 6
        assert cameras[1].model_name == "OPENCV" and cameras[2].model_name == "OPENCV_FISHEYE"
        # COLMAP pixel centres are +0.5 from OpenCV's.
        np.testing.assert_allclose(
            cameras[1].params, [170.0, 171.0, 161.0, 118.5, -0.2, 0.05, 1e-4, -2e-4]
        )
        np.testing.assert_allclose(cameras[2].params[:4], [300.0, 301.0, 320.5, 240.5])
        for image in db.read_all_images():
            i = keyframes.names.index(image.name)
            assert image.camera_id == int(keyframes.camera[i]) + 1
        priors = {p.corr_data_id.id: p for p in db.read_all_pose_priors()}
    # Priors only for placed keyframes (an unplaced session's poses are in its own frame).
    assert len(priors) == int(np.sum(keyframes.placed))
    for name, image_id in ids.items():
        i = keyframes.names.index(name)
        if not keyframes.placed[i]:
            assert image_id not in priors
            continue
        prior = priors[image_id]
        np.testing.assert_allclose(prior.position, keyframes.world_from_cam[i, :3, 3])
        np.testing.assert_allclose(
            prior.position_covariance, np.eye(3) * keyframes.prior_sigma_m[i] ** 2
        )
        # Gravity (world -z) seen in the camera frame.
        expected = keyframes.world_from_cam[i, :3, :3].T @ [0.0, 0.0, -1.0]
        np.testing.assert_allclose(prior.gravity, expected, atol=1e-12)
        assert prior.coordinate_system == pycolmap.PosePriorCoordinateSystem.CARTESIAN


def test_database_refuses_an_existing_path(tmp_path: Path) -> None:
    path = tmp_path / "database.db"
    path.write_bytes(b"")
    with pytest.raises(InputError, match="already exists"):
        write_database(path, [RADTAN], keyframe_set())


def test_unsupported_camera_model_is_an_input_error() -> None:
    class Orthographic:
        width, height = 10, 10
        kalibr_model = ("omni", "none")

    with pytest.raises(InputError, match="not supported"):
        colmap_camera(Orthographic(), 1)  # type: ignore[arg-type]


def test_rigid3d_round_trip() -> None:
    T = make_pose(so3_exp([0.3, -0.2, 0.9]), [1.0, -2.0, 3.0])
    np.testing.assert_allclose(pose_from_rigid3d(rigid3d_from_pose(T)), T, atol=1e-12)
