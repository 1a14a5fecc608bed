"""Mesh completeness counts only the truth surface the keyframes filmed: on two stacked
squares filmed from above, the hidden lower one is left out of the denominator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from postproc.pipeline.evaluate import CompletenessOptions, evaluate_mesh, truth_camera
from shared.calibration.cameras import PinholeRadtan
from shared.errors import InputError
from shared.formats.ply import PlyData, write_ply
from shared.geometry import make_pose, so3_exp

# A small camera with some barrel distortion (the canvas then differs from the image).
CAMERA = PinholeRadtan(160, 120, 100.0, 100.0, 80.5, 59.0, -0.1, 0.01, 0.0, 0.0)


def two_storeys(tmp_path: Path) -> Path:
    """Two 2 m squares over x, y in [-1, 1], at z = 0 and z = -1 (the lower one hidden
    from any camera above the upper one)."""
    square = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    mesh = PlyData(
        vertices=np.concatenate([square, square + np.array([0, 0, -1.0])]),
        faces=np.concatenate([faces, faces + 4]),
    )
    return write_ply(tmp_path / "truth.ply", mesh)


def keyframes_above() -> np.ndarray:
    """world_from_cam of four cameras 3 m above the squares, looking straight down."""
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, :3] = np.column_stack([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    poses[:, :3, 3] = [[x, y, 3.0] for x in (-0.2, 0.2) for y in (-0.2, 0.2)]
    return poses


def reconstruction(tmp_path: Path, recon_from_truth: np.ndarray) -> Path:
    """A dense grid over the x >= 0 half of the upper square, in a rigid frame."""
    x, y = np.meshgrid(np.arange(0.0, 1.0001, 0.01), np.arange(-1.0, 1.0001, 0.01))
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    points = points @ recon_from_truth[:3, :3].T + recon_from_truth[:3, 3]
    return write_ply(tmp_path / "mesh.ply", PlyData(vertices=points))


def test_completeness_of_the_filmed_half(tmp_path: Path) -> None:
    truth_from_recon = make_pose(so3_exp([0.1, -0.2, 0.3]), [2.0, -1.0, 0.5])
    recon = reconstruction(tmp_path, np.linalg.inv(truth_from_recon))
    result = evaluate_mesh(
        recon,
        two_storeys(tmp_path),
        truth_from_recon,
        camera=CAMERA,
        world_from_cams=keyframes_above(),
        options=CompletenessOptions(sample_spacing_m=0.02),
    )
    assert "seen by >= 3 of 4 keyframes within 8 m" in result["completeness_basis"]
    # The upper square is filmed, the lower one hidden: half the samples count.
    assert result["filmed_samples"] == result["truth_samples"] // 2
    assert result["median_distance_m"] < 1e-6  # float32 PLY
    for score in result["scores"]:
        d = score["threshold_m"]
        assert score["accuracy"] == 1.0
        # The reconstruction covers x in [0, 1] of the 2 m wide upper square: within d of
        # it lies x in [-d, 1], a share (1 + d) / 2 of the filmed surface.
        assert score["completeness"] == pytest.approx((1 + d) / 2, abs=0.01)
        # The bounding box (x in [-0.1, 1.1], z within 0.1 of 0) holds upper-square
        # samples only, x in [-0.1, 1]: a share (1 + min(d, 0.1)) / 1.1 is near a point.
        assert score["completeness_bbox"] == pytest.approx((1 + min(d, 0.1)) / 1.1, abs=0.01)
        f1 = 2 * score["completeness"] / (1 + score["completeness"])
        assert score["f1"] == pytest.approx(f1)


def test_a_mesh_counts_its_triangles_not_only_its_vertices(tmp_path: Path) -> None:
    """Two triangles over the x >= 0 half of the upper square: their four corners alone
    would cover almost nothing at 5 cm, the surface covers half the filmed square."""
    half = np.array([[0, -1, 0], [1, -1, 0], [1, 1, 0], [0, 1, 0]], float)
    recon = write_ply(
        tmp_path / "coarse.ply", PlyData(vertices=half, faces=np.array([[0, 1, 2], [0, 2, 3]]))
    )
    result = evaluate_mesh(
        recon,
        two_storeys(tmp_path),
        np.eye(4),
        camera=CAMERA,
        world_from_cams=keyframes_above(),
        options=CompletenessOptions(sample_spacing_m=0.02),
    )
    for score in result["scores"]:
        d = score["threshold_m"]
        assert score["completeness"] == pytest.approx((1 + d) / 2, abs=0.01)


def test_out_of_range_and_without_cameras(tmp_path: Path) -> None:
    truth_path = two_storeys(tmp_path)
    recon = reconstruction(tmp_path, np.eye(4))
    too_far = evaluate_mesh(
        recon,
        truth_path,
        np.eye(4),
        camera=CAMERA,
        world_from_cams=keyframes_above(),
        options=CompletenessOptions(max_range_m=2.5, sample_spacing_m=0.05),
    )
    assert too_far["filmed_samples"] == 0
    assert all(s["completeness"] == 0.0 for s in too_far["scores"])
    # More views asked for than there are keyframes: nothing counts as filmed either.
    few = evaluate_mesh(
        recon,
        truth_path,
        np.eye(4),
        camera=CAMERA,
        world_from_cams=keyframes_above(),
        options=CompletenessOptions(min_views=5, sample_spacing_m=0.05),
    )
    assert few["filmed_samples"] == 0
    # No camera known: the bounding-box figure, and said so.
    box = evaluate_mesh(recon, truth_path, np.eye(4))
    assert box["completeness_basis"].startswith("truth surface inside the reconstruction's")
    assert "filmed_samples" not in box
    assert all(s["completeness"] == s["completeness_bbox"] for s in box["scores"])
    assert box["scores"][0]["completeness"] > 0.9


def test_truth_camera_and_mesh_errors(tmp_path: Path) -> None:
    entry = {
        "model": ["pinhole", "radtan"],
        "width": 640,
        "height": 360,
        "intrinsics_fx_fy_cx_cy": [339.2, 339.2, 326.54, 176.62],
        "distortion_k1_k2_p1_p2": [-0.22, 0.05, 0.0003, -0.0002],
    }
    camera = truth_camera({"camera": entry})
    assert isinstance(camera, PinholeRadtan) and camera.k1 == -0.22 and camera.width == 640
    assert truth_camera({"camera": {"timeshift_cam_imu_s": 0.0}}) is None
    with pytest.raises(InputError, match=r"camera model \('omni', 'radtan'\) unknown"):
        truth_camera({"camera": {**entry, "model": ["omni", "radtan"]}})
    write_ply(tmp_path / "points.ply", PlyData(vertices=np.zeros((3, 3))))
    with pytest.raises(InputError, match=r"points.ply: no triangles"):
        evaluate_mesh(tmp_path / "points.ply", tmp_path / "points.ply", np.eye(4))
