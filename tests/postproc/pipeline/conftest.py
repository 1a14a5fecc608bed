"""Fixtures of the pipeline tests: a small project on fake inputs, fake stages importable."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def write_project(root: Path, *, extra: str = "", sessions: int = 2) -> Path:
    """Two EuRoC-like folders with a dive CSV each, one target file, and the project YAML."""
    lines = [
        "name: fake-survey",
        "output: out",
        "targets: [targets/grid.yaml]",
        "sessions:",
    ]
    (root / "targets").mkdir(parents=True, exist_ok=True)
    (root / "targets" / "grid.yaml").write_text("target_type: aprilgrid\n")
    for k in range(1, sessions + 1):
        recording = root / "data" / f"s{k}"
        (recording / "mav0").mkdir(parents=True, exist_ok=True)
        (recording / "mav0" / "frames.txt").write_text(f"frames of session {k}\n")
        (root / "data" / f"dive{k}.csv").write_text(
            f"timestamp_s,depth_m,temperature_c\n{k},1.0,\n"
        )
        lines += [f"  - name: s{k}", f"    euroc: data/s{k}", f"    dive: data/dive{k}.csv"]
    path = root / "project.yaml"
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


@pytest.fixture
def fake_stages(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, str]:
    """The fake adapters (module `fake_stages` on sys.path), markers in tmp_path/markers."""
    monkeypatch.syspath_prepend(str(HERE))
    markers = tmp_path / "markers"
    markers.mkdir()
    monkeypatch.setenv("FAKE_STAGE_MARKERS", str(markers))
    sys.modules.pop("fake_stages", None)
    import fake_stages

    return dict(fake_stages.ADAPTERS)


@pytest.fixture
def project_file(tmp_path: Path) -> Path:
    return write_project(tmp_path / "proj")
