"""COLMAP depth/normal map files, fusion visibility files and known-pose models."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from postproc.dense.colmap_io import (
    DenseWorkspace,
    FusionVisibility,
    array_bytes,
    parse_array,
    read_array,
    read_fusion_visibility,
    read_pinhole_views,
    write_array,
    write_known_pose_model,
)
from shared.errors import InputError, OutputExistsError


def test_layout_matches_colmap_mat() -> None:
    # COLMAP's mvs::Mat: "W&H&C&" then float32 at index slice*W*H + row*W + col.
    normals = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)  # H=2, W=3, C=3
    data = array_bytes(normals)
    header = b"3&2&3&"
    assert data.startswith(header)
    values = struct.unpack(f"<{2 * 3 * 3}f", data[len(header) :])
    for row in range(2):
        for col in range(3):
            for ch in range(3):
                assert values[ch * 3 * 2 + row * 3 + col] == normals[row, col, ch]


@pytest.mark.parametrize("shape", [(5, 7), (4, 6, 3)])
def test_round_trip(tmp_path: Path, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(1)
    array = rng.normal(size=shape).astype(np.float32)
    path = write_array(tmp_path / "x.bin", array)
    back = read_array(path)
    assert back.shape == shape and back.dtype == np.float32
    np.testing.assert_array_equal(back, array)
    with pytest.raises(OutputExistsError):
        write_array(path, array)
    write_array(path, array * 2, overwrite=True)
    np.testing.assert_array_equal(read_array(path), array * 2)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"nonsense", "header"),
        (b"3&x&1&" + bytes(12), "bad header field"),
        (b"3&2&1&" + bytes(20), "24 bytes"),
        (b"0&2&1&", "0 bytes"),
    ],
)
def test_bad_maps_are_refused(data: bytes, message: str) -> None:
    with pytest.raises(InputError, match=message):
        parse_array(data, name="bad.bin")


def test_missing_map(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such depth/normal map"):
        read_array(tmp_path / "none.bin")


def test_bad_array_shape() -> None:
    with pytest.raises(ValueError, match="shape"):
        array_bytes(np.zeros((2, 2, 2, 2)))


def test_workspace_paths(tmp_path: Path) -> None:
    ws = DenseWorkspace(tmp_path)
    assert ws.depth_map_path("a/b.png") == tmp_path / "stereo/depth_maps/a/b.png.geometric.bin"
    assert ws.normal_map_path("c.png", "photometric").name == "c.png.photometric.bin"
    assert not ws.is_undistorted()


def _vis_bytes(entries: list[list[int]]) -> bytes:
    out = struct.pack("<Q", len(entries))
    for e in entries:
        out += struct.pack(f"<I{len(e)}I", len(e), *e)
    return out


def test_fusion_visibility(tmp_path: Path) -> None:
    path = tmp_path / "fused.ply.vis"
    path.write_bytes(_vis_bytes([[0, 2], [1], [3, 4, 5]]))
    vis = read_fusion_visibility(path)
    assert [v.tolist() for v in vis] == [[0, 2], [1], [3, 4, 5]]
    assert vis.counts.tolist() == [2, 1, 3] and vis[2].tolist() == [3, 4, 5]
    assert vis.point_of_each_image().tolist() == [0, 0, 1, 2, 2, 2]
    assert [v.tolist() for v in vis.subset(np.array([2, 0]))] == [[3, 4, 5], [0, 2]]
    assert vis.subset(np.array([], np.int64)).counts.tolist() == []
    packed = FusionVisibility.from_lists([[0, 2], [1], [3, 4, 5]])
    assert packed.offsets.tolist() == vis.offsets.tolist()
    assert packed.images.tolist() == vis.images.tolist()
    path.write_bytes(_vis_bytes([[], [7]]))
    assert [v.tolist() for v in read_fusion_visibility(path)] == [[], [7]]
    # Written back as COLMAP lays it out.
    assert vis.to_bytes() == _vis_bytes([[0, 2], [1], [3, 4, 5]])
    assert FusionVisibility.from_lists([[], [7]]).to_bytes() == _vis_bytes([[], [7]])
    assert FusionVisibility.from_lists([]).to_bytes() == _vis_bytes([])
    path.write_bytes(_vis_bytes([[0, 2], [1]])[:-4])
    with pytest.raises(InputError, match="truncated"):
        read_fusion_visibility(path)
    path.write_bytes(_vis_bytes([[0]]) + bytes(4))
    with pytest.raises(InputError, match="past the last point"):
        read_fusion_visibility(path)
    path.write_bytes(b"abc")
    with pytest.raises(InputError, match="bad size"):
        read_fusion_visibility(path)
    with pytest.raises(InputError, match="no fusion visibility"):
        read_fusion_visibility(tmp_path / "none.vis")


def test_known_pose_model_reads_back(tmp_path: Path) -> None:
    poses = []
    for k in range(3):
        pose = np.eye(4)
        pose[0, 3] = -0.5 * k  # camera k at x = 0.5 k
        poses.append(pose)
    points = np.array([[0.0, 0.0, 3.0], [0.5, 0.2, 4.0], [9.0, 9.0, 9.0]])
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    observations = []
    for pose in poses:
        seen = []
        for p in range(2):
            pc = pose[:3, :3] @ points[p] + pose[:3, 3]
            u, v, w = K @ pc
            seen.append((p, u / w, v / w))
        observations.append(seen)
    model = write_known_pose_model(
        tmp_path / "sparse", camera_model="PINHOLE", camera_params=[100, 100, 50, 40],
        size=(100, 80), image_names=["a.png", "b.png", "c.png"], cams_from_world=poses,
        points_m=points, observations=observations,
    )  # fmt: skip
    views = read_pinhole_views(model)
    assert [v.name for v in views] == ["a.png", "b.png", "c.png"]
    np.testing.assert_allclose(views[1].centre_m, [0.5, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(views[0].K, K)
    # Point 2 has no observation and is left out; the others are seen by all three.
    assert len(views[2].points_m) == 2
    np.testing.assert_allclose(np.sort(views[0].point_depths_m()), [3.0, 4.0])
    with pytest.raises(OutputExistsError):
        write_known_pose_model(
            model, camera_model="PINHOLE", camera_params=[100, 100, 50, 40], size=(100, 80),
            image_names=["a.png"], cams_from_world=poses[:1],
        )  # fmt: skip


def test_views_refuse_distorted_or_missing_model(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no COLMAP model"):
        read_pinhole_views(tmp_path)
    model = write_known_pose_model(
        tmp_path / "m", camera_model="OPENCV", camera_params=[100, 100, 50, 40, 0.1, 0, 0, 0],
        size=(100, 80), image_names=["a.png"], cams_from_world=[np.eye(4)],
    )  # fmt: skip
    with pytest.raises(InputError, match="OPENCV"):
        read_pinhole_views(model)
