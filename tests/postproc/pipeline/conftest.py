"""Fixtures of the pipeline tests: a small project on fake inputs, fake stages importable,
a loopback Dask cluster of real subprocesses."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]


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
def fake_stages(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, Any]:
    """The registry with the fake run functions (module `fake_stages` on sys.path),
    markers in tmp_path/markers."""
    monkeypatch.syspath_prepend(str(HERE))
    markers = tmp_path / "markers"
    markers.mkdir()
    monkeypatch.setenv("FAKE_STAGE_MARKERS", str(markers))
    sys.modules.pop("fake_stages", None)
    import fake_stages  # type: ignore[import-not-found]  # on the sys.path entry added above

    return dict(fake_stages.STAGES)


@pytest.fixture
def project_file(tmp_path: Path) -> Path:
    return write_project(tmp_path / "proj")


@dataclass
class LoopbackCluster:
    """A Dask scheduler and workers on 127.0.0.1, each a real subprocess."""

    address: str
    workers: list[subprocess.Popen[bytes]]


@contextlib.contextmanager
def loopback_cluster(
    logs: Path, *, workers: int = 2, env: dict[str, str] | None = None
) -> Iterator[LoopbackCluster]:
    """Start `dask scheduler` and `workers` one-thread workers (no nanny: the worker's pid
    is the process that runs the tasks) with this folder and the repository on
    PYTHONPATH; stop them all (SIGINT, then kill) on exit."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    address = f"tcp://127.0.0.1:{port}"
    environment = {
        **os.environ,
        **(env or {}),
        "PYTHONPATH": os.pathsep.join([str(HERE), str(REPO), os.environ.get("PYTHONPATH", "")]),
        "WRECKMAP_PROGRESS": "0",
    }
    logs.mkdir(parents=True, exist_ok=True)
    procs: list[subprocess.Popen[bytes]] = []

    def start(args: list[str], name: str) -> subprocess.Popen[bytes]:
        with (logs / f"{name}.log").open("wb") as log_file:
            proc = subprocess.Popen(
                [sys.executable, "-m", *args],
                env=environment,
                stdout=log_file,
                stderr=subprocess.STDOUT,
            )
        procs.append(proc)
        return proc

    try:
        start(
            ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--dashboard-address", ":0", "--no-show"],
            "scheduler",
        )  # fmt: skip
        worker_args = ["--nthreads", "1", "--no-nanny", "--host", "127.0.0.1", "--no-dashboard"]
        started = [
            start(
                ["distributed.cli.dask_worker", address, *worker_args, "--name", f"w{k}"],
                f"worker{k}",
            )
            for k in range(workers)
        ]
        yield LoopbackCluster(address=address, workers=started)
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
