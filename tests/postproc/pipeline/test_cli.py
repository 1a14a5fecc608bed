"""`wreckmap-post run` and `report` as real subprocesses."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def wreckmap_post(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "WRECKMAP_PROGRESS": "0", "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "postproc.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=120,
        check=False,
    )


def test_run_help_and_project_errors(tmp_path: Path) -> None:
    shown = wreckmap_post("run", "--help", cwd=tmp_path)
    assert shown.returncode == 0 and "--scheduler" in shown.stdout and "example" in shown.stdout
    (tmp_path / "p.yaml").write_text("sessions:\n  - {name: a, euroc: missing}\n")
    failed = wreckmap_post("run", "p.yaml", cwd=tmp_path)
    assert failed.returncode == 1
    assert "p.yaml: sessions[0].euroc:" in failed.stderr and "does not exist" in failed.stderr
    bad = wreckmap_post("run", "p.yaml", "--scheduler", "mpi", cwd=tmp_path)
    assert bad.returncode == 1


def test_run_reports_a_failing_stage_and_blocks_downstream(tmp_path: Path) -> None:
    (tmp_path / "empty" / "mav0").mkdir(parents=True)
    (tmp_path / "p.yaml").write_text(
        "name: t\noutput: out\nsessions:\n  - {name: a, euroc: empty}\n"
    )
    result = wreckmap_post("run", "p.yaml", cwd=tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    stages = ("slam", "sfm", "dense")
    rows = [line.split() for line in result.stdout.splitlines()]
    table = {row[0]: row[2] for row in rows if len(row) > 2 and row[0] in stages}
    assert table["slam"] == "failed" and table["sfm"] == "blocked" and table["dense"] == "blocked"
    assert "note: merge: no targets in the project" in result.stdout
    assert (tmp_path / "out" / "logs" / "slam_a.log").is_file()
    assert not (tmp_path / "out" / "sessions" / "a").exists()
    report = tmp_path / "out" / "report.html"
    assert f"report: {report}" in result.stdout and report.is_file()
    again = wreckmap_post("report", "p.yaml", "--out", "r.html", cwd=tmp_path)
    assert again.returncode == 0 and (tmp_path / "r.html").is_file()
