"""The orthophoto's scale on the simulated wreck: hatch sizes on the truth mesh, and the
distance between the two hatches on a dense reconstruction from rendered top-down views."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from postproc.export.stage import OrthoOptions, write_ortho
from shared.formats.ply import PlyData, write_ply
from sim.mesh import scene_mesh
from sim.scene import WreckScene, build_wreck_scene

from .test_ortho import read_geotiff

HERE = Path(__file__).resolve().parent
# From sim/scene.py: (x0, x1, y0, y1, top z) of the two hatches on the fore deck.
HATCHES = {"hatch_1": (0.8, 2.6, -1.5, 1.5, -11.4), "hatch_2": (5.0, 7.2, -1.5, 1.5, -11.5)}


def dense_fixtures() -> ModuleType:
    """The dense tests' renderer-backed SfM builder (reused, not copied)."""
    name = "wreckmap_dense_test_fixtures"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, HERE.parent / "dense" / "conftest.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


@pytest.fixture(scope="module")
def scene() -> WreckScene:
    return build_wreck_scene(seed=3, texel_m=0.02, seafloor_texel_m=0.06)


def hatch_runs(
    dem: np.ndarray, scale: tuple[float, ...], tie: tuple[float, ...]
) -> dict[str, dict[str, float]]:
    """Per hatch, the median length along x and y of the run of cells above mid-height
    through its middle, and the median centre of those runs (metres)."""
    res = scale[0]

    def run_through(line: np.ndarray, m: int) -> tuple[int, int] | None:
        if not line[m]:
            return None
        a = b = m
        while a > 0 and line[a - 1]:
            a -= 1
        while b < len(line) - 1 and line[b + 1]:
            b += 1
        return a, b

    out = {}
    for name, (x0, x1, y0, y1, z_top) in HATCHES.items():
        top = dem > z_top - 0.3
        col = int(np.floor(((x0 + x1) / 2 - tie[3]) / res))
        row = int(np.floor((tie[4] - (y0 + y1) / 2) / res))
        lengths_x, centres_x, lengths_y = [], [], []
        for y in np.linspace(y0 + 0.3, y1 - 0.3, 25):
            found = run_through(top[int(np.floor((tie[4] - y) / res))], col)
            if found:
                lengths_x.append((found[1] - found[0] + 1) * res)
                centres_x.append(tie[3] + (found[0] + found[1] + 1) / 2 * res)
        for x in np.linspace(x0 + 0.2, x1 - 0.2, 15):
            found = run_through(top[:, int(np.floor((x - tie[3]) / res))], row)
            if found:
                lengths_y.append((found[1] - found[0] + 1) * res)
        assert len(lengths_x) > 10 and len(lengths_y) > 5, name
        out[name] = {
            "x_m": float(np.median(lengths_x)),
            "y_m": float(np.median(lengths_y)),
            "centre_x_m": float(np.median(centres_x)),
        }
    return out


def test_truth_mesh_hatches_measure_their_true_size(scene: WreckScene, tmp_path: Path) -> None:
    truth = scene_mesh(scene)
    centres = truth.vertices[truth.triangles].mean(axis=1)
    keep = (centres[:, 0] > -1) & (centres[:, 0] < 8) & (np.abs(centres[:, 1]) < 3)
    write_ply(tmp_path / "mesh.ply", PlyData(vertices=truth.vertices,
              faces=truth.triangles[keep], colors=truth.colors))  # fmt: skip
    write_ortho(OrthoOptions(resolution_m=0.02), tmp_path / "mesh.ply", tmp_path / "ortho")
    dem, scale, tie, _ = read_geotiff(tmp_path / "ortho" / "dem.tif")
    runs = hatch_runs(dem, scale, tie)
    for name, (x0, x1, y0, y1, _) in HATCHES.items():
        assert runs[name]["x_m"] == pytest.approx(x1 - x0, rel=0.005)
        assert runs[name]["y_m"] == pytest.approx(y1 - y0, rel=0.005)


@pytest.mark.slow
def test_dense_reconstruction_keeps_the_scale(scene: WreckScene, tmp_path: Path) -> None:
    """Twelve top-down views 3 m above the hatches at their true poses, CPU dense stereo
    and Poisson, then the ortho at 1 cm. The distance between the hatch centres (edge
    biases cancel) is the scale check; measured -0.23 %. Hatch sizes carry the stereo's
    edge bias (measured +1.7 / +0.9 % across x, -1.7 / -2.3 % along y)."""
    from postproc.dense.fusion import FusionOptions
    from postproc.dense.meshing import MeshingOptions
    from postproc.dense.stage import DenseOptions
    from postproc.dense.stage import run as run_dense

    def looking_down(x: float, y: float) -> np.ndarray:
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = (x, y, -8.4)
        return pose

    poses = [looking_down(x, y) for y in (-0.7, 0.7) for x in np.linspace(1.2, 6.6, 6)]
    dense_fixtures().build_sfm(tmp_path / "sfm", scene, poses)
    options = DenseOptions(
        fusion=FusionOptions(num_threads=1), meshing=MeshingOptions(num_threads=1, max_depth=9)
    )
    run_dense(options, tmp_path / "sfm", tmp_path / "dense")
    write_ortho(OrthoOptions(), tmp_path / "dense" / "mesh.ply", tmp_path / "ortho")
    dem, scale, tie, _ = read_geotiff(tmp_path / "ortho" / "dem.tif")
    runs = hatch_runs(dem, scale, tie)
    true_distance = np.mean(HATCHES["hatch_2"][:2]) - np.mean(HATCHES["hatch_1"][:2])
    distance = runs["hatch_2"]["centre_x_m"] - runs["hatch_1"]["centre_x_m"]
    assert distance == pytest.approx(true_distance, rel=0.005)
    for name, (x0, x1, y0, y1, _) in HATCHES.items():
        assert runs[name]["x_m"] == pytest.approx(x1 - x0, rel=0.04)
        assert runs[name]["y_m"] == pytest.approx(y1 - y0, rel=0.04)
