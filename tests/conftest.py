"""Test-wide fixtures: where the shared real data lives, quiet progress bars."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

os.environ.setdefault("WRECKMAP_PROGRESS", "0")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the repository (real GoPro files, AprilGrid photos, dive logs)."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"{SHARED_DATA}: shared data folder missing (expected beside the repo)")
    return SHARED_DATA
