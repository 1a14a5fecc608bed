"""Octree depth from the scene, Poisson meshing of a cloud, trimming."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from postproc.dense.meshing import (
    MeshingOptions,
    choose_octree_depth,
    mesh,
    point_spacing_m,
    scene_extent_m,
    trim_mesh,
)
from shared.errors import InputError, OutputExistsError
from shared.formats.ply import PlyData, read_ply, write_ply


@pytest.mark.parametrize(
    ("extent", "spacing", "expected"),
    [
        (5.0, 0.02, 8),  # 250 cells -> 2^8 = 256
        (5.0, 0.01, 9),  # 500 -> 512
        (40.0, 0.01, 11),  # 4000 -> 12, clamped to 11
        (0.5, 0.05, 6),  # 10 -> 4, clamped to 6
        (8.0, 0.0625, 7),  # exactly 128 -> 7
    ],
)
def test_octree_depth_choice(extent: float, spacing: float, expected: int) -> None:
    assert choose_octree_depth(extent, spacing) == expected


def test_octree_depth_bounds_and_errors() -> None:
    assert choose_octree_depth(40.0, 0.01, max_depth=13) == 12
    with pytest.raises(ValueError, match="positive"):
        choose_octree_depth(0.0, 0.01)


def plane_cloud(rng: np.random.Generator, spacing: float = 0.02, size: float = 2.0) -> PlyData:
    """A noisy square of the plane z = 0 (normals +z, grey)."""
    n = int(size / spacing)
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    points = np.column_stack((x.ravel(), y.ravel(), rng.normal(0, 0.002, x.size)))
    points[:, :2] += rng.uniform(-0.3, 0.3, (x.size, 2)) * spacing
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    colors = np.full((len(points), 3), 120, np.uint8)
    return PlyData(vertices=points, normals=normals, colors=colors)


def test_spacing_and_extent() -> None:
    cloud = plane_cloud(np.random.default_rng(0))
    assert 0.012 < point_spacing_m(cloud.vertices) < 0.022
    assert scene_extent_m(cloud.vertices) == pytest.approx(2.0, abs=0.05)
    with pytest.raises(ValueError, match="two points"):
        point_spacing_m(np.zeros((1, 3)))


def test_trim_keeps_supported_triangles() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0], [6, 5, 0]], float)
    faces = np.array([[0, 1, 2], [1, 3, 4]])
    points = vertices[:3] + 0.01
    out = trim_mesh(PlyData(vertices=vertices, faces=faces), points, 0.1)
    np.testing.assert_array_equal(out.faces, [[0, 1, 2]])
    assert len(out.vertices) == 3


def test_poisson_mesh_of_a_plane(tmp_path: Path) -> None:
    cloud = plane_cloud(np.random.default_rng(1), spacing=0.03)
    fused = write_ply(tmp_path / "fused.ply", cloud)
    options = MeshingOptions(num_threads=1)
    report = mesh(options, fused, tmp_path / "mesh.ply")
    # 2 m at about 2.3 cm nearest-neighbour spacing (jittered 3 cm grid): 2^7 cells.
    assert report.octree_depth == choose_octree_depth(report.extent_m, report.spacing_m) == 7
    surface = read_ply(tmp_path / "mesh.ply")
    assert surface.faces is not None
    assert report.faces == len(surface.faces) > 500
    assert np.abs(surface.vertices[:, 2]).max() < 0.02
    # Trimmed to the cloud: nothing beyond the square plus the trim distance (spacings or
    # octree cells, the larger), which Poisson's surface does reach past the edges.
    cell = report.extent_m / 2.0**report.octree_depth
    trim = options.trim_distance_spacings * max(report.spacing_m, cell)
    assert 0.05 < trim < 0.25
    lo, hi = surface.vertices[:, :2].min(), surface.vertices[:, :2].max()
    assert -trim - 0.01 < lo < -0.3 * trim and 2.0 + 0.3 * trim < hi < 2.0 + trim + 0.01
    assert surface.colors is not None
    with pytest.raises(OutputExistsError):
        mesh(MeshingOptions(), fused, tmp_path / "mesh.ply")


def test_meshing_refuses_clouds_without_normals(tmp_path: Path) -> None:
    cloud = plane_cloud(np.random.default_rng(1))
    fused = write_ply(tmp_path / "f.ply", PlyData(vertices=cloud.vertices))
    with pytest.raises(InputError, match="without normals"):
        mesh(MeshingOptions(), fused, tmp_path / "mesh.ply")
