"""Deterministic stand-ins for the stages' run functions, for runner and scheduler tests.

Each writes a small output derived only from its inputs' contents and options (so two
runs anywhere give identical files) plus the marker of the folder kind the registry
says the stage writes. `STAGES` is the registry with these run functions. Environment:
FAKE_STAGE_MARKERS (a folder: one `<key>.<pid>.<n>.started` file per call, holding the
pid), FAKE_STAGE_SLEEP_S (seconds to sleep mid-stage), FAKE_STAGE_FAIL (a stage key to
fail with a StageError). Imported by name (`fake_stages`) from this folder, by the test
process and by Dask workers started with this folder on PYTHONPATH.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import time
import uuid
from pathlib import Path
from typing import Any

from postproc.pipeline.stages import STAGES as REAL_STAGES
from postproc.pipeline.stages import Stage
from shared.errors import StageError


def _content(path: Path) -> str:
    """Digest of a file or folder (names and bytes), skipping hidden entries and depth/."""
    h = hashlib.sha256()
    path = Path(path)
    if path.is_file():
        h.update(path.read_bytes())
    elif path.is_dir():
        for file in sorted(p for p in path.rglob("*") if p.is_file()):
            rel = file.relative_to(path)
            # Hidden entries are the runner's (stamps, partial folders of running stages).
            if rel.parts[0].startswith(".") or rel.name.startswith(".") or rel.parts[0] == "depth":
                continue
            h.update(str(rel).encode() + file.read_bytes())
    return h.hexdigest()


def _fake(stage: str, options: Any, inputs: dict[str, Any], out: Path, key: str) -> Path:
    markers = os.environ.get("FAKE_STAGE_MARKERS")
    if markers:
        name = f"{key.replace(':', '_')}.{os.getpid()}.{uuid.uuid4().hex[:6]}.started"
        (Path(markers) / name).write_text(str(os.getpid()))
    out.mkdir(parents=True)
    (out / "part1.txt").write_text("first half\n")
    time.sleep(float(os.environ.get("FAKE_STAGE_SLEEP_S", "0")))
    if os.environ.get("FAKE_STAGE_FAIL") == key:
        raise StageError(f"{key}: failing on purpose")
    record = {
        "stage": stage,
        "options": json.dumps(dataclasses.asdict(options), sort_keys=True, default=str),
        "inputs": {
            name: [_content(Path(p)) for p in (value if isinstance(value, list) else [value])]
            for name, value in sorted(inputs.items())
        },
    }
    marker = REAL_STAGES[stage].writes(out).marker_path
    marker.write_text(json.dumps(record, sort_keys=True, indent=1))
    return out


def _key(stage: str, inputs: dict[str, Any]) -> str:
    if stage == "slam":
        return f"slam:{Path(inputs['recording']).name}"
    if stage == "depth":
        return f"depth:{Path(inputs['slam']).name}"
    if stage == "import":
        return f"import:{Path(inputs['videos'][0]).stem}"
    return stage


def _run(
    stage: str, options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]
) -> Path:
    return _fake(stage, options, inputs, out, _key(stage, inputs))


# One picklable run function per stage (a partial of a top-level function travels to a
# Dask worker by reference).
RUNS = {name: functools.partial(_run, name) for name in REAL_STAGES}


def with_runs(runs: dict[str, Any]) -> dict[str, Stage]:
    """The registry with the run functions of `runs` in place of the real ones."""
    return {
        name: dataclasses.replace(entry, run=runs[name]) if name in runs else entry
        for name, entry in REAL_STAGES.items()
    }


STAGES = with_runs(RUNS)


def run_sfm_copy(
    options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]
) -> Path:
    """An SfM stand-in that copies a ready SfM folder (FAKE_SFM_SOURCE: a COLMAP model in
    `sparse/` and its `images/`), for running the real dense stage in the pipeline."""
    import shutil

    shutil.copytree(os.environ["FAKE_SFM_SOURCE"], out)
    REAL_STAGES["sfm"].writes(out).marker_path.write_text("{}\n")
    return out


# Per-item functions for the map tests (importable by name in spawned processes).


def square(x: int) -> int:
    return x * x


def pid_of(_: object) -> int:
    return os.getpid()


def pid_after_meeting(folder: str) -> int:
    """Register this process in `folder`, then wait (up to 60 s) until two processes have:
    returns only when the items really ran in two processes at once."""
    (Path(folder) / str(os.getpid())).touch()
    deadline = time.monotonic() + 60.0
    while len(list(Path(folder).iterdir())) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    return os.getpid()
