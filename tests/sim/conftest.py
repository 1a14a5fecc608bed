"""Fixtures for the simulator tests: one coarse-textured scene shared by the module."""

from __future__ import annotations

import pytest

from sim.scene import WreckScene, build_wreck_scene


@pytest.fixture(scope="session")
def coarse_scene() -> WreckScene:
    """The wreck with coarse textures (fast to build; geometry is exact regardless)."""
    return build_wreck_scene(seed=3, texel_m=0.04, seafloor_texel_m=0.2)
