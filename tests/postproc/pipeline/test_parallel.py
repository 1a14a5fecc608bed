"""Map functions: serial, a local process pool, Dask from inside a worker; the stage
adapters hand them to SfM and dense."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import pytest

from postproc.pipeline import stages
from postproc.pipeline.dask_backend import InlineBackend, ProcessBackend
from postproc.pipeline.parallel import (
    ParallelSpec,
    dask_map,
    in_dask_worker,
    make_map,
    process_map,
)
from shared.errors import InputError
from shared.progress import serial_map


@pytest.fixture
def helpers(fake_stages: dict[str, Any]) -> Any:
    """The per-item functions of `fake_stages` (importable in spawned processes)."""
    import fake_stages as module  # type: ignore[import-not-found]  # on the conftest's sys.path

    return module


def test_serial_map_keeps_the_order(helpers: Any) -> None:
    square = helpers.square
    assert serial_map(square, [3, 1, 2]) == [9, 1, 4]
    assert serial_map(square, []) == []
    assert make_map(None) is serial_map
    assert make_map(ParallelSpec()) is serial_map


def test_process_map_spreads_over_processes(tmp_path: Path, helpers: Any) -> None:
    square, pid_of, pid_after_meeting = helpers.square, helpers.pid_of, helpers.pid_after_meeting
    tmp_path = tmp_path / "met"
    tmp_path.mkdir()
    results = process_map(2)(pid_after_meeting, [str(tmp_path)] * 4)
    assert len(set(results)) == 2 and os.getpid() not in results
    assert sorted(int(p.name) for p in tmp_path.iterdir()) == sorted(set(results))
    assert make_map(ParallelSpec(kind="process", workers=2))(square, [4, 5, 6]) == [16, 25, 36]
    # One worker, or a single item: no pool, this process.
    assert process_map(1)(pid_of, [0, 1]) == [os.getpid()] * 2
    assert process_map(2)(pid_of, [0]) == [os.getpid()]


def test_bad_specs_are_refused() -> None:
    with pytest.raises(InputError, match="0 workers"):
        process_map(0)
    with pytest.raises(InputError, match="parallel kind 'mpi'"):
        make_map(ParallelSpec(kind="mpi"))  # type: ignore[arg-type]


def test_dask_map_outside_a_worker_runs_here(
    caplog: pytest.LogCaptureFixture, helpers: Any
) -> None:
    square = helpers.square
    assert not in_dask_worker()
    with caplog.at_level(logging.WARNING):
        assert make_map(ParallelSpec(kind="dask"))(square, [1, 2]) == [1, 4]
    assert "outside a Dask worker" in caplog.text
    assert dask_map(square, []) == []


def test_backends_say_how_to_spread() -> None:
    assert InlineBackend().parallel == ParallelSpec(kind="serial")
    backend = ProcessBackend(2)
    try:
        assert backend.parallel == ParallelSpec(kind="process", workers=2)
    finally:
        backend.close()


def test_adapters_pass_the_map_function(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, helpers: Any
) -> None:
    square = helpers.square
    import postproc.dense.stage
    import postproc.sfm.stage

    calls: dict[str, Any] = {}

    def dense_run(options: Any, sfm_dir: Path, out: Path, **kwargs: Any) -> Path:
        calls["dense"] = kwargs
        return out

    def sfm_with_map(
        options: Any, input_dirs: list[Path], out: Path, *, merge: Path | None = None,
        overwrite: bool = False, map_fn: Any = None,
    ) -> Path:  # fmt: skip
        calls["sfm"] = {"overwrite": overwrite, "map_fn": map_fn, "merge": merge}
        return out

    monkeypatch.setattr(postproc.dense.stage, "run", dense_run)
    context = {"parallel": ParallelSpec(kind="process", workers=3)}
    stages.run_dense(None, {"sfm": tmp_path}, tmp_path / "d", context=context)
    assert calls["dense"]["overwrite"] is True
    assert calls["dense"]["map_fn"](square, [1, 2, 3]) == [1, 4, 9]
    monkeypatch.setattr(postproc.sfm.stage, "run", sfm_with_map)
    stages.run_sfm(None, {"slam": [tmp_path]}, tmp_path / "s", context={"parallel": None})
    # Inline, the stage does its per-image work itself (SfM matches in its one database
    # instead of a copy of it per chunk of pairs).
    assert calls["sfm"]["map_fn"] is None and calls["sfm"]["merge"] is None
    inline = {"parallel": InlineBackend().parallel}
    stages.run_sfm(None, {"slam": [tmp_path]}, tmp_path / "s", context=inline)
    assert calls["sfm"]["map_fn"] is None
    stages.run_sfm(None, {"slam": [tmp_path]}, tmp_path / "s", context=context)
    pool_map = calls["sfm"]["map_fn"]
    assert pool_map is not None and pool_map(square, [2, 3]) == [4, 9]
    inputs = {"slam": [tmp_path], "merge": tmp_path / "merge"}
    stages.run_sfm(None, inputs, tmp_path / "s", context={"parallel": None})
    assert calls["sfm"]["merge"] == tmp_path / "merge"
