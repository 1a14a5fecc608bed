"""Orthophoto and DEM: GeoTIFF tags, scale, a known point in the right cell, georeference."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from postproc.export.ortho import Georeference, nice_length_m, raster_grid
from postproc.export.stage import ExportOptions, OrthoOptions, run
from shared.errors import InputError

from .conftest import BOX_MAX, BOX_MIN, BOX_TOP_Z, SEABED_Z, TARGET_M, RunFixture


def read_geotiff(
    path: Path,
) -> tuple[np.ndarray, tuple[float, ...], tuple[float, ...], dict[str, Any]]:
    """Pixels, ModelPixelScale, ModelTiepoint and the decoded GeoKeys (tifffile)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert isinstance(page, tifffile.TiffPage)
        scale = tuple(page.tags["ModelPixelScaleTag"].value)
        tie = tuple(page.tags["ModelTiepointTag"].value)
        keys = dict(tif.geotiff_metadata or {})
        return page.asarray(), scale, tie, keys


def cell(scale: tuple[float, ...], tie: tuple[float, ...], x: float, y: float) -> tuple[int, int]:
    """(row, col) of map point (x, y): the tie point puts pixel (0, 0)'s corner at tie[3:5]."""
    return int(np.floor((tie[4] - y) / scale[1])), int(np.floor((x - tie[3]) / scale[0]))


