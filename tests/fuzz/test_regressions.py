"""Every input that once crashed a parser, replayed (tests/fuzz/regressions/<parser>/).

Files are the hostile input itself, or for the big GoPro files a `.patch.json` of edits
to a file of ../shared/data. Each must now end in a result or a clear WreckmapError.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from .harness import describe_failure
from .targets import REGRESSIONS, TARGETS, load_regression, regression_dir, run_input

pytestmark = pytest.mark.timeout(60)

_BY_FOLDER = {regression_dir(target).name: target for target in TARGETS.values()}
CASES = sorted(p for p in REGRESSIONS.glob("*/*") if p.is_file())


def test_every_regression_folder_names_a_parser() -> None:
    folders = {p.name for p in REGRESSIONS.iterdir() if p.is_dir()}
    assert folders <= set(_BY_FOLDER), f"unknown folders: {folders - set(_BY_FOLDER)}"
    assert CASES, "no regression cases checked in"


@pytest.mark.parametrize("path", CASES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_regression_input(path: Path, tmp_path: Path) -> None:
    target = _BY_FOLDER[path.parent.name]
    outcome = run_input(target, load_regression(path), tmp_path / "case")
    if outcome.failed:
        pytest.fail(describe_failure(target.name, path.name, outcome, path))
