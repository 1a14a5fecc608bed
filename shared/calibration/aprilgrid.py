"""Kalibr's AprilGrid calibration target: geometry, tag patterns and a printable texture.

Pure math (no file I/O). The layout follows Kalibr exactly
(`GridCalibrationTargetAprilgrid.cpp` and `createTargetPDF.py` in ethz-asl/kalibr):

Target frame (metres), seen from the printed side with the page upright::

      y
      ^   +----------+  +----------+
      |   | id c+0   |  | id c+1   |      id = tag_id_offset + row * tag_cols + col
      |   |  (row 1) |  |          |      c  = tag_id_offset + tag_cols
      |   3----------2  3----------2
      |      <- spacing = tag_spacing_ratio * tag_size_m ->
      |   3----------2  3----------2
      |   | id 0     |  | id 1     |      tag corners, counter-clockwise on the page:
      |   | (row 0)  |  |          |        0 = (x0, y0)            bottom-left
      |   0----------1  0----------1        1 = (x0 + s, y0)        bottom-right
      |                                     2 = (x0 + s, y0 + s)    top-right
      +------------------------------> x    3 = (x0, y0 + s)        top-left
    origin = corner 0 of the first tag; z = x cross y points out of the page
    towards the viewer; every corner has z = 0.

  Tag (row, col) has x0 = col * (1 + ratio) * s, y0 = row * (1 + ratio) * s with
  s = tag_size_m; tags count along x first (row 0 is the bottom row of the page).
  The flat corner index Kalibr uses is 4 * (id - offset) + corner.

Tag size and border: `tag_size_m` (Kalibr `tagSize`) is the side of the whole
black square. Kalibr prints 36h11 tags with a *2-cell* black border, so that
square is 10 x 10 cells of tag_size_m / 10: two black rings around the 6 x 6
code. (A standard 36h11 tag is 8 x 8 cells, one black ring, inside a white
ring; Kalibr's tag is that tag with its white ring painted black.) Kalibr also
prints small black squares of side `spacing` touching each tag diagonally at
its four corners, so every tag corner is an X-junction for sub-pixel
refinement; `render_target_texture` draws them too.

Matching OpenCV's cv2.aruco: detect with `DICT_APRILTAG_36h11` and
`DetectorParameters.markerBorderBits = 2`; ids come out equal to Kalibr's ids.
Kalibr prints each code rotated by 180 degrees relative to the marker that
`generateImageMarker` draws upright (Kalibr fills cell (i, j) from bit 6 i + j,
least significant first, then rotates the matrix by 180 degrees; OpenCV's
upright marker reads most significant first, which is that matrix unrotated).
OpenCV reports corners of the upright marker as top-left, top-right,
bottom-right, bottom-left; on Kalibr's page those are Kalibr corners
1, 0, 3, 2. Hence `kalibr_corners = opencv_corners[list(OPENCV_CORNER_ORDER)]`
(the permutation is its own inverse). The detector that does so is
`shared.calibration.aprilgrid_detection`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

#: Index into an OpenCV aruco corner list (TL, TR, BR, BL of the upright marker) for
#: each Kalibr corner 0..3 of the same printed tag. Its own inverse.
OPENCV_CORNER_ORDER: tuple[int, int, int, int] = (1, 0, 3, 2)

#: Cells across a Kalibr AprilGrid tag: 6 code cells plus two black rings on each side.
TAG_CELLS = 10
#: Black rings around the 6x6 code in a Kalibr tag.
KALIBR_BORDER_BITS = 2
#: Number of ids in OpenCV's DICT_APRILTAG_36h11 (the full 36h11 family).
TAG36H11_COUNT = 587


@dataclass(frozen=True)
class AprilGridTarget:
    """A Kalibr AprilGrid: `tag_rows` x `tag_cols` 36h11 tags.

    tag_size_m: side of each tag's black square (Kalibr `tagSize`), metres.
    tag_spacing_ratio: gap between neighbouring tags / tag_size_m (Kalibr `tagSpacing`).
    tag_id_offset: id of the first tag (bottom-left); ours, Kalibr assumes 0.
    """

    tag_rows: int
    tag_cols: int
    tag_size_m: float
    tag_spacing_ratio: float
    tag_id_offset: int = 0

    def __post_init__(self) -> None:
        if self.tag_rows < 1 or self.tag_cols < 1:
            raise ValueError(
                f"AprilGrid needs at least 1x1 tags, got {self.tag_rows}x{self.tag_cols}"
            )
        if not self.tag_size_m > 0:
            raise ValueError(f"tag_size_m must be positive, got {self.tag_size_m}")
        if not self.tag_spacing_ratio > 0:
            raise ValueError(f"tag_spacing_ratio must be positive, got {self.tag_spacing_ratio}")
        last = self.tag_id_offset + self.tag_rows * self.tag_cols - 1
        if self.tag_id_offset < 0 or last >= TAG36H11_COUNT:
            raise ValueError(
                f"tag ids {self.tag_id_offset}..{last} outside the 36h11 family "
                f"(0..{TAG36H11_COUNT - 1})"
            )

    @property
    def tag_spacing_m(self) -> float:
        """Gap between neighbouring tags (metres)."""
        return self.tag_spacing_ratio * self.tag_size_m

    @property
    def extent_m(self) -> tuple[float, float]:
        """(width along x, height along y) of the tag area, from the first to the last
        tag edge (metres); the corner squares stick out `tag_spacing_m` beyond it."""
        pitch = self.tag_size_m + self.tag_spacing_m
        return (
            (self.tag_cols - 1) * pitch + self.tag_size_m,
            (self.tag_rows - 1) * pitch + self.tag_size_m,
        )

    def tag_ids(self) -> list[int]:
        """All tag ids in Kalibr order (row by row from the bottom, x first)."""
        return list(range(self.tag_id_offset, self.tag_id_offset + self.tag_rows * self.tag_cols))

    def tag_origin_m(self, tag_id: int) -> tuple[float, float]:
        """(x0, y0) of corner 0 (bottom-left on the page) of `tag_id`, metres."""
        index = tag_id - self.tag_id_offset
        if not 0 <= index < self.tag_rows * self.tag_cols:
            raise ValueError(f"tag id {tag_id} is not on this grid ({self.tag_ids()[0]}..)")
        row, col = divmod(index, self.tag_cols)
        pitch = self.tag_size_m + self.tag_spacing_m
        return col * pitch, row * pitch

    def all_corner_points(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """(ids (M,), corners (M,4,3)) in the target frame (metres, z = 0), Kalibr order."""
        ids = np.array(self.tag_ids(), dtype=np.int64)
        index = ids - self.tag_id_offset
        pitch = self.tag_size_m + self.tag_spacing_m
        x0 = (index % self.tag_cols) * pitch
        y0 = (index // self.tag_cols) * pitch
        s = self.tag_size_m
        offsets = np.array([[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]])
        points = np.zeros((len(ids), 4, 3))
        points[:, :, 0] = x0[:, None] + offsets[None, :, 0]
        points[:, :, 1] = y0[:, None] + offsets[None, :, 1]
        return ids, points

    def corner_points(self) -> dict[int, NDArray[np.float64]]:
        """Tag id -> (4,3) corners in the target frame (metres, z = 0), Kalibr order."""
        ids, points = self.all_corner_points()
        return {int(i): p for i, p in zip(ids, points, strict=True)}


@cache
def _tag36h11_bits_cached(tag_id: int) -> bytes:
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    # One pixel per cell: the drawn image is exactly the cell pattern.
    image = dictionary.generateImageMarker(tag_id, TAG_CELLS, borderBits=KALIBR_BORDER_BITS)
    return bytes((np.asarray(image) > 127).astype(np.uint8).tobytes())


def tag36h11_bits(tag_id: int) -> NDArray[np.bool_]:
    """(10,10) cells of 36h11 tag `tag_id` with Kalibr's 2-cell black border; True = white.

    Oriented as OpenCV's `generateImageMarker` draws the upright marker (row 0 at
    the top). Kalibr prints this pattern rotated by 180 degrees (see the module
    docstring); `render_target_texture` does that rotation.
    """
    if not 0 <= tag_id < TAG36H11_COUNT:
        raise ValueError(f"tag id {tag_id} outside the 36h11 family (0..{TAG36H11_COUNT - 1})")
    cells = np.frombuffer(_tag36h11_bits_cached(tag_id), dtype=np.uint8)
    return cells.reshape(TAG_CELLS, TAG_CELLS).astype(bool)


def texture_pixel_from_target(
    target: AprilGridTarget, pixels_per_m: float, points_xy_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Map (N,2) target-frame points (metres) to pixel coordinates in the texture.

    Pixel centres are at integer coordinates (OpenCV convention): the texture's
    top-left pixel centre is target point (-margin + 0.5/ppm, ymax + margin - 0.5/ppm)
    where margin = `texture_margin_m(target)` and ymax = `target.extent_m[1]`.
    """
    points = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    margin = texture_margin_m(target)
    top = target.extent_m[1] + margin
    u = (points[:, 0] + margin) * pixels_per_m - 0.5
    v = (top - points[:, 1]) * pixels_per_m - 0.5
    return np.column_stack((u, v))


