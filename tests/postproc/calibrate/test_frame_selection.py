"""View selection: coverage of the image, viewing angles, sharpness, corner counts."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from postproc.calibrate.frame_selection import (
    FrameSelectionOptions,
    GridView,
    coverage_fraction,
    covered_cells,
    select_frames,
    sharpness,
    viewing_angles_deg,
)

SIZE = (640, 480)


def _grid_view(index, centre_px, *, scale_px=20.0, sharp=100.0, tilt_deg=0.0, corners=36):
    """A fronto-parallel (or tilted about y) 6x6 point grid drawn around `centre_px`."""
    side = int(np.sqrt(corners))
    xs, ys = np.meshgrid(np.arange(side), np.arange(side))
    object_points = np.column_stack((xs.ravel() * 0.1, ys.ravel() * 0.1, np.zeros(side * side)))
    # Project through a camera with f = 640 at 1 m, board rotated about y by tilt_deg.
    tilt = np.radians(tilt_deg)
    rotation = np.array(
        [[np.cos(tilt), 0, np.sin(tilt)], [0, 1, 0], [-np.sin(tilt), 0, np.cos(tilt)]]
    )
    centred = object_points - object_points.mean(axis=0)
    points = centred @ rotation.T + [0, 0, 640.0 / (scale_px * 10)]
    pixels = 640.0 * points[:, :2] / points[:, 2:3] + np.asarray(centre_px)
    return GridView(
        index=index,
        stamp_ns=index,
        image_points_px=pixels,
        object_points_m=object_points,
        sharpness=sharp,
    )


def test_spread_views_win_over_duplicates():
    duplicates = [_grid_view(i, (320, 240)) for i in range(10)]
    corners = [
        _grid_view(10 + k, c) for k, c in enumerate([(80, 60), (560, 60), (80, 420), (560, 420)])
    ]
    chosen = select_frames(duplicates + corners, SIZE, FrameSelectionOptions(max_frames=5))
    assert len(chosen) == 5
    # All four corner views, and one of the centre duplicates.
    assert set(range(10, 14)) <= set(chosen)
    assert sum(i < 10 for i in chosen) == 1


def test_tilted_views_are_preferred_among_equals():
    flat = [_grid_view(i, (320, 240)) for i in range(5)]
    tilted = _grid_view(5, (320, 240), tilt_deg=40.0)
    chosen = select_frames([*flat, tilted], SIZE, FrameSelectionOptions(max_frames=2))
    assert 5 in chosen
    assert abs(viewing_angles_deg(tilted, SIZE)[1]) > 25.0
    assert abs(viewing_angles_deg(flat[0], SIZE)[1]) < 5.0


def test_blurred_and_sparse_views_are_never_taken():
    views = [_grid_view(i, (100 + 100 * i, 240)) for i in range(5)]
    views.append(_grid_view(5, (320, 60), sharp=10.0))  # blurred: 10 % of the median
    views.append(_grid_view(6, (320, 420), corners=9))  # 9 corners < 16
    chosen = select_frames(views, SIZE, FrameSelectionOptions())
    assert chosen == [0, 1, 2, 3, 4]
    assert select_frames([], SIZE, FrameSelectionOptions()) == []
    assert select_frames([views[6]], SIZE, FrameSelectionOptions()) == []


def test_coverage_measures_the_cells_with_corners():
    view = _grid_view(0, (40, 30), scale_px=4.0)  # a small grid in the top-left cell
    assert list(covered_cells(view.image_points_px, SIZE, (8, 6))) == [0]
    assert coverage_fraction([view], SIZE, (8, 6)) == 1 / 48
    assert coverage_fraction([], SIZE, (8, 6)) == 0.0


def test_sharpness_falls_with_blur():
    rng = np.random.default_rng(0)
    image = (rng.random((120, 160)) * 255).astype(np.uint8)
    # cv2 stubs type the output loosely; it has the input's dtype (uint8).
    blurred = cast("npt.NDArray[np.uint8]", cv2.GaussianBlur(image, (0, 0), 2.0))
    assert sharpness(blurred) < 0.2 * sharpness(image)
