"""PLY: write-then-read round trips, the exact layout the tree's writers rely on, bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.errors import InputError, OutputExistsError
from shared.formats.ply import PlyData, ply_bytes, read_ply, vertex_ply_header, write_ply


def test_ply_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    ply = PlyData(
        vertices=rng.normal(size=(5, 3)),
        normals=rng.normal(size=(5, 3)),
        colors=rng.integers(0, 255, (5, 3)).astype(np.uint8),
        faces=np.array([[0, 1, 2], [2, 3, 4]]),
    )
    back = read_ply(write_ply(tmp_path / "a.ply", ply, comments=["frame W, metres"]))
    np.testing.assert_allclose(back.vertices, ply.vertices, rtol=1e-6)
    assert back.normals is not None and ply.normals is not None
    np.testing.assert_allclose(back.normals, ply.normals, rtol=1e-6)
    np.testing.assert_array_equal(back.colors, ply.colors)
    np.testing.assert_array_equal(back.faces, ply.faces)
    with pytest.raises(OutputExistsError):
        write_ply(tmp_path / "a.ply", ply)
    assert [p.name for p in tmp_path.iterdir()] == ["a.ply"]  # no temporary left behind


def test_points_with_a_comment_have_the_layout_of_map_ply() -> None:
    points = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25]])
    data = ply_bytes(PlyData(vertices=points), comments=["landmarks, session frame S, metres"])
    header, _, body = data.partition(b"end_header\n")
    assert header.decode().splitlines() == [
        "ply",
        "format binary_little_endian 1.0",
        "comment landmarks, session frame S, metres",
        "element vertex 2",
        "property float x",
        "property float y",
        "property float z",
    ]
    np.testing.assert_array_equal(np.frombuffer(body, "<f4").reshape(-1, 3), points)


def test_a_coloured_mesh_is_packed_15_bytes_a_vertex_13_a_triangle(tmp_path: Path) -> None:
    vertices = np.arange(12, dtype=float).reshape(4, 3)
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], np.uint8)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    data = ply_bytes(PlyData(vertices=vertices, colors=colours, faces=faces))
    header, _, body = data.partition(b"end_header\n")
    assert b"element face 2\nproperty list uchar int vertex_indices\n" in header
    assert len(body) == 4 * 15 + 2 * 13
    assert body[12:15] == bytes([255, 0, 0])
    back = read_ply(write_ply(tmp_path / "m.ply", PlyData(vertices, colors=colours, faces=faces)))
    assert back.normals is None
    np.testing.assert_array_equal(back.faces, faces)


def test_bad_ply_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such PLY"):
        read_ply(tmp_path / "none.ply")
    (tmp_path / "t.ply").write_bytes(b"hello")
    with pytest.raises(InputError, match="not a PLY"):
        read_ply(tmp_path / "t.ply")
    (tmp_path / "a.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(InputError, match=r"a\.ply: PLY format 'ascii' \(expected binary_little"):
        read_ply(tmp_path / "a.ply")
    (tmp_path / "b.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quad x\nend_header\n"
    )
    with pytest.raises(InputError, match="unknown PLY property type 'quad'"):
        read_ply(tmp_path / "b.ply")
    with pytest.raises(ValueError, match="single lines"):
        ply_bytes(PlyData(vertices=np.zeros((1, 3))), comments=["two\nlines"])


def test_vertex_header_is_read_without_the_body(tmp_path: Path) -> None:
    cloud = PlyData(vertices=np.zeros((7, 3)), colors=np.zeros((7, 3), np.uint8))
    path = write_ply(tmp_path / "c.ply", cloud, comments=["frame W"])
    lines, count, offset = vertex_ply_header(path)
    assert count == 7
    assert lines[0] == b"ply" and b"element vertex 7" in lines and b"end_header" not in lines
    assert path.stat().st_size - offset == 7 * 15  # float32 x, y, z and uchar r, g, b
    mesh = PlyData(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match="one vertex element"):
        vertex_ply_header(write_ply(tmp_path / "m.ply", mesh))
    (tmp_path / "x.ply").write_bytes(b"solid x\n")
    with pytest.raises(InputError, match="not a PLY file"):
        vertex_ply_header(tmp_path / "x.ply")