def texture_margin_m(target: AprilGridTarget) -> float:
    """White margin around the tag area in the texture: corner squares plus one more gap."""
    return 2.0 * target.tag_spacing_m


def _interval_overlap(
    pixel_count: int, pixels_per_m: float, low_m: NDArray[np.float64], length_m: float
) -> NDArray[np.float64]:
    """(pixel_count, K) fraction of each pixel covered by each interval [low, low + length)
    along one texture axis whose pixel 0 starts at 0 m (exact box-filter antialiasing)."""
    high_m = low_m + length_m
    pixel_low = np.arange(pixel_count, dtype=np.float64)[:, None] / pixels_per_m
    pixel_high = pixel_low + 1.0 / pixels_per_m
    overlap = np.minimum(pixel_high, high_m[None, :]) - np.maximum(pixel_low, low_m[None, :])
    return np.clip(overlap * pixels_per_m, 0.0, 1.0)


def render_target_texture(target: AprilGridTarget, pixels_per_m: float) -> NDArray[np.uint8]:
    """A printable grayscale image (H,W) of the whole grid: white paper, black ink.

    Kalibr's layout as seen from the printed side, page upright (target +y up the
    image): tags with their 2-cell black border, the corner squares, and a white
    margin of `texture_margin_m(target)` on every side. Edges are antialiased
    with exact area coverage, so tag corners land at the sub-pixel positions
    given by `texture_pixel_from_target`. At `pixels_per_m` = 10 / tag_size_m a
    code cell is one pixel; use several pixels per cell for detection.
    """
    if not pixels_per_m > 0:
        raise ValueError(f"pixels_per_m must be positive, got {pixels_per_m}")
    margin = texture_margin_m(target)
    width_m, height_m = target.extent_m
    width = int(np.ceil((width_m + 2 * margin) * pixels_per_m))
    height = int(np.ceil((height_m + 2 * margin) * pixels_per_m))
    ink = np.zeros((height, width), dtype=np.float64)
    s = target.tag_size_m
    gap = target.tag_spacing_m
    cell = s / TAG_CELLS
    top_m = height_m + margin

    def paint(x_low: float, y_top: float, black: NDArray[np.float64], cell_m: float) -> None:
        # `black` is a (rows, cols) ink matrix with row 0 at the top of the image,
        # covering [x_low, x_low + cols*cell_m] x [y_top - rows*cell_m, y_top] in metres.
        rows, cols = black.shape
        u_low = x_low + margin
        v_low = top_m - y_top
        c0 = max(int(np.floor(u_low * pixels_per_m)) - 1, 0)
        c1 = min(int(np.ceil((u_low + cols * cell_m) * pixels_per_m)) + 1, width)
        r0 = max(int(np.floor(v_low * pixels_per_m)) - 1, 0)
        r1 = min(int(np.ceil((v_low + rows * cell_m) * pixels_per_m)) + 1, height)
        col_edges = np.asarray(u_low - c0 / pixels_per_m + np.arange(cols) * cell_m, np.float64)
        row_edges = np.asarray(v_low - r0 / pixels_per_m + np.arange(rows) * cell_m, np.float64)
        ax = _interval_overlap(c1 - c0, pixels_per_m, col_edges, cell_m)
        ay = _interval_overlap(r1 - r0, pixels_per_m, row_edges, cell_m)
        ink[r0:r1, c0:c1] += ay @ black @ ax.T

    ids, corners = target.all_corner_points()
    for tag_id, tag_corners in zip(ids, corners, strict=True):
        x0, y0 = float(tag_corners[0, 0]), float(tag_corners[0, 1])
        # Kalibr prints the code rotated by 180 degrees relative to OpenCV's upright marker.
        black = (~np.rot90(tag36h11_bits(int(tag_id)), 2)).astype(np.float64)
        paint(x0, y0 + s, black, cell)
    # Kalibr's corner squares (side `gap`) touch every tag diagonally at its corners.
    # They form a lattice shared by neighbouring tags: square k spans
    # [k * pitch - gap, k * pitch] along each axis, k = 0..cols (or rows).
    pitch = s + gap
    square = np.ones((1, 1))
    for k_row in range(target.tag_rows + 1):
        for k_col in range(target.tag_cols + 1):
            paint(k_col * pitch - gap, k_row * pitch, square, gap)
    image = 255.0 * (1.0 - np.clip(ink, 0.0, 1.0))
    return np.round(image).astype(np.uint8)
