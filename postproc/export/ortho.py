"""Orthophoto and elevation raster (DEM) of the site from the mesh, as GeoTIFF + PNG.

Pure math first: `raster_grid` chooses the grid, `rasterise_top_down` draws the mesh
seen from straight above (for every cell, the highest surface over its centre: its
colour, interpolated from the vertex colours, and its elevation). Then the writers:
GeoTIFF through tifffile with the GeoTIFF tags GDAL and QGIS read (ModelPixelScale,
ModelTiepoint, GeoKeyDirectory, GDAL_NODATA), and PNG previews with a scale bar.

Raster frame: columns run along +x (east when georeferenced), rows along -y (north up);
the tie point puts the top-left corner of pixel (0, 0) at (x0, y0), so the centre of
pixel (row r, column c) is at (x0 + (c + 0.5) res, y0 - (r + 0.5) res) (PixelIsArea).
Elevation is world z in metres (z up, 0 at the sea surface: -12.3 is 12.3 m deep), NaN
where the mesh does not reach. Without georeferencing the coordinates are the run's
local world frame (GeoTIFF "user-defined" projected CRS, metres).

Georeferencing (`Georeference`): one target of the merge with a surveyed position
(easting, northing in a projected CRS given by its EPSG code, e.g. UTM) moves the local
frame onto the map. One position fixes no direction: the heading of the world x axis
(degrees clockwise from grid north; 90 = world x points east, the default) comes from
the target's own orientation when its bearing is given, else it is assumed. Elevations
stay relative to the sea surface at the time of the dive (no tide correction).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.errors import InputError

FloatArray = npt.NDArray[np.float64]

# Candidate (triangle, cell) pairs tested per vectorised pass (~100 bytes each).
_CHUNK_CANDIDATES = 1 << 20
# The largest raster accepted (cells: 60 x 100 m at 1 cm; about 20 bytes a cell while
# drawing); a finer resolution is refused with a hint.
MAX_CELLS = 60_000_000
# GeoTIFF tag and key numbers (GeoTIFF 1.1 / OGC 19-008).
TAG_PIXEL_SCALE, TAG_TIEPOINT, TAG_GEOKEYS, TAG_GEOASCII, TAG_GDAL_NODATA = (
    33550, 33922, 34735, 34737, 42113,
)  # fmt: skip
USER_DEFINED = 32767


@dataclass(frozen=True)
class RasterGrid:
    """A north-up grid: `x0_m`, `y0_m` the top-left corner, `resolution_m` the cell
    size, `width` x `height` cells."""

    x0_m: float
    y0_m: float
    resolution_m: float
    width: int
    height: int

    def cell_of(self, x_m: FloatArray, y_m: FloatArray) -> tuple[npt.NDArray[np.int64], ...]:
        """(row, col) of the cells holding points (x, y)."""
        col = np.floor((np.asarray(x_m) - self.x0_m) / self.resolution_m).astype(np.int64)
        row = np.floor((self.y0_m - np.asarray(y_m)) / self.resolution_m).astype(np.int64)
        return row, col


def raster_grid(xy_m: FloatArray, resolution_m: float, *, margin_cells: int = 2) -> RasterGrid:
    """The grid covering points (N, 2), corners on multiples of `resolution_m`.

    Raises InputError when the grid would exceed `MAX_CELLS`."""
    if not resolution_m > 0:
        raise ValueError(f"resolution must be positive, got {resolution_m}")
    lo, hi = np.min(xy_m, axis=0), np.max(xy_m, axis=0)
    x0 = (np.floor(lo[0] / resolution_m) - margin_cells) * resolution_m
    y0 = (np.ceil(hi[1] / resolution_m) + margin_cells) * resolution_m
    width = int(np.ceil((hi[0] - x0) / resolution_m)) + margin_cells
    height = int(np.ceil((y0 - lo[1]) / resolution_m)) + margin_cells
    if width * height > MAX_CELLS:
        raise InputError(
            f"a {resolution_m * 100:g} cm raster of this {hi[0] - lo[0]:.1f} x "
            f"{hi[1] - lo[1]:.1f} m site has {width * height:,} cells (limit "
            f"{MAX_CELLS:,}): choose a coarser resolution"
        )
    return RasterGrid(x0_m=float(x0), y0_m=float(y0), resolution_m=resolution_m,
                      width=width, height=height)  # fmt: skip


def rasterise_top_down(
    vertices_m: FloatArray,
    faces: npt.NDArray[np.int64],
    colors: npt.NDArray[np.uint8] | None,
    grid: RasterGrid,
    *,
    on_progress: Callable[[int], None] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
    """The mesh seen from above on `grid`: elevation (H, W) float32 (the highest surface
    over each cell centre, NaN where none) and RGB (H, W, 3) uint8 of that surface
    (vertex colours interpolated; grey without colours). Vertices are (x, y, z) in the
    grid's frame, metres. on_progress: called with the number of triangles done after
    each vectorised pass (a progress bar)."""
    V = np.asarray(vertices_m, float)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    C = np.full((len(V), 3), 160.0) if colors is None else np.asarray(colors, float)
    # Vertex positions in continuous cell coordinates (cell centres at integers).
    u = (V[:, 0] - grid.x0_m) / grid.resolution_m - 0.5
    v = (grid.y0_m - V[:, 1]) / grid.resolution_m - 0.5
    height, width = grid.height, grid.width
    best = np.full(height * width, -np.inf)
    rgb = np.zeros((height * width, 3), np.float32)
    tu, tv = u[F], v[F]
    area = (tu[:, 1] - tu[:, 0]) * (tv[:, 2] - tv[:, 0]) - (tu[:, 2] - tu[:, 0]) * (
        tv[:, 1] - tv[:, 0]
    )
    keep = np.abs(area) > 1e-12  # walls seen edge-on cover no cell centre
    c0 = np.clip(np.ceil(tu.min(1)), 0, width).astype(np.int64)
    c1 = np.clip(np.floor(tu.max(1)), -1, width - 1).astype(np.int64)
    r0 = np.clip(np.ceil(tv.min(1)), 0, height).astype(np.int64)
    r1 = np.clip(np.floor(tv.max(1)), -1, height - 1).astype(np.int64)
    nx, ny = c1 - c0 + 1, r1 - r0 + 1
    keep &= (nx > 0) & (ny > 0)
    tris = np.flatnonzero(keep)
    counts = (nx * ny)[tris]
    ends = np.cumsum(counts)
    start = 0
    while start < len(tris):
        base = ends[start - 1] if start else 0
        stop = int(np.searchsorted(ends, base + _CHUNK_CANDIDATES, side="right"))
        stop = max(stop, start + 1)
        t = tris[start:stop]
        n = counts[start:stop]
        owner = np.repeat(np.arange(len(t)), n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        ti = t[owner]
        col = c0[ti] + local % nx[ti]
        row = r0[ti] + local // nx[ti]
        pu, pv = tu[ti], tv[ti]
        # Barycentric weights of the cell centre (edge functions over twice the area).
        w0 = (pu[:, 1] - col) * (pv[:, 2] - row) - (pu[:, 2] - col) * (pv[:, 1] - row)
        w1 = (pu[:, 2] - col) * (pv[:, 0] - row) - (pu[:, 0] - col) * (pv[:, 2] - row)
        w = np.column_stack((w0, w1, area[ti] - w0 - w1)) / area[ti, None]
        inside = np.all(w >= -1e-9, axis=1)
        ti, w, cell = ti[inside], w[inside], (row * width + col)[inside]
        z = np.einsum("ij,ij->i", w, V[F[ti], 2])
        np.maximum.at(best, cell, z)
        top = z >= best[cell]
        colour = np.einsum("ij,ijk->ik", w[top], C[F[ti[top]]])
        rgb[cell[top]] = colour
        if on_progress is not None:
            on_progress(stop - start)
        start = stop
    if on_progress is not None:
        on_progress(len(F) - len(tris))  # the triangles that cover no cell centre
    elevation = np.where(np.isfinite(best), best, np.nan).reshape(height, width)
    image = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(height, width, 3)
    image[~np.isfinite(elevation)] = 0
    return elevation.astype(np.float32), image


@dataclass(frozen=True)
class Georeference:
    """Where a merge target lies on a map: `target` (its name in targets.json), its
    `easting_m`, `northing_m` in the projected CRS `epsg`, and `heading_deg`: the
    bearing (clockwise from grid north) of the world x axis; None: the target's own x
    axis bearing is unknown and world x is assumed to point east (90)."""

    target: str
    easting_m: float
    northing_m: float
    epsg: int
    heading_deg: float | None = None


def map_from_world(georef: Georeference | None, target_position_m: FloatArray | None) -> FloatArray:
    """3x3 homogeneous 2D transform from world (x, y) to map (easting, northing); the
    identity without georeferencing."""
    if georef is None:
        return np.eye(3)
    if target_position_m is None:
        raise ValueError("a georeference needs the target's world position")
    heading = np.radians(90.0 if georef.heading_deg is None else georef.heading_deg)
    # World x has bearing `heading`: its map direction is (sin h, cos h).
    ex = np.array([np.sin(heading), np.cos(heading)])
    ey = np.array([-ex[1], ex[0]])  # x turned 90 deg anticlockwise (seen from above)
    R = np.column_stack((ex, ey))
    out = np.eye(3)
    out[:2, :2] = R
    out[:2, 2] = np.array([georef.easting_m, georef.northing_m]) - R @ target_position_m[:2]
    return out


def geokeys(epsg: int | None, citation: str) -> tuple[list[int], str]:
    """GeoKeyDirectory values and GeoAsciiParams text: a projected CRS (EPSG code, or
    user-defined metres for the local frame), PixelIsArea, a citation."""
    ascii_params = citation + "|"
    keys = [
        (1024, 0, 1, 1),  # GTModelType: projected
        (1025, 0, 1, 1),  # GTRasterType: PixelIsArea
        (1026, TAG_GEOASCII, len(ascii_params), 0),  # GTCitation
        (3072, 0, 1, epsg if epsg is not None else USER_DEFINED),  # ProjectedCSType
    ]
    if epsg is None:
        keys.append((3076, 0, 1, 9001))  # ProjLinearUnits: metre
    keys += [(4096, 0, 1, USER_DEFINED), (4099, 0, 1, 9001)]  # vertical: local, metre
    values = [1, 1, 0, len(keys)]
    for key in keys:
        values.extend(key)
    return values, ascii_params


def geotiff_bytes(
    data: npt.NDArray[Any], grid: RasterGrid, *, epsg: int | None, citation: str
) -> bytes:
    """A GeoTIFF of `data` (H, W) float32 elevation or (H, W, 4) uint8 RGBA) on `grid`."""
    import io

    import tifffile

    keys, ascii_params = geokeys(epsg, citation)
    res = grid.resolution_m
    extratags: list[tuple[int, str, int, Any, bool]] = [
        (TAG_PIXEL_SCALE, "d", 3, (res, res, 0.0), True),
        (TAG_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, grid.x0_m, grid.y0_m, 0.0), True),
        (TAG_GEOKEYS, "H", len(keys), tuple(keys), True),
        (TAG_GEOASCII, "s", 0, ascii_params, True),
    ]
    kwargs: dict[str, Any] = {}
    if data.ndim == 2:
        extratags.append((TAG_GDAL_NODATA, "s", 0, "nan", True))
        kwargs["photometric"] = "minisblack"
    else:
        kwargs.update(photometric="rgb", extrasamples=("unassalpha",))
    out = io.BytesIO()
    tifffile.imwrite(out, data, extratags=extratags, compression="zlib", **kwargs)
    return out.getvalue()


def nice_length_m(span_m: float) -> float:
    """A round scale-bar length (1, 2 or 5 x 10^k m) near a fifth of `span_m`."""
    target = max(span_m / 5.0, 1e-6)
    power = 10.0 ** np.floor(np.log10(target))
    return float(max(m * power for m in (1.0, 2.0, 5.0) if m * power <= target))


def preview_png(
    rgb: npt.NDArray[np.uint8], valid: npt.NDArray[np.bool_], resolution_m: float,
    *, max_side_px: int = 1600, caption: str = "",
) -> bytes:  # fmt: skip
    """A PNG preview: the image on white, shrunk to `max_side_px`, with a scale bar and
    its length, an arrow to +y (north when georeferenced) and a caption."""
    import cv2

    image: npt.NDArray[np.uint8] = np.where(valid[..., None], rgb, 255).astype(np.uint8)
    scale = min(1.0, max_side_px / max(image.shape[:2]))
    if scale < 1.0:
        image = np.asarray(
            cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), np.uint8
        )
    px_m = resolution_m / scale  # metres per preview pixel
    height, width = image.shape[:2]
    pad = 60
    canvas = np.full((height + pad, max(width, 320), 3), 255, np.uint8)
    canvas[:height, :width] = image
    bar_m = nice_length_m(width * px_m)
    bar_px = max(1, round(bar_m / px_m))
    y = height + 20
    cv2.rectangle(canvas, (10, y), (10 + bar_px, y + 8), (0, 0, 0), -1)
    text = f"{bar_m:g} m" if bar_m >= 1 else f"{bar_m * 100:g} cm"
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, text, (16 + bar_px, y + 9), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, caption, (10, y + 34), font, 0.42, (60, 60, 60), 1, cv2.LINE_AA)
    x = canvas.shape[1] - 24
    cv2.arrowedLine(canvas, (x, y + 30), (x, y - 4), (0, 0, 0), 2, tipLength=0.3)
    cv2.putText(canvas, "+y", (x - 30, y + 10), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    ok, encoded = cv2.imencode(".png", canvas[..., ::-1])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()


def colourise_elevation(elevation: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    """RGB (H, W, 3) of an elevation raster (viridis, low = dark), NaN black."""
    import cv2

    valid = np.isfinite(elevation)
    if not valid.any():
        return np.zeros((*elevation.shape, 3), np.uint8)
    lo, hi = float(np.nanmin(elevation)), float(np.nanmax(elevation))
    level = np.zeros(elevation.shape, np.uint8)
    level[valid] = np.clip((elevation[valid] - lo) / max(hi - lo, 1e-9) * 255, 0, 255)
    return np.asarray(cv2.applyColorMap(level, cv2.COLORMAP_VIRIDIS)[..., ::-1], np.uint8)