@pytest.fixture(scope="module")
def ortho_dir(run_folder: RunFixture, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ortho") / "export"
    run(ExportOptions(formats=("ortho",)), run_folder.root, out)
    return out / "ortho"


def test_geotiff_tags_scale_and_a_known_point(ortho_dir: Path) -> None:
    dem, scale, tie, keys = read_geotiff(ortho_dir / "dem.tif")
    assert scale == (0.01, 0.01, 0.0)
    assert tie[:3] == (0.0, 0.0, 0.0)
    assert int(keys["GTRasterTypeGeoKey"]) == 1  # PixelIsArea
    assert int(keys["ProjectedCSTypeGeoKey"]) == 32767  # user-defined: the local frame
    assert dem.dtype == np.float32
    # A point on the plank's top and one on the seabed land in cells of their heights.
    r, c = cell(scale, tie, 0.333, 0.111)
    assert dem[r, c] == pytest.approx(BOX_TOP_Z, abs=1e-5)
    r, c = cell(scale, tie, -1.5, 1.0)
    assert dem[r, c] == pytest.approx(SEABED_Z, abs=1e-5)
    # Either side of the plank's west edge (x = -1.0), half a cell away: on the top, and
    # on the mesh's sloping edge (seabed vertices 5 cm out): 0.3 * 4.5 / 5 m up.
    r, c = cell(scale, tie, -0.995, 0.0)
    assert dem[r, c] == pytest.approx(BOX_TOP_Z, abs=1e-5)
    r, c = cell(scale, tie, -1.005, 0.0)
    assert dem[r, c] == pytest.approx(SEABED_Z + 0.27, abs=1e-5)
    assert np.isnan(dem[0, 0])  # the margin outside the mesh
    ortho, scale2, tie2, _ = read_geotiff(ortho_dir / "ortho.tif")
    assert (scale2, tie2) == (scale, tie)
    assert ortho.shape == (*dem.shape, 4)
    r, c = cell(scale, tie, 0.333, 0.111)
    np.testing.assert_array_equal(ortho[r, c], [200, 30, 30, 255])  # the red plank
    assert ortho[0, 0, 3] == 0


def test_plank_measures_its_true_size(ortho_dir: Path) -> None:
    """The plank is 2.000 x 0.500 m: counted in cells of its height, within 0.5 %."""
    dem, scale, tie, _ = read_geotiff(ortho_dir / "dem.tif")
    on_top = np.abs(dem - BOX_TOP_Z) < 1e-4
    rows, cols = np.nonzero(on_top)
    length_m = (cols.max() - cols.min() + 1) * scale[0]
    width_m = (rows.max() - rows.min() + 1) * scale[1]
    true_length, true_width = BOX_MAX - BOX_MIN
    assert abs(length_m - true_length) / true_length <= 0.005
    assert abs(width_m - true_width) / true_width <= 0.02  # 50 cells: one cell is 2 %
    # And where: the plank's west edge is at x = -1.0.
    west = tie[3] + cols.min() * scale[0]
    assert west == pytest.approx(BOX_MIN[0], abs=scale[0])


def test_previews_and_summary(ortho_dir: Path) -> None:
    import cv2

    summary = json.loads((ortho_dir / "ortho.json").read_text())
    assert summary["resolution_m"] == 0.01
    assert summary["elevation_range_m"] == pytest.approx([SEABED_Z, BOX_TOP_Z], abs=1e-5)
    for name in ("ortho.png", "dem.png"):
        image = cv2.imread(str(ortho_dir / name))
        assert image is not None
        # The raster (404 px wide) plus a 60 px strip for the scale bar underneath.
        assert image.shape[1] == summary["width"]
        assert image.shape[0] == summary["height"] + 60
        strip = image[summary["height"] :]
        assert (strip < 50).all(axis=2).sum() > 100  # the black bar and its label
    assert nice_length_m(4.04) == 0.5


def test_georeferenced_rasters_put_the_target_on_the_map(
    run_folder: RunFixture, tmp_path: Path
) -> None:
    easting, northing = 512_000.0, 6_543_000.0
    georef = Georeference(target="grid_a", easting_m=easting, northing_m=northing,
                          epsg=32633, heading_deg=0.0)  # world x points north  # fmt: skip
    options = ExportOptions(formats=("ortho",), ortho=OrthoOptions(georeference=georef))
    run(options, run_folder.root, tmp_path / "out")
    dem, scale, tie, keys = read_geotiff(tmp_path / "out" / "ortho" / "dem.tif")
    assert int(keys["ProjectedCSTypeGeoKey"]) == 32633
    # World x -> north, world y -> west. A plank-top point at world (0.8, 0.1):
    world = np.array([0.8, 0.1])
    offset = world - TARGET_M[:2]
    e, n = easting - offset[1], northing + offset[0]
    r, c = cell(scale, tie, e, n)
    assert dem[r, c] == pytest.approx(BOX_TOP_Z, abs=1e-5)
    # The plank (2 m along world x) now runs north-south.
    rows, _ = np.nonzero(np.abs(dem - BOX_TOP_Z) < 1e-4)
    assert (rows.max() - rows.min() + 1) * scale[1] == pytest.approx(2.0, rel=0.005)
    summary = json.loads((tmp_path / "out" / "ortho" / "ortho.json").read_text())
    assert summary["heading_assumed"] is False


def test_unknown_target_and_too_fine_a_grid_are_refused(
    run_folder: RunFixture, tmp_path: Path
) -> None:
    georef = Georeference(target="nope", easting_m=0.0, northing_m=0.0, epsg=32633)
    options = ExportOptions(formats=("ortho",), ortho=OrthoOptions(georeference=georef))
    with pytest.raises(InputError, match=r"targets\.json: no world pose T_W_m for target 'nope'"):
        run(options, run_folder.root, tmp_path / "out")
    with pytest.raises(InputError, match="choose a coarser resolution"):
        raster_grid(np.array([[0.0, 0.0], [500.0, 500.0]]), 0.01)


def test_without_a_heading_world_x_is_taken_as_east(run_folder: RunFixture, tmp_path: Path) -> None:
    georef = Georeference(target="grid_a", easting_m=400_000.0, northing_m=5_000_000.0, epsg=32630)
    options = ExportOptions(
        formats=("ortho",), ortho=OrthoOptions(resolution_m=0.02, georeference=georef)
    )
    run(options, run_folder.root, tmp_path / "out")
    dem, scale, tie, _ = read_geotiff(tmp_path / "out" / "ortho" / "dem.tif")
    # The plank's west half at world (-0.5, 0.0): a pure shift onto the map.
    e, n = 400_000.0 + (-0.5 - TARGET_M[0]), 5_000_000.0 + (0.0 - TARGET_M[1])
    r, c = cell(scale, tie, e, n)
    assert dem[r, c] == pytest.approx(BOX_TOP_Z, abs=1e-5)
    _, cols = np.nonzero(np.abs(dem - BOX_TOP_Z) < 1e-4)
    assert (cols.max() - cols.min() + 1) * scale[0] == pytest.approx(2.0, rel=0.01)
    summary = json.loads((tmp_path / "out" / "ortho" / "ortho.json").read_text())
    assert summary["heading_assumed"] is True
    assert summary["frame"] == "EPSG:32630"
