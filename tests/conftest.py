"""Test-wide fixtures: where the shared real data lives, quiet progress bars; and, when the
suite runs on several workers (`make test`: pytest-xdist), the longest files first."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

os.environ.setdefault("WRECKMAP_PROGRESS", "0")

# What a test marked `slow` is assumed to take, unless its mark says: `slow(seconds=240)`.
SLOW_DEFAULT_S = 20.0


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the repository (real GoPro files, AprilGrid photos, dive logs)."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"{SHARED_DATA}: shared data folder missing (expected beside the repo)")
    return SHARED_DATA


def expected_seconds(item: pytest.Item) -> float:
    """A test's rough cost for ordering: its `slow` mark's `seconds`, else 20 s or none."""
    mark = item.get_closest_marker("slow")
    if mark is None:
        return 0.0
    return float(mark.kwargs.get("seconds", SLOW_DEFAULT_S))


def longest_files_first(items: list[pytest.Item]) -> list[pytest.Item]:
    """Files in decreasing order of their tests' expected seconds (ties keep collection order),
    each file's tests in their own order.

    pytest-xdist's `--dist loadfile --no-loadscope-reorder` hands out whole files in this
    order, so the long ones start first instead of leaving one worker busy at the end.
    """
    cost: dict[str, float] = {}
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        cost[path] = cost.get(path, 0.0) + expected_seconds(item)
    rank = {path: i for i, path in enumerate(sorted(cost, key=lambda p: -cost[p]))}
    return sorted(items, key=lambda item: rank[item.nodeid.split("::", 1)[0]])


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # Only in xdist workers (they all collect, and must agree on one order); a plain
    # `pytest` run keeps the collection order.
    if hasattr(config, "workerinput"):
        items[:] = longest_files_first(items)
