"""A small simulated two-session survey as SLAM-like folders, shared by the SfM tests."""

from __future__ import annotations

import pytest

from sim.slam_like import SlamLikeSession, write_slam_like_survey


@pytest.fixture(scope="session")
def slam_survey(tmp_path_factory: pytest.TempPathFactory) -> list[SlamLikeSession]:
    """Two 60 s sessions, keyframes every 2 s (30 each), 320x240, drifting priors."""
    root = tmp_path_factory.mktemp("sfm_survey")
    return write_slam_like_survey(
        root, sessions=2, duration_s=60.0, keyframe_hz=0.5, width=320, height=240, seed=1
    )
