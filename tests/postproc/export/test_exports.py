"""Every export of a tiny run, read back with an independent reader."""

from __future__ import annotations

import csv
import json
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from postproc.export.stage import ExportOptions, export_formats, run
from shared.errors import InputError, OutputExistsError

from .conftest import HEIGHT, PARAMS, SEABED_Z, WIDTH, RunFixture, build_run

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def exported(run_folder: RunFixture, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("export") / "export"
    formats = ("glb", "gltf", "las", "laz", "colmap-text", "nerfstudio", "camera-csv")
    written = export_formats(ExportOptions(formats=formats), run_folder.root, out)
    assert set(written) == set(formats)
    return out


def _gltf_json_and_buffer(path: Path) -> tuple[dict[str, Any], bytes]:
    """The JSON document and the buffer of a .glb or .gltf, read as the glTF 2.0 spec
    lays them out (GLB: 12-byte header, then JSON and BIN chunks)."""
    data = path.read_bytes()
    if path.suffix == ".gltf":
        document = json.loads(data)
        return document, (path.parent / document["buffers"][0]["uri"]).read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A  # "JSON"
    document = json.loads(data[20 : 20 + json_length])
    bin_length, bin_type = struct.unpack_from("<II", data, 20 + json_length)
    assert bin_type == 0x004E4942  # "BIN"
    start = 28 + json_length
    return document, data[start : start + bin_length]


def _accessor(document: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    """An accessor's values as floats (normalised integers divided by their maximum)."""
    types = {5121: "u1", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
    sizes = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    dtype = np.dtype(types[accessor["componentType"]])
    n = accessor["count"] * sizes[accessor["type"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    values = np.frombuffer(blob, dtype, count=n, offset=start).reshape(accessor["count"], -1)
    if accessor.get("normalized"):
        return values / np.iinfo(dtype).max
    return values.astype(float)


@pytest.mark.parametrize("name", ["mesh.glb", "mesh.gltf"])
def test_gltf_holds_the_full_mesh_upright_with_colours(
    exported: Path, run_folder: RunFixture, name: str
) -> None:
    import trimesh

    mesh = run_folder.mesh
    # trimesh's loader: the geometry, glTF's y up (world (x, y, z) stored as (x, z, -y)).
    scene = trimesh.load(exported / name, process=False)
    assert isinstance(scene, trimesh.Scene)
    (loaded,) = scene.geometry.values()
    back = np.asarray(loaded.vertices)
    world = np.column_stack((back[:, 0], -back[:, 2], back[:, 1]))
    np.testing.assert_allclose(world, mesh.vertices, atol=2e-6)
    np.testing.assert_array_equal(np.asarray(loaded.faces), mesh.faces)
    # The colours by hand: COLOR_0 is linear RGB (the spec), ours are sRGB.
    document, blob = _gltf_json_and_buffer(exported / name)
    primitive = document["meshes"][0]["primitives"][0]
    linear = _accessor(document, blob, primitive["attributes"]["COLOR_0"])
    np.testing.assert_array_equal(linear[:, 3], 1.0)
    linear = linear[:, :3]
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    assert mesh.colors is not None
    np.testing.assert_allclose(srgb * 255, mesh.colors, atol=0.05)
    # The spec's alignment rule: vertex attribute elements on 4-byte boundaries.
    sizes = {5121: 1, 5123: 2, 5125: 4, 5126: 4}
    for index in primitive["attributes"].values():
        accessor = document["accessors"][index]
        view = document["bufferViews"][accessor["bufferView"]]
        element = sizes[accessor["componentType"]] * int(accessor["type"][-1])
        assert view.get("byteOffset", 0) % 4 == 0 and element % 4 == 0
    normals = _accessor(document, blob, primitive["attributes"]["NORMAL"])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    # The flat seabed's normals point up (glTF +y).
    seabed = np.isclose(mesh.vertices[:, 2], SEABED_Z) & (np.abs(mesh.vertices[:, 0]) > 1.5)
    np.testing.assert_allclose(normals[seabed, 1], 1.0, atol=1e-6)


@pytest.mark.parametrize("name", ["points.las", "points.laz"])
def test_las_keeps_every_point_to_the_millimetre(
    exported: Path, run_folder: RunFixture, name: str
) -> None:
    import laspy  # type: ignore[import-untyped]  # laspy ships no type information

    las = laspy.read(exported / name)
    points = np.column_stack((las.x, las.y, las.z))
    np.testing.assert_allclose(points, run_folder.fused.vertices, atol=0.0005 + 1e-9)
    rgb = np.column_stack((las.red, las.green, las.blue))
    assert run_folder.fused.colors is not None
    np.testing.assert_array_equal(rgb, run_folder.fused.colors.astype(np.uint16) * 257)
    if name.endswith(".las"):
        # The public header read by hand (LAS 1.4 spec): scales at byte 131, offsets at
        # 155, the 64-bit point count at 247.
        raw = (exported / name).read_bytes()
        assert raw[:4] == b"LASF" and raw[24:26] == bytes([1, 4])
        assert struct.unpack_from("<3d", raw, 131) == (0.001, 0.001, 0.001)
        offsets = np.array(struct.unpack_from("<3d", raw, 155))
        np.testing.assert_array_equal(offsets, np.floor(run_folder.fused.vertices.min(0)))
        assert struct.unpack_from("<Q", raw, 247)[0] == len(run_folder.fused.vertices)
    else:
        assert (exported / name).stat().st_size < (exported / "points.las").stat().st_size


def test_colmap_text_model_reads_back_as_the_binary_one(
    exported: Path, run_folder: RunFixture
) -> None:
    import pycolmap

    text = pycolmap.Reconstruction(str(exported / "colmap" / "sparse" / "0"))
    binary = pycolmap.Reconstruction(str(run_folder.root / "sfm" / "sparse" / "0"))
    assert (exported / "colmap" / "sparse" / "0" / "images.txt").is_file()
    assert text.num_reg_images() == binary.num_reg_images() == 6
    assert text.num_points3D() == binary.num_points3D() > 100
    for image_id, image in binary.images.items():
        other = text.images[image_id]
        assert other.name == image.name
        copied = exported / "colmap" / "images" / image.name
        assert copied.is_file() and not copied.is_symlink()
        assert copied.read_bytes() == (run_folder.root / "sfm" / "images" / image.name).read_bytes()
        np.testing.assert_allclose(
            other.cam_from_world().matrix(), image.cam_from_world().matrix(), atol=1e-12
        )
    np.testing.assert_allclose(text.cameras[1].params, PARAMS)


def _nerfstudio_pixel(
    document: dict[str, Any], frame: dict[str, Any], point: np.ndarray
) -> np.ndarray:
    """Project a world point the way nerfstudio's docs define its data: c2w with OpenGL
    axes (camera looks along -z, y up), OPENCV distortion, pixel centres at +0.5."""
    c2w = np.array(frame["transform_matrix"])
    p = np.linalg.inv(c2w) @ np.r_[point, 1.0]
    x, y = p[0] / -p[2], -p[1] / -p[2]
    k1, k2, p1, p2 = (document[k] for k in ("k1", "k2", "p1", "p2"))
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.array(
        [document["fl_x"] * xd + document["cx"], document["fl_y"] * yd + document["cy"]]
    )


def test_nerfstudio_cameras_project_points_where_colmap_saw_them(
    exported: Path, run_folder: RunFixture
) -> None:
    import cv2
    import pycolmap

    folder = exported / "nerfstudio"
    document = json.loads((folder / "transforms.json").read_text())
    assert document["camera_model"] == "OPENCV"
    assert (document["w"], document["h"]) == (WIDTH, HEIGHT)
    assert (folder / document["ply_file_path"]).is_file()
    rec = pycolmap.Reconstruction(str(run_folder.root / "sfm" / "sparse" / "0"))
    by_path = {f["file_path"]: f for f in document["frames"]}
    assert len(by_path) == 6
    checked = 0
    for image in rec.images.values():
        frame = by_path[f"images/{image.name}"]
        picture = cv2.imread(str(folder / frame["file_path"]))
        assert picture is not None
        assert picture.shape[:2] == (document["h"], document["w"])
        camera = rec.cameras[image.camera_id]
        for p2d in image.points2D:
            if not p2d.has_point3D():
                continue
            xyz = np.asarray(rec.points3D[p2d.point3D_id].xyz)
            ours = _nerfstudio_pixel(document, frame, xyz)
            exact = camera.img_from_cam(image.cam_from_world() * xyz)
            np.testing.assert_allclose(ours, exact, atol=1e-6)
            # The observation had 0.3 px noise.
            assert np.linalg.norm(ours - np.asarray(p2d.xy)) < 2.0
            checked += 1
    assert checked > 200


def test_camera_reference_positions_angles_and_accuracies(
    exported: Path, run_folder: RunFixture
) -> None:
    from scipy.spatial.transform import Rotation

    folder = exported / "camera_reference"
    with (folder / "cameras.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6
    truth = {name.replace("/", "__"): pose for name, pose in
             zip(run_folder.names, run_folder.worlds_from_cam, strict=True)}  # fmt: skip
    for row in rows:
        pose = truth[row["label"]]
        position = [float(row[k]) for k in ("x_m", "y_m", "z_m")]
        np.testing.assert_allclose(position, pose[:3, 3], atol=1e-4)
        # Photogrammetry's omega-phi-kappa: R = Rx(omega) Ry(phi) Rz(kappa) (intrinsic
        # XYZ) maps camera axes x right, y up, z back to the world.
        angles = [float(row[k]) for k in ("omega_deg", "phi_deg", "kappa_deg")]
        R = Rotation.from_euler("XYZ", angles, degrees=True).as_matrix()
        np.testing.assert_allclose(R @ np.diag([1, -1, -1]), pose[:3, :3], atol=1e-6)
        sigmas = [float(row[k]) for k in ("x_sigma_m", "y_sigma_m", "z_sigma_m")]
        assert all(0.005 <= s < 0.05 for s in sigmas)
        assert row["accuracy_source"].startswith("reprojection")
        assert (folder / "images" / row["label"]).is_file()
    xml = (folder / "calibration.xml").read_text()
    assert "<f>152.000000</f>" in xml and "<b1>-2.000000</b1>" in xml


FISHEYE = (150.0, 151.0, 128.5, 96.0, 0.05, -0.02, 0.004, -0.001)  # fx fy cx cy k1-k4


@pytest.mark.parametrize(("model", "params"), [("OPENCV", PARAMS), ("OPENCV_FISHEYE", FISHEYE)])
def test_undistorted_image_puts_a_point_where_the_pinhole_says(
    model: str, params: list[float]
) -> None:
    import cv2

    from postproc.export.camera_reference import undistort_maps
    from postproc.export.cameras import ExportCamera, project

    camera = ExportCamera(
        name="a.png", camera_id=1, model=model, params=tuple(params), width=WIDTH,
        height=HEIGHT, cam_from_world=np.eye(4), points_m=np.zeros((0, 3)),
        pixels=np.zeros((0, 2)),
    )  # fmt: skip
    point = np.array([[0.55, -0.4, 1.0]])  # far off-centre: distortion moves it a lot
    distorted = project(camera, point, np.eye(4))[0]
    K = camera.intrinsic_matrix()
    pinhole = (K @ point[0])[:2] / point[0, 2]
    assert np.linalg.norm(distorted - pinhole) > 5.0
    image = np.zeros((HEIGHT, WIDTH), np.float32)
    vv, uu = np.mgrid[0:HEIGHT, 0:WIDTH]
    # A blob at the distorted pixel (COLMAP convention: pixel centres at +0.5).
    image = np.exp(-((uu + 0.5 - distorted[0]) ** 2 + (vv + 0.5 - distorted[1]) ** 2) / 2.0)
    map_x, map_y = undistort_maps(camera)
    flat = cv2.remap(image.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR)
    w = flat / flat.sum()
    centroid = np.array([(w * (uu + 0.5)).sum(), (w * (vv + 0.5)).sum()])
    np.testing.assert_allclose(centroid, pinhole, atol=0.15)


def test_opk_of_a_camera_looking_straight_down_is_zero() -> None:
    from postproc.export.camera_reference import opk_deg

    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # x east, image down = south, looking down
    np.testing.assert_allclose(opk_deg(pose), (0.0, 0.0, 0.0), atol=1e-12)


def test_existing_exports_are_kept(exported: Path, run_folder: RunFixture) -> None:
    before = (exported / "mesh.glb").read_bytes()
    with pytest.raises(OutputExistsError, match=r"mesh\.glb"):
        run(ExportOptions(formats=("glb",)), run_folder.root, exported)
    assert (exported / "mesh.glb").read_bytes() == before


def test_missing_inputs_are_named(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such run folder"):
        run(ExportOptions(formats=("glb",)), tmp_path / "nope", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a run folder"):
        run(ExportOptions(formats=("glb",)), tmp_path / "empty", tmp_path / "out")
    fixture = build_run(tmp_path / "run")
    (fixture.root / "dense" / "mesh.ply").unlink()
    with pytest.raises(InputError, match=r"no mesh \(expected dense/mesh.ply\)"):
        run(ExportOptions(formats=("glb",)), fixture.root, tmp_path / "out")
    (fixture.root / "sfm" / "images" / fixture.names[2]).resolve().unlink()
    with pytest.raises(InputError, match="1 of 6 images the model names are missing"):
        run(ExportOptions(formats=("colmap-text",)), fixture.root, tmp_path / "out2")
    with pytest.raises(ValueError, match="unknown export format"):
        ExportOptions(formats=("obj",))


def test_cli_exports_and_reports_errors_in_one_line(run_folder: RunFixture, tmp_path: Path) -> None:
    env = {"WRECKMAP_PROGRESS": "0", "PATH": ""}
    command = [sys.executable, "-m", "postproc.cli", "export", str(run_folder.root)]
    done = subprocess.run(
        [*command, "--format", "glb", "laz", "--out", str(tmp_path / "x")],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "x" / "mesh.glb").is_file() and (tmp_path / "x" / "points.laz").is_file()
    failed = subprocess.run(
        [*command, "--format", "ortho", "--georef-target", "grid_a", "--out", str(tmp_path / "y")],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=120,
    )  # fmt: skip
    assert failed.returncode == 1
    assert failed.stderr.strip().count("\n") == 0
    assert "--easting-m" in failed.stderr


def test_a_stage_folder_is_a_run_too(run_folder: RunFixture, tmp_path: Path) -> None:
    """`export SFM_DIR` finds sparse/0 and images/ inside it."""
    import pycolmap

    out = run(ExportOptions(formats=("colmap-text",)), run_folder.root / "sfm", tmp_path / "x")
    rec = pycolmap.Reconstruction(str(out / "colmap" / "sparse" / "0"))
    assert rec.num_reg_images() == 6


def test_nerfstudio_fisheye_intrinsics() -> None:
    from postproc.export.cameras import ExportCamera
    from postproc.export.nerfstudio import transforms_document

    camera = ExportCamera(
        name="s/1.png", camera_id=1, model="OPENCV_FISHEYE", params=FISHEYE, width=WIDTH,
        height=HEIGHT, cam_from_world=np.eye(4), points_m=np.zeros((0, 3)),
        pixels=np.zeros((0, 2)),
    )  # fmt: skip
    document = transforms_document([camera], with_points=False)
    assert document["camera_model"] == "OPENCV_FISHEYE"
    assert [document[k] for k in ("k1", "k2", "k3", "k4")] == list(FISHEYE[4:])
    assert "p1" not in document and "ply_file_path" not in document
    # Identity T_W_C (OpenCV axes) in OpenGL axes: y and z flipped.
    np.testing.assert_array_equal(
        document["frames"][0]["transform_matrix"], np.diag([1, -1, -1, 1])
    )
