"""The dense stage end to end on a tiny rendered scene: accuracy, resuming, errors, CLI."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from postproc.dense.carving import DepthView, carved_vertices
from postproc.dense.colmap_io import (
    DenseWorkspace,
    read_array,
    read_fusion_visibility,
    read_pinhole_views,
    write_known_pose_model,
)
from postproc.dense.evaluate import distance_to_mesh
from postproc.dense.fusion import FusionOptions, fuse
from postproc.dense.meshing import MeshingOptions
from postproc.dense.options import ViewSelectionOptions
from postproc.dense.stage import (
    DenseOptions,
    choose_backend,
    read_depth_map,
    run,
    stereo_partners,
    undistort,
    undistort_missing,
)
from shared.errors import InputError, OutputExistsError, StageError
from shared.formats.ply import read_ply
from sim.mesh import TruthMesh, scene_mesh
from sim.scene import WreckScene

from .conftest import CAMERA, SyntheticSfm, build_sfm, hull_poses

REPO = Path(__file__).resolve().parents[3]


def _triangles(mesh: TruthMesh) -> npt.NDArray[np.int64]:
    # The truth mesh stores int32 indices; distance_to_mesh is annotated for int64 but
    # takes any integer index array.
    return cast("npt.NDArray[np.int64]", mesh.triangles)


def quick_options(**kwargs: object) -> DenseOptions:
    """Single-threaded fusion and meshing (the test machine is shared), octree depth <= 8,
    and the reference spacing these 7 views were laid out for (views 0, 2, 4 and 6 get a
    depth map; the default since stop 41 spaces references closer)."""
    options: dict[str, object] = {
        "view_selection": ViewSelectionOptions(min_baseline_rel=0.15, min_rotation_deg=10.0),
        **kwargs,
    }
    return DenseOptions(
        fusion=FusionOptions(num_threads=1),
        meshing=MeshingOptions(num_threads=1, max_depth=8),
        **options,  # type: ignore[arg-type]
    )


@pytest.fixture(scope="module")
def sfm(tmp_path_factory: pytest.TempPathFactory, coarse_scene: WreckScene) -> SyntheticSfm:
    return build_sfm(tmp_path_factory.mktemp("sfm") / "sfm", coarse_scene, hull_poses(7))


@pytest.fixture(scope="module")
def dense_dir(tmp_path_factory: pytest.TempPathFactory, sfm: SyntheticSfm) -> Path:
    out = tmp_path_factory.mktemp("dense") / "dense"
    result = run(quick_options(), sfm.folder, out)
    assert result == out / "mesh.ply"
    return out


def test_outputs_are_close_to_the_truth(dense_dir: Path, coarse_scene: WreckScene) -> None:
    truth = scene_mesh(coarse_scene)
    fused = read_ply(dense_dir / "fused.ply")
    assert len(fused.vertices) > 5000
    d = distance_to_mesh(fused.vertices, truth.vertices, _triangles(truth))
    # Measured: 99.4 % within 5 cm, 91 % within 2 cm (mesh vertices: 100 %, 97 %), with
    # depth maps for 3 reference views of 7, fusion's min_num_pixels 1 and the mesh from
    # points seen twice (all 7 views, min_num_pixels 2: 99.97 / 91 %, mesh 100 / 93 %).
    assert np.mean(d < 0.05) > 0.98
    assert np.mean(d < 0.02) > 0.8
    mesh = read_ply(dense_dir / "mesh.ply")
    assert mesh.faces is not None and len(mesh.faces) > 5000
    d_mesh = distance_to_mesh(mesh.vertices, truth.vertices, _triangles(truth))
    assert np.mean(d_mesh < 0.05) > 0.97
    report = json.loads((dense_dir / "dense.json").read_text())
    assert report["backend"] == "cpu"
    # Cameras 0.3 m apart, 2.5-3 m from the hull: a reference once the nearest one is
    # 0.15 x depth (0.38-0.45 m) away, i.e. every second camera: 0, 2, 4, 6.
    assert report["images"] == 7 and report["reference_images"] == 4
    assert report["depth_maps"]["computed"] == 4
    assert 6 <= report["mesh"]["octree_depth"] <= 11
    # Carved: no vertex left where two depth maps saw past it, and Poisson's mesh gone.
    assert report["mesh"]["vertices"] == len(mesh.vertices)
    assert "carved_vertices" in report["mesh"] and "carving_s" in report["timings"]
    ws = DenseWorkspace(dense_dir / "workspace")
    views = {v.name: v for v in read_pinhole_views(ws.sparse_dir)}
    depth_views = [
        DepthView(read_array(ws.depth_map_path(n)), views[n].K, views[n].cam_from_world)
        for n in references(dense_dir)
    ]
    assert not carved_vertices(mesh.vertices, depth_views, tolerance_rel=0.02, min_views=2).any()
    assert not list(dense_dir.glob("*poisson*"))


def references(dense_dir: Path) -> list[str]:
    """The reference images: those fusion read (fusion.cfg, one name a line)."""
    cfg = DenseWorkspace(dense_dir / "workspace").stereo_dir / "fusion.cfg"
    return cfg.read_text().split()


def test_workspace_is_colmaps(dense_dir: Path, sfm: SyntheticSfm) -> None:
    ws = DenseWorkspace(dense_dir / "workspace")
    assert ws.is_undistorted()
    chosen = references(dense_dir)
    assert chosen == [sfm.names[0], sfm.names[2], sfm.names[4], sfm.names[6]]
    for name in sfm.names:
        done = ws.depth_map_path(name).is_file() and ws.normal_map_path(name).is_file()
        assert done == (name in chosen)


def test_only_the_images_the_stereo_reads_are_undistorted(
    sfm: SyntheticSfm, tmp_path: Path
) -> None:
    # One partner a reference, best two cameras away (0.6 m at 2.7 m: 13 deg): the
    # references 0, 2, 4, 6 pair among themselves, and the odd images are never read.
    options = quick_options(make_mesh=False)
    options.neighbours.max_neighbours = 1
    options.neighbours.far_neighbours = 0
    options.neighbours.best_angle_deg = 14.0
    run(options, sfm.folder, tmp_path / "few")
    ws = DenseWorkspace(tmp_path / "few" / "workspace")
    views = read_pinhole_views(ws.sparse_dir)
    assert [v.name for v in views] == sfm.names  # the model keeps every image
    chosen = references(tmp_path / "few")
    partners = stereo_partners(options, views, [sfm.names.index(n) for n in chosen])
    read = set(chosen) | {views[j].name for p in partners for j in p}
    on_disk = {p.relative_to(ws.images_dir).as_posix() for p in ws.images_dir.rglob("*.png")}
    assert on_disk == read and len(read) < len(sfm.names)
    report = json.loads((tmp_path / "few" / "dense.json").read_text())
    assert report["undistorted_images"] == len(read)
    # The pixels of COLMAP's undistortion of every image, to its rounding.
    undistort(options, sfm.folder / "sparse", sfm.folder / "images", tmp_path / "all")
    for name in read:
        mine = cv2.imread(str(ws.images_dir / name), cv2.IMREAD_UNCHANGED)
        full = cv2.imread(str(tmp_path / "all" / "images" / name), cv2.IMREAD_UNCHANGED)
        assert mine is not None and full is not None and mine.shape == full.shape
        diff = np.abs(mine.astype(np.int16) - full.astype(np.int16))
        assert diff.mean() < 0.01 and diff.max() <= 1, name
    # An image lost from the workspace is undistorted again on the next run.
    lost = sorted(read)[0]
    (ws.images_dir / lost).unlink()
    assert (
        undistort_missing(
            sfm.folder / "sparse", sfm.folder / "images", ws, [v for v in views if v.name in read]
        )
        == 1
    )
    assert (ws.images_dir / lost).is_file()
    assert not list(ws.images_dir.rglob(".*"))  # no temporary file left


def assert_visibility_is_the_workspaces(workspace: Path, ply: Path) -> None:
    """Each fused point projects into the images its `.vis` names (workspace order), onto
    a depth there that agrees with it (200 points drawn)."""
    views = read_pinhole_views(workspace / "sparse")
    fused = read_ply(ply)
    vis = read_fusion_visibility(ply.with_name(ply.name + ".vis"))
    assert len(vis) == len(fused.vertices)
    depths: dict[str, npt.NDArray[np.float32]] = {}
    rng = np.random.default_rng(0)
    for i in rng.choice(len(vis), 200, replace=False):
        for k in vis[i]:
            view = views[int(k)]
            pc = view.cam_from_world[:3, :3] @ fused.vertices[i] + view.cam_from_world[:3, 3]
            u, v, w = view.K @ pc
            assert w > 0 and 0 <= u / w < view.width and 0 <= v / w < view.height
            # A fused point averages pixels: one of the 3x3 around its projection made it.
            if view.name not in depths:
                depths[view.name] = read_depth_map(workspace, view.name)
            depth = depths[view.name]
            r, c = int(v / w), int(u / w)
            patch = depth[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2]
            assert np.any(np.abs(patch - pc[2]) < 0.03 * pc[2])


def test_fusion_visibility_follows_the_workspace_order(dense_dir: Path) -> None:
    # Colour correction takes camera ranges from fused.ply.vis by workspace image index.
    assert_visibility_is_the_workspaces(dense_dir / "workspace", dense_dir / "fused.ply")


def test_fusion_box_by_box_gives_the_cloud_of_one_call(dense_dir: Path, tmp_path: Path) -> None:
    ws = DenseWorkspace(dense_dir / "workspace")
    views = read_pinhole_views(ws.sparse_dir)
    chosen = references(dense_dir)
    refs = [k for k, v in enumerate(views) if v.name in chosen]
    one = fuse(
        FusionOptions(num_threads=1, max_tile_pixels=0), ws, views, refs, tmp_path / "one.ply"
    )
    assert one["tiles"] == 1
    budget = one["depth_pixels"] // 3
    boxes = fuse(
        FusionOptions(num_threads=1, max_tile_pixels=budget),
        ws,
        views,
        refs,
        tmp_path / "boxes.ply",
    )
    assert boxes["tiles"] >= 3 and boxes["depth_pixels"] == one["depth_pixels"]
    # Pixels fused across a cut become two points: a few more points, on the same surface.
    a = read_ply(tmp_path / "one.ply").vertices
    b = read_ply(tmp_path / "boxes.ply").vertices
    assert len(b) == boxes["points"] and len(a) == one["points"]
    print(len(a), len(b))
    assert len(a) <= len(b) < 1.05 * len(a)
    from scipy.spatial import cKDTree

    assert np.mean(cKDTree(a).query(b)[0] < 0.005) > 0.99
    assert np.mean(cKDTree(b).query(a)[0] < 0.005) > 0.99
    assert_visibility_is_the_workspaces(ws.root, tmp_path / "boxes.ply")
    assert references(dense_dir) == chosen  # the workspace's fusion.cfg is as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["one.ply", "one.ply.vis", "boxes.ply", "boxes.ply.vis"]
    )


def test_finished_run_is_not_redone(dense_dir: Path, sfm: SyntheticSfm) -> None:
    before = {p: p.stat().st_mtime_ns for p in dense_dir.iterdir() if p.is_file()}
    assert run(quick_options(), sfm.folder, dense_dir) == dense_dir / "mesh.ply"
    assert {p: p.stat().st_mtime_ns for p in dense_dir.iterdir() if p.is_file()} == before


def test_resumes_per_image(sfm: SyntheticSfm, tmp_path: Path) -> None:
    out = tmp_path / "dense"

    def interrupted(fn: Any, items: list[Any]) -> list[Any]:
        # Three depth maps computed, then the run is killed.
        for item in items[:3]:
            fn(item)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(quick_options(), sfm.folder, out, map_fn=interrupted)
    assert not out.exists()  # nothing under the final name
    run(quick_options(), sfm.folder, out)
    report = json.loads((out / "dense.json").read_text())
    assert report["depth_maps"]["computed"] == 1
    assert report["depth_maps"]["skipped"] == report["reference_images"] - 1 == 3
    assert (out / "mesh.ply").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dense"]  # no partial left
    # Other options: the result is refused, not returned as theirs; overwrite redoes all.
    with pytest.raises(OutputExistsError, match="other inputs or options"):
        run(quick_options(make_mesh=False), sfm.folder, out)
    run(quick_options(make_mesh=False), sfm.folder, out, overwrite=True)
    report = json.loads((out / "dense.json").read_text())
    assert report["depth_maps"]["computed"] == 4
    assert not (out / "mesh.ply").exists()


def test_without_view_selection_every_image_gets_maps(
    sfm: SyntheticSfm, dense_dir: Path, tmp_path: Path
) -> None:
    options = quick_options(make_mesh=False)
    options.view_selection.enabled = False
    run(options, sfm.folder, tmp_path / "all")
    report = json.loads((tmp_path / "all" / "dense.json").read_text())
    assert report["reference_images"] == report["depth_maps"]["computed"] == 7
    assert references(tmp_path / "all") == sfm.names
    # The selection keeps the surface: the references' cloud covers what all seven give
    # (fused points of the full run within 2 and 5 cm of the selected run's cloud).
    from scipy.spatial import cKDTree

    every = read_ply(tmp_path / "all" / "fused.ply").vertices
    chosen = read_ply(dense_dir / "fused.ply").vertices
    distances = cKDTree(chosen).query(every, distance_upper_bound=0.1)[0]
    print(np.mean(distances < 0.02), np.mean(distances < 0.05))
    assert np.mean(distances < 0.05) > 0.9


def test_colour_correction_writes_a_corrected_cloud(
    dense_dir: Path, sfm: SyntheticSfm, tmp_path: Path
) -> None:
    out = tmp_path / "dense"
    options = quick_options(colour_correction=True, make_mesh=False)
    options.colour.attenuation_per_m = (0.40, 0.13, 0.11)
    options.colour.backscatter = (0.02, 0.13, 0.16)
    run(options, sfm.folder, out)
    raw = read_ply(out / "fused.ply")
    fixed = read_ply(out / "fused_corrected.ply")
    np.testing.assert_array_equal(raw.vertices, fixed.vertices)
    # The simulated water turns the wreck blue-green; corrected, red comes back.
    assert raw.colors is not None and fixed.colors is not None
    ratio_before = raw.colors[:, 0].mean() / raw.colors[:, 2].mean()
    ratio_after = fixed.colors[:, 0].mean() / fixed.colors[:, 2].mean()
    assert ratio_after > 1.5 * ratio_before
    report = json.loads((out / "dense.json").read_text())
    assert report["colour"]["estimated"] is False


def test_missing_inputs(tmp_path: Path, sfm: SyntheticSfm) -> None:
    with pytest.raises(InputError, match="no such SfM folder"):
        run(quick_options(), tmp_path / "none", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no COLMAP model"):
        run(quick_options(), tmp_path / "empty", tmp_path / "out")
    # A model whose images are elsewhere.
    shutil.copytree(sfm.folder / "sparse", tmp_path / "noimages" / "model")
    with pytest.raises(InputError, match="no images for the model"):
        run(quick_options(), tmp_path / "noimages", tmp_path / "out")
    # Some images missing.
    shutil.copytree(sfm.folder, tmp_path / "partial")
    (tmp_path / "partial" / "images" / sfm.names[2]).unlink()
    with pytest.raises(InputError, match=f"1 of 7 images .* missing \\(first: {sfm.names[2]}\\)"):
        run(quick_options(), tmp_path / "partial", tmp_path / "out")
    # A model with no registered image.
    write_known_pose_model(
        tmp_path / "unregistered" / "sparse", camera_model="PINHOLE",
        camera_params=[100, 100, 50, 40], size=(100, 80), image_names=[], cams_from_world=[],
    )  # fmt: skip
    with pytest.raises(InputError, match="no registered images"):
        run(quick_options(), tmp_path / "unregistered", tmp_path / "out")


def test_model_without_sparse_points_cannot_fuse(tmp_path: Path, sfm: SyntheticSfm) -> None:
    folder = tmp_path / "sfm"
    shutil.copytree(sfm.folder / "images", folder / "images")
    write_known_pose_model(
        folder / "sparse", camera_model="OPENCV",
        camera_params=[CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, CAMERA.k1, CAMERA.k2,
                       CAMERA.p1, CAMERA.p2],
        size=(CAMERA.width, CAMERA.height), image_names=sfm.names,
        cams_from_world=[np.linalg.inv(p) for p in sfm.worlds_from_cam],
    )  # fmt: skip
    options = quick_options(fallback_depth_range_m=(1.5, 5.0))
    # With min_num_pixels 1 one image's depths fuse on their own; two images must agree
    # for fusion to need the sparse points that tell it which images overlap.
    options.fusion.min_num_pixels = 2
    with pytest.raises(StageError, match="no points"):
        run(options, folder, tmp_path / "out")


def test_a_half_or_foreign_folder_is_refused(
    tmp_path: Path, dense_dir: Path, sfm: SyntheticSfm
) -> None:
    out = tmp_path / "dense"
    shutil.copytree(dense_dir, out)
    (out / "dense.json").unlink()
    with pytest.raises(OutputExistsError, match="holds other files, not a complete dense"):
        run(quick_options(max_image_size_px=128), sfm.folder, out)
    assert (out / "mesh.ply").is_file()
    broken = tmp_path / "broken"
    (broken / "workspace" / "images").mkdir(parents=True)
    with pytest.raises(OutputExistsError, match="not a complete dense folder"):
        run(quick_options(), sfm.folder, broken)


def test_backend_choice() -> None:
    assert choose_backend("auto", has_cuda=False) == "cpu"
    assert choose_backend("auto", has_cuda=True) == "patchmatch"
    assert choose_backend("cpu", has_cuda=True) == "cpu"
    with pytest.raises(StageError, match="needs pycolmap built with CUDA"):
        choose_backend("patchmatch", has_cuda=False)
    with pytest.raises(ValueError, match="backend must be"):
        choose_backend("magic", has_cuda=False)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, WRECKMAP_PROGRESS="0")
    return subprocess.run(
        [sys.executable, "-m", "postproc.cli", "dense", *args],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip


def test_cli_runs_and_reports_errors(tmp_path: Path, sfm: SyntheticSfm) -> None:
    done = _cli(str(sfm.folder), "--out", str(tmp_path / "d"), "--max-image-size", "128",
                "--threads", "1", "--octree-depth", "7")  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(tmp_path / "d" / "mesh.ply")
    assert len(read_ply(tmp_path / "d" / "mesh.ply").faces) > 500  # type: ignore[arg-type]
    report = json.loads((tmp_path / "d" / "dense.json").read_text())
    assert report["options"]["max_image_size_px"] == 128
    assert report["mesh"]["octree_depth"] == 7
    failed = _cli(str(tmp_path / "nothing"), "--out", str(tmp_path / "e"))
    assert failed.returncode == 1
    assert failed.stderr.strip().splitlines() == [
        f"wreckmap-post: error: {tmp_path / 'nothing'}: no such SfM folder"
    ]
    helped = _cli("--help")
    assert helped.returncode == 0 and "--max-image-size" in helped.stdout


@pytest.mark.gpu
def test_patchmatch_backend_on_gpu(
    sfm: SyntheticSfm, tmp_path: Path, coarse_scene: WreckScene
) -> None:
    import pycolmap

    assert pycolmap.has_cuda, "this test needs pycolmap built with CUDA"
    run(quick_options(backend="patchmatch"), sfm.folder, tmp_path / "dense")
    report = json.loads((tmp_path / "dense" / "dense.json").read_text())
    assert report["backend"] == "patchmatch"
    truth = scene_mesh(coarse_scene)
    fused = read_ply(tmp_path / "dense" / "fused.ply")
    d = distance_to_mesh(fused.vertices, truth.vertices, _triangles(truth))
    assert np.mean(d < 0.05) > 0.9


def test_mesh_input_keeps_points_seen_twice(tmp_path: Path) -> None:
    from postproc.dense.stage import supported_points
    from shared.formats.ply import PlyData, write_ply

    points = np.arange(12, dtype=np.float64).reshape(4, 3)
    colors = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]], np.uint8)
    write_ply(tmp_path / "fused.ply", PlyData(vertices=points, colors=colors))
    seen_by = [[0], [0, 2], [1], [1, 2, 3]]
    values = [v for images in seen_by for v in (len(images), *images)]
    vis = tmp_path / "fused.ply.vis"
    vis.write_bytes(np.uint64(4).tobytes() + np.array(values, "<u4").tobytes())
    out = supported_points(tmp_path / "fused.ply", vis, tmp_path / "s.ply", min_images=2)
    kept = read_ply(out)
    np.testing.assert_allclose(kept.vertices, points[[1, 3]])
    np.testing.assert_array_equal(kept.colors, colors[[1, 3]])
    with pytest.raises(StageError, match="no point was fused from 5 or more images"):
        supported_points(tmp_path / "fused.ply", vis, tmp_path / "s.ply", min_images=5)
    vis.write_bytes(np.uint64(1).tobytes() + np.array([1, 0], "<u4").tobytes())
    with pytest.raises(InputError, match=r"1 points, but .* has 4"):
        supported_points(tmp_path / "fused.ply", vis, tmp_path / "s.ply", min_images=2)


def grid_and_kept(
    tmp_path: Path, others: npt.NDArray[np.float64], seen_by: list[list[int]]
) -> tuple[npt.NDArray[np.float64], Callable[..., npt.NDArray[np.float64]]]:
    """A 1 cm grid of 100 points at z = 2 m followed by `others`, written as fused.ply with
    its .vis (`seen_by`: the images of each point); returns the grid and `kept(**rules)`,
    the points `supported_points` keeps (min_images 2) under those rules."""
    from postproc.dense.stage import supported_points
    from shared.formats.ply import PlyData, write_ply

    u, v = np.meshgrid(np.arange(10) * 0.01, np.arange(10) * 0.01)
    patch = np.column_stack((u.ravel(), v.ravel(), np.full(u.size, 2.0)))
    points = np.concatenate((patch, others))
    write_ply(tmp_path / "fused.ply", PlyData(vertices=points))
    values = [v for images in seen_by for v in (len(images), *images)]
    vis = tmp_path / "fused.ply.vis"
    vis.write_bytes(np.uint64(len(points)).tobytes() + np.array(values, "<u4").tobytes())

    def kept(**kwargs: Any) -> npt.NDArray[np.float64]:
        out = supported_points(
            tmp_path / "fused.ply", vis, tmp_path / "s.ply", min_images=2, **kwargs
        )
        return read_ply(out).vertices

    return patch, kept


def test_mesh_input_keeps_dense_patches_of_one_depth_map(tmp_path: Path) -> None:
    # A 1 cm grid of points seen by one image, two strays seen by one image, and one
    # point seen by two images.
    strays = np.array([[1.0, 1.0, 2.0], [-1.0, 0.5, 3.0]])
    twice = np.array([[5.0, 5.0, 5.0]])
    patch, kept = grid_and_kept(tmp_path, np.concatenate((strays, twice)), [[0]] * 102 + [[0, 1]])

    np.testing.assert_allclose(kept(), twice)  # the rule off: only the point seen twice
    # Every grid point has at least 3 others within 1.5 cm (corners: 3), the strays none.
    np.testing.assert_allclose(
        kept(min_neighbours=3, radius_m=0.015), np.concatenate((patch, twice))
    )
    # Asking for more neighbours than the corners have drops them.
    assert len(kept(min_neighbours=4, radius_m=0.015)) == len(patch) - 4 + 1


def test_mesh_input_leaves_out_lone_points_however_many_images_saw_them(tmp_path: Path) -> None:
    from postproc.dense.meshing import lone_points

    # A 1 cm grid seen by two images, two strays seen by three, one single-image point.
    strays = np.array([[1.0, 1.0, 2.0], [1.02, 1.0, 2.0]])  # each other's only neighbour
    single = np.array([[0.05, 0.05, 2.01]])
    patch, kept = grid_and_kept(
        tmp_path, np.concatenate((strays, single)), [[0, 1]] * 100 + [[0, 1, 2]] * 2 + [[0]]
    )

    np.testing.assert_allclose(kept(), np.concatenate((patch, strays)))
    # Grid points have 3 or more others within 1.5 cm (the single-image point, left out
    # first, does not count for them); each stray has one.
    np.testing.assert_allclose(kept(stray_neighbours=3, stray_radius_m=0.015), patch)
    np.testing.assert_allclose(
        kept(stray_neighbours=1, stray_radius_m=0.025), np.concatenate((patch, strays))
    )
    with pytest.raises(StageError, match="fewer than 200 others"):
        kept(stray_neighbours=200, stray_radius_m=1.0)
    # The count stops at the asked-for neighbours, and fewer points than that are all lone.
    assert lone_points(patch, 3, 0.015).sum() == 0
    assert lone_points(patch, 4, 0.015).sum() == 4  # the corners
    assert lone_points(patch[:3], 5, 1.0).all()
    assert len(lone_points(np.zeros((0, 3)), 5, 1.0)) == 0
    # A coarse grid (3 cm) has no neighbour within 1.5 cm; 2 spacings (6 cm) find them.
    assert lone_points(3.0 * patch, 3, 0.015).all()
    assert not lone_points(3.0 * patch, 3, 0.015, radius_spacings=2.0).any()


def test_mesh_input_keeps_points_of_one_map_that_pairs_support(tmp_path: Path) -> None:
    from postproc.dense.colmap_io import PinholeView, write_array
    from postproc.dense.stage import supported_points
    from shared.formats.ply import PlyData, write_ply

    # Two 20x10 px views looking down +z from the origin and from x = 1 m; four points at
    # 2 m, each of one map: pixel (5, 5) and (15, 5) of view 0, (5, 5) of view 1, and one
    # behind view 1's support map (no map: nothing kept by the rule).
    K = np.array([[10.0, 0.0, 10.0], [0.0, 10.0, 5.0], [0.0, 0.0, 1.0]])
    pose1 = np.eye(4)
    pose1[0, 3] = -1.0  # T_C_W of a camera at x = 1 m
    views = [
        PinholeView(name="a.png", K=K, width=20, height=10, cam_from_world=np.eye(4),
                    points_m=np.zeros((0, 3))),
        PinholeView(name="b.png", K=K, width=20, height=10, cam_from_world=pose1,
                    points_m=np.zeros((0, 3))),
        PinholeView(name="c.png", K=K, width=20, height=10, cam_from_world=np.eye(4),
                    points_m=np.zeros((0, 3))),
    ]  # fmt: skip
    pixels = [(0, 5.5, 5.5), (0, 15.5, 5.5), (1, 5.5, 5.5), (2, 5.5, 5.5)]
    points = []
    for k, u, v in pixels:
        cam = np.array([(u - 10.0) / 10.0 * 2.0, (v - 5.0) / 10.0 * 2.0, 2.0])
        pose = views[k].cam_from_world
        points.append(pose[:3, :3].T @ (cam - pose[:3, 3]))
    write_ply(tmp_path / "fused.ply", PlyData(vertices=np.array(points)))
    values = [x for k, _, _ in pixels for x in (1, k)]
    vis = tmp_path / "fused.ply.vis"
    vis.write_bytes(np.uint64(len(points)).tobytes() + np.array(values, "<u4").tobytes())
    workspace = DenseWorkspace(tmp_path / "ws")
    support_a = np.zeros((10, 20), np.float32)
    support_a[:, :10] = 3  # left half: three pairs agree; right half: one
    support_a[:, 10:] = 1
    write_array(workspace.support_map_path("a.png"), support_a)
    write_array(workspace.support_map_path("b.png"), np.full((10, 20), 2, np.float32))

    def kept(min_pairs: int, near: int = 0, near_range_m: float = 0.0) -> npt.NDArray[np.float64]:
        out = supported_points(
            tmp_path / "fused.ply", vis, tmp_path / "s.ply", min_images=2,
            min_pairs=min_pairs, near_min_pairs=near, near_range_m=near_range_m,
            workspace=workspace, views=views,
        )  # fmt: skip
        return read_ply(out).vertices

    np.testing.assert_allclose(kept(3), np.array(points)[[0]])
    np.testing.assert_allclose(kept(2), np.array(points)[[0, 2]])
    np.testing.assert_allclose(kept(1), np.array(points)[[0, 1, 2]])
    # Fewer pairs within a range: the points lie 2 m in front of their cameras.
    np.testing.assert_allclose(kept(3, near=2, near_range_m=2.5), np.array(points)[[0, 2]])
    np.testing.assert_allclose(kept(3, near=2, near_range_m=1.5), np.array(points)[[0]])
    np.testing.assert_allclose(kept(0, near=1, near_range_m=2.5), np.array(points)[[0, 1, 2]])
    with pytest.raises(ValueError, match="needs the workspace"):
        supported_points(tmp_path / "fused.ply", vis, tmp_path / "s.ply", min_images=2,
                         min_pairs=2)  # fmt: skip
