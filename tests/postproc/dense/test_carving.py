"""Free-space carving: surface where the depth maps saw past it goes, the rest stays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from postproc.dense.carving import DepthView, carved_vertices, free_space_votes
from postproc.dense.meshing import keep_vertices, write_mesh
from shared.errors import StageError
from shared.formats.ply import PlyData
from shared.geometry import look_at

K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])


def wall_view(x_m: float, *, wall_y_m: float = 5.0, box: bool = False) -> DepthView:
    """A 100x80 depth map of the wall y = `wall_y_m` from (x, 0, 0), looking along +y
    (optionally with a box face 1 m nearer over the image's left half)."""
    world_from_cam = look_at(np.array([x_m, 0.0, 0.0]), np.array([x_m, 10.0, 0.0]))
    cam_from_world = np.asarray(np.linalg.inv(world_from_cam), dtype=np.float64)
    # Depth along the optical axis of a wall facing the camera: constant.
    depth = np.full((80, 100), wall_y_m, np.float32)
    if box:
        depth[:, :50] = wall_y_m - 1.0
    return DepthView(depth, K, cam_from_world)


def test_a_blob_in_front_of_the_wall_is_carved_and_the_wall_kept() -> None:
    views = [wall_view(x) for x in (-0.2, 0.0, 0.2)]
    wall = np.array([[0.0, 5.0, 0.0], [0.3, 5.0, -0.2], [-0.4, 5.01, 0.3]])
    blob = np.array([[0.0, 4.0, 0.0], [0.1, 4.8, 0.1]])  # 20 % and 4 % nearer
    hidden = np.array([[0.0, 6.0, 0.0]])  # behind the wall: nothing saw it, nothing says no
    outside = np.array([[50.0, 4.0, 0.0]])  # seen by no map
    points = np.vstack([wall, blob, hidden, outside])
    carved = carved_vertices(points, views, tolerance_rel=0.02, min_views=2)
    assert carved.tolist() == [False] * 3 + [True] * 2 + [False, False]
    # Within the tolerance it is the wall; past two of three maps is not enough when
    # fewer views see past it than agree with it.
    near = np.array([[0.0, 4.95, 0.0]])
    assert not carved_vertices(near, views, tolerance_rel=0.02, min_views=2).any()
    assert carved_vertices(near, views, tolerance_rel=0.005, min_views=2).all()
    mixed = [*views, wall_view(0.1, wall_y_m=4.0), wall_view(-0.1, wall_y_m=4.0)]
    blob_at_4_5 = np.array([[0.0, 4.5, 0.0]])
    # Three maps see past it (the wall at 5 m); to the two that see a surface at 4 m it
    # is hidden (no vote): three against none agreeing.
    assert carved_vertices(blob_at_4_5, mixed, tolerance_rel=0.02, min_views=2).all()
    # One map alone does not carve.
    assert not carved_vertices(blob, views[:1], tolerance_rel=0.02, min_views=2).any()
    assert carved_vertices(blob, views[:1], tolerance_rel=0.02, min_views=1).all()


def test_a_vertex_on_a_silhouette_is_not_seen_past() -> None:
    # The box's edge at column 50: a vertex of the box face projecting to column 50,
    # whose pixel shows the wall 1 m behind, has the box's depth in its 3x3 pixels.
    view = wall_view(0.0, box=True)
    world_from_cam = np.linalg.inv(view.cam_from_world)
    z = 4.0
    x_cam = (50.2 - K[0, 2]) / K[0, 0] * z  # column 50 (pixels 50 and on show the wall)
    edge = (world_from_cam[:3, :3] @ np.array([x_cam, 0.0, z]) + world_from_cam[:3, 3])[None]
    seen_past, agrees = free_space_votes(edge, view, tolerance_rel=0.02)
    assert not seen_past.any() and not agrees.any()
    # Two pixels further right, the same depth is in front of the wall in every pixel.
    x_cam = (52.2 - K[0, 2]) / K[0, 0] * z
    inside = (world_from_cam[:3, :3] @ np.array([x_cam, 0.0, z]) + world_from_cam[:3, 3])[None]
    seen_past, _ = free_space_votes(inside, view, tolerance_rel=0.02)
    assert seen_past.all()


def test_unknown_depth_and_the_camera_behind_say_nothing() -> None:
    view = wall_view(0.0)
    view.depth_m[:, :] = 0.0
    points = np.array([[0.0, 2.0, 0.0], [0.0, -2.0, 0.0]])
    seen_past, agrees = free_space_votes(points, view, tolerance_rel=0.02)
    assert not seen_past.any() and not agrees.any()
    assert carved_vertices(np.zeros((0, 3)), [view], tolerance_rel=0.02, min_views=1).shape == (0,)


def test_keep_vertices_drops_the_triangles_of_removed_vertices() -> None:
    mesh = PlyData(
        vertices=np.arange(15, dtype=float).reshape(5, 3),
        colors=np.arange(15, dtype=np.uint8).reshape(5, 3),
        faces=np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]]),
    )
    kept = keep_vertices(mesh, np.array([True, True, True, True, False]))
    assert kept.faces is not None and kept.colors is not None
    assert kept.faces.tolist() == [[0, 1, 2], [1, 2, 3]]
    assert kept.vertices.tolist() == mesh.vertices[:4].tolist()
    kept = keep_vertices(mesh, np.array([False, True, True, True, True]))
    assert kept.faces is not None and kept.faces.tolist() == [[0, 1, 2], [1, 2, 3]]
    assert kept.vertices.tolist() == mesh.vertices[1:].tolist()
    assert kept.colors is not None and kept.colors.tolist() == mesh.colors[1:].tolist()  # type: ignore[index]


@pytest.mark.parametrize("tolerance", [0.0, 0.5])
def test_votes_need_a_depth_in_front_of_the_camera(tolerance: float) -> None:
    view = wall_view(0.0)
    behind = np.array([[0.0, -4.0, 0.0]])
    seen_past, agrees = free_space_votes(behind, view, tolerance_rel=tolerance)
    assert not seen_past.any() and not agrees.any()


def test_a_mesh_with_no_triangle_left_is_an_error_and_not_written(tmp_path: Path) -> None:
    empty = PlyData(vertices=np.zeros((3, 3)), faces=np.zeros((0, 3), np.int64))
    with pytest.raises(StageError, match="carving removed the whole mesh"):
        write_mesh(tmp_path / "mesh.ply", empty, empty="x.ply: carving removed the whole mesh")
    assert not list(tmp_path.iterdir())
    one = PlyData(vertices=np.eye(3), faces=np.array([[0, 1, 2]]))
    assert write_mesh(tmp_path / "mesh.ply", one, empty="unused") == 1
    assert (tmp_path / "mesh.ply").is_file()
