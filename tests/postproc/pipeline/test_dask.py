"""Dask distributed on loopback: a scheduler and two workers as real subprocesses, one
killed mid-stage; the run completes and its outputs equal a local run's."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import pytest

from postproc.pipeline.dask_backend import DaskBackend, make_backend
from postproc.pipeline.project import load_project
from postproc.pipeline.runner import STAMP_NAME, run_project

from .conftest import loopback_cluster


def outputs(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
        and p.name != STAMP_NAME
        and p.relative_to(root).parts[0] not in ("logs", ".wreckmap")
    }


def wait_for(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.1)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.slow
def test_worker_killed_mid_stage_reruns_elsewhere(
    project_file: Path, fake_stages: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    markers = tmp_path / "markers"
    # The local reference run (no sleep).
    local = load_project(project_file)
    assert run_project(local, stages=fake_stages).exit_code() == 0
    expected = outputs(local.output)
    for p in markers.glob("*"):
        p.unlink()

    env = {"FAKE_STAGE_SLEEP_S": "2.0", "FAKE_STAGE_MARKERS": str(markers)}
    with loopback_cluster(tmp_path / "dask-logs", workers=2, env=env) as cluster:
        address, workers = cluster.address, cluster.workers
        backend = None
        deadline = time.monotonic() + 60
        while backend is None:
            try:
                backend = make_backend(address)
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        assert isinstance(backend, DaskBackend)
        backend.client.wait_for_workers(2, timeout=60)

        remote = load_project(project_file)
        remote.output = tmp_path / "dask-out"
        import threading

        killed: list[int] = []

        def kill_first_slam_worker() -> None:
            wait_for(lambda: any(markers.glob("slam_*.started")), 60, "a SLAM stage to start")
            time.sleep(0.5)  # mid-stage: its first half is written, the rest not
            pid = int(next(iter(markers.glob("slam_*.started"))).read_text())
            victim = next(w for w in workers if w.pid == pid)
            victim.send_signal(signal.SIGKILL)
            killed.append(pid)

        killer = threading.Thread(target=kill_first_slam_worker)
        killer.start()
        try:
            result = run_project(remote, stages=fake_stages, backend=backend)
        finally:
            killer.join()
            backend.close()
        assert killed, "no worker was killed"
        statuses = {o.key: o.status for o in result.outcomes}
        assert set(statuses.values()) == {"done"}, statuses
        # Every task after the kill ran on the surviving worker, and the killed stage ran twice.
        started = sorted(p.name for p in markers.glob("*.started"))
        killed_key = next(n for n in started if f".{killed[0]}." in n).split(".")[0]
        assert sum(1 for n in started if n.split(".")[0] == killed_key) == 2, started
        assert len(started) == 8, started
        assert all(o.worker and not o.worker.endswith(f":{killed[0]}") for o in result.outcomes)
        assert outputs(remote.output) == expected
        leftovers = [
            p for p in remote.output.rglob("*") if "partial" in p.name or p.name.endswith(".tmp")
        ]
        assert leftovers == []
