"""Rendered calibration data shared by the tests of this folder (made once per session)."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.calibrate.frame_selection import GridView
from postproc.calibrate.stage import detect_grid
from shared.calibration.aprilgrid_detection import DetectionOptions
from sim.calibration import TARGET, board_views, radtan_camera, recording


@pytest.fixture(scope="session")
def radtan_views():
    """(camera, 20 grey 320x240 images of the board, their world_from_cam)."""
    camera = radtan_camera(320, 240)
    images, poses = board_views(camera, 20, seed=3)
    return camera, images, poses


@pytest.fixture(scope="session")
def radtan_grid_views(radtan_views) -> list[GridView]:
    _, images, _ = radtan_views
    views = []
    for index, image in enumerate(images):
        view = detect_grid(
            image,
            TARGET,
            index=index,
            stamp_ns=index,
            detection=DetectionOptions(),
            min_tags=4,
        )
        if view is not None:
            views.append(view)
    return views


@pytest.fixture(scope="session")
def sweep():
    """A rendered 4 s hand-held sweep (320x240, 30 fps) with a 200 Hz IMU, shift 23.7 ms."""
    return recording(seed=5, duration_s=4.0, camera=radtan_camera(320, 240))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
