"""The real dense stage inside a pipeline run on a loopback Dask cluster (a scheduler and
two workers, real subprocesses): its per-image depth maps run as separate tasks on both
workers, and every output equals a run in this process."""

from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from postproc.pipeline.dask_backend import DaskBackend, make_backend
from postproc.pipeline.project import load_project
from postproc.pipeline.runner import run_project

from .conftest import loopback_cluster, write_project

HERE = Path(__file__).resolve().parent

# Small and single-threaded where it matters: no mesh, one fusion thread, every image a
# reference (seven per-image tasks to spread).
DENSE_OPTIONS = """stages:
  dense:
    max_image_size_px: 256
    make_mesh: false
    view_selection: {enabled: false}
    fusion: {num_threads: 1}
"""


def _dense_fixtures() -> Any:
    """The dense tests' scene builders (tests/postproc/dense/conftest.py)."""
    path = HERE.parent / "dense" / "conftest.py"
    spec = importlib.util.spec_from_file_location("dense_test_fixtures", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    # Registered first: its dataclasses look their module up while being defined.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def dense_outputs(root: Path) -> dict[str, bytes]:
    """The dense stage's data files (depth, normal and support maps, fused cloud and
    visibility), by path relative to the project output; dense.json holds timings and is
    left out."""
    dense = root / "dense"
    files = [dense / "fused.ply", dense / "fused.ply.vis"]
    files += sorted((dense / "workspace" / "stereo").rglob("*.bin"))
    return {str(p.relative_to(root)): p.read_bytes() for p in files}


@pytest.mark.slow
def test_dense_images_spread_over_two_dask_workers(
    tmp_path: Path, fake_stages: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    fixtures = _dense_fixtures()
    from sim.scene import build_wreck_scene

    scene = build_wreck_scene(seed=3, texel_m=0.02, seafloor_texel_m=0.06)
    sfm = fixtures.build_sfm(tmp_path / "sfm", scene, fixtures.hull_poses(7))
    monkeypatch.setenv("FAKE_SFM_SOURCE", str(sfm.folder))
    monkeypatch.setenv("WRECKMAP_PROGRESS", "0")
    import fake_stages as module  # type: ignore[import-not-found]  # on the conftest's sys.path

    from postproc.pipeline.stages import run_dense

    # The real dense stage on a copied SfM folder; the other stages faked.
    stages = module.with_runs({**module.RUNS, "sfm": module.run_sfm_copy, "dense": run_dense})
    project_file = write_project(tmp_path / "proj", extra=DENSE_OPTIONS)

    local = load_project(project_file)
    assert run_project(local, stages=stages).exit_code() == 0
    expected = dense_outputs(local.output)
    assert len(expected) == 2 + 3 * 7
    local_report = json.loads((local.output / "dense" / "dense.json").read_text())
    assert len(local_report["depth_maps"]["workers"]) == 1

    env = {"FAKE_SFM_SOURCE": str(sfm.folder)}
    with loopback_cluster(tmp_path / "dask-logs", workers=2, env=env) as cluster:
        backend = None
        deadline = time.monotonic() + 60
        while backend is None:
            try:
                backend = make_backend(cluster.address)
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        assert isinstance(backend, DaskBackend)
        try:
            backend.client.wait_for_workers(2, timeout=60)
            remote = load_project(project_file)
            remote.output = tmp_path / "dask-out"
            result = run_project(remote, stages=stages, backend=backend)
        finally:
            backend.close()
        pids = {str(w.pid) for w in cluster.workers}

    statuses = {o.key: o.status for o in result.outcomes}
    assert set(statuses.values()) == {"done"}, statuses
    report = json.loads((remote.output / "dense" / "dense.json").read_text())
    workers = report["depth_maps"]["workers"]
    # Seven depth maps, computed on both workers (host:pid), none in this process.
    assert sum(workers.values()) == 7
    assert {w.rsplit(":", 1)[1] for w in workers} == pids
    assert dense_outputs(remote.output) == expected
