"""The stage graph of a project, run with content-hash skipping and atomic outputs.

Layout of the output folder (`project.output`)::

    imports/<session>/        GoPro chapters imported (field session folder), when needed
    sessions/<session>/       SLAM result folder (trajectory.tum, keyframes/, stats.json...)
    sessions/<session>/depth/ depth stage (sync.json, trajectory_world*.tum, depth_sync.png)
    merge/                    transforms.json, targets.json, merge_top.png, merge_side.png
    sfm/                      COLMAP model (sparse/0), stats.json
    dense/                    fused.ply, mesh.ply, dense.json
    logs/<stage>[_<session>].log    one log per stage run
    report.html, evaluation.json    (`report`)

The SLAM folder is named after the session because the merge and SfM stages name the
sessions after their folders, and the depth folder lives inside it because both look for
`depth/` beside the SLAM results.

Skipping: each finished stage folder holds `.wreckmap-stage.json` with a digest (SHA-256)
of the stage name, its options and its inputs: raw inputs (recordings, dive logs,
calibration, targets) by content, upstream stages by their own digests (a Merkle chain).
A stage whose digest matches is not run again; changing an option reruns that stage and
everything downstream. Every stage writes into a hidden partial folder beside its final
place and is renamed into place when complete, so a killed worker never leaves a
half-written output (the rerun starts from scratch elsewhere).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import importlib
import json
import logging
import os
import shutil
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from postproc.pipeline.project import (
    STAGE_MODULES,
    STAGE_OPTIONS,
    Project,
    stage_module_available,
)
from shared.errors import InputError, WreckmapError
from shared.fsutil import atomic_path, write_text_atomic

log = logging.getLogger(__name__)

STAMP_NAME = ".wreckmap-stage.json"
FORMAT_VERSION = 1
# Where each stage's adapter lives ("module:function"); tests swap in fakes.
DEFAULT_ADAPTERS: dict[str, str] = {
    stage: f"postproc.pipeline.stages:run_{stage}" for stage in STAGE_OPTIONS
}
STAGE_ORDER = ("calibrate", "import", "slam", "depth", "merge", "sfm", "dense")


@dataclass(kw_only=True)
class Task:
    """One stage run: `stage` for `session` (None: the whole project) into `out`.

    inputs: name -> path or list of paths, as the adapter receives them.
    raw_inputs: the files and folders hashed by content (the project's own inputs).
    deps: keys of the tasks whose outputs are inputs here.
    soft_deps: tasks whose outputs are used when they exist (depth for merge and SfM): a
        failure there does not block this task, and its outcome is part of the digest.
    option_overrides: fields of the stage's options set for this task only (a session's
        own dive-clock offset); part of the digest like every option.
    """

    key: str
    stage: str
    session: str | None
    out: Path
    inputs: dict[str, Any]
    raw_inputs: tuple[Path, ...] = ()
    deps: tuple[str, ...] = ()
    soft_deps: tuple[str, ...] = ()
    option_overrides: dict[str, Any] = field(default_factory=dict)


@dataclass(kw_only=True)
class TaskSpec:
    """What a worker needs to run a task (picklable: paths and options, no data)."""

    key: str
    stage: str
    adapter: str
    options: Any
    inputs: dict[str, Any]
    out: Path
    digest: str
    log_path: Path
    context: dict[str, Any]
    stamp: dict[str, Any]
    force: bool = False


@dataclass
class TaskOutcome:
    """How a task ended: status is done, skipped (up to date), failed, missing or blocked."""

    key: str
    stage: str
    session: str | None
    status: str
    seconds: float = 0.0
    message: str = ""
    worker: str = ""


@dataclass
class RunResult:
    """Every task's outcome, in plan order, plus notes on stages left out of the plan."""

    outcomes: list[TaskOutcome]
    notes: list[str] = field(default_factory=list)
    missing_modules: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(o.status in ("done", "skipped") for o in self.outcomes)

    @property
    def failed(self) -> list[TaskOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def exit_code(self) -> int:
        """0 all done, 1 a stage failed, 2 stages not built yet (and nothing failed)."""
        if self.failed:
            return 1
        return 2 if not self.ok else 0


def plan(project: Project) -> tuple[list[Task], list[str]]:
    """The tasks of `project` in dependency order, and notes on stages not planned (why)."""
    out = project.output
    tasks: list[Task] = []
    notes: list[str] = []
    slam_keys: list[str] = []
    slam_dirs: list[Path] = []
    depth_missing: list[str] = []
    # Calibrated from a recording: import and SLAM wait for it and use its camchain.
    calib_deps: tuple[str, ...] = ()
    if project.calibration_recording is not None and project.calibration_target is not None:
        tasks.append(
            Task(
                key="calibrate",
                stage="calibrate",
                session=None,
                out=out / "calibration",
                inputs={
                    "recording": project.calibration_recording,
                    "target": project.calibration_target,
                },
                raw_inputs=(project.calibration_recording, project.calibration_target),
            )
        )
        calib_deps = ("calibrate",)
    for session in project.sessions:
        recording: Path
        slam_deps: tuple[str, ...] = ()
        raw: tuple[Path, ...]
        if session.source == "gopro":
            imported = out / "imports" / session.name
            tasks.append(
                Task(
                    key=f"import:{session.name}",
                    stage="import",
                    session=session.name,
                    out=imported,
                    inputs={"videos": list(session.paths)},
                    raw_inputs=tuple(session.paths),
                    deps=calib_deps,
                )
            )
            recording, slam_deps, raw = imported, (f"import:{session.name}", *calib_deps), ()
        else:
            recording, raw = session.paths[0], (session.paths[0],)
            slam_deps = calib_deps
        slam_dir = out / "sessions" / session.name
        tasks.append(
            Task(
                key=f"slam:{session.name}",
                stage="slam",
                session=session.name,
                out=slam_dir,
                inputs={"recording": recording},
                raw_inputs=raw,
                deps=slam_deps,
            )
        )
        slam_keys.append(f"slam:{session.name}")
        slam_dirs.append(slam_dir)
        if session.dive is not None:
            tasks.append(
                Task(
                    key=f"depth:{session.name}",
                    stage="depth",
                    session=session.name,
                    out=slam_dir / "depth",
                    inputs={"slam": slam_dir, "dive": session.dive},
                    raw_inputs=(session.dive,),
                    deps=(f"slam:{session.name}",),
                    option_overrides=(
                        {"time_offset_s": session.dive_time_offset_s}
                        if session.dive_time_offset_s is not None
                        else {}
                    ),
                )
            )
        else:
            depth_missing.append(session.name)
    if depth_missing:
        notes.append(f"depth: no dive log for {', '.join(depth_missing)} (not planned)")
    depth_keys = [t.key for t in tasks if t.stage == "depth"]
    merge_key: str | None = None
    if project.targets:
        merge_key = "merge"
        tasks.append(
            Task(
                key="merge",
                stage="merge",
                session=None,
                out=out / "merge",
                inputs={"slam": list(slam_dirs)},
                raw_inputs=tuple(project.targets),
                deps=tuple(slam_keys),
                soft_deps=tuple(depth_keys),
            )
        )
    else:
        notes.append("merge: no targets in the project (not planned)")
    sfm_inputs: dict[str, Any] = {"slam": list(slam_dirs)}
    if merge_key is not None:
        sfm_inputs["merge"] = out / "merge"
    tasks.append(
        Task(
            key="sfm",
            stage="sfm",
            session=None,
            out=out / "sfm",
            inputs=sfm_inputs,
            deps=(*slam_keys, *([merge_key] if merge_key else [])),
            soft_deps=tuple(depth_keys),
        )
    )
    tasks.append(
        Task(
            key="dense",
            stage="dense",
            session=None,
            out=out / "dense",
            inputs={"sfm": out / "sfm"},
            deps=("sfm",),
        )
    )
    return tasks, notes


def run_project(
    project: Project,
    *,
    backend: Any | None = None,
    adapters: dict[str, str] | None = None,
    available: Callable[[str], bool] = stage_module_available,
    force: bool = False,
    echo: Callable[[str], None] | None = None,
) -> RunResult:
    """Run every task of `project` not already up to date; returns every task's outcome.

    backend: where tasks run (`dask_backend.make_backend`); None runs them in this process.
    adapters: stage -> "module:function" (default: `postproc.pipeline.stages`).
    available: whether a stage's module is built; a stage that is not stops its branch
        (its tasks are "missing", those downstream "blocked"); nothing is faked.
    force: rerun every stage even when up to date.
    echo: where progress lines go (default: log.info).
    """
    from postproc.pipeline.dask_backend import InlineBackend
    from shared.progress import progress_bar

    say = echo or log.info
    adapters = {**DEFAULT_ADAPTERS, **(adapters or {})}
    own_backend = backend is None
    backend = backend or InlineBackend()
    tasks, notes = plan(project)
    project.output.mkdir(parents=True, exist_ok=True)
    (project.output / "logs").mkdir(exist_ok=True)
    hashes = ContentHashCache(project.output / ".wreckmap" / "hash-cache.json")
    outcomes: dict[str, TaskOutcome] = {}
    digests: dict[str, str] = {}
    missing_modules: dict[str, str] = {}
    running: dict[Any, tuple[Task, float]] = {}
    context = {
        "camchain": project.camchain
        if project.calibration_recording is None
        else project.output / "calibration" / "camchain.yaml",
        "imu_yaml": project.imu_yaml,
        "targets": list(project.targets),
        # Where per-image work goes (not part of the digest: outputs are the same).
        "parallel": getattr(backend, "parallel", None),
    }
    say(f"{project.name}: {len(tasks)} stage runs for {len(project.sessions)} session(s)")
    bar = progress_bar(total=len(tasks), desc="pipeline", unit="stage")
    try:
        while len(outcomes) < len(tasks):
            submitted = False
            for task in tasks:
                if task.key in outcomes or any(t.key == task.key for t, _ in running.values()):
                    continue
                dep_states = [outcomes.get(d) for d in task.deps]
                if any(outcomes.get(d) is None for d in (*task.deps, *task.soft_deps)):
                    continue
                bad = [
                    s for s in dep_states if s is not None and s.status not in ("done", "skipped")
                ]
                if bad:
                    outcomes[task.key] = _outcome(
                        task, "blocked", f"needs {bad[0].key} ({bad[0].status})"
                    )
                    bar.update(1)
                    continue
                if not available(task.stage):
                    module = STAGE_MODULES.get(task.stage, STAGE_OPTIONS[task.stage][0])
                    missing_modules[task.stage] = module
                    outcomes[task.key] = _outcome(
                        task, "missing", f"stage {task.stage} is not built yet (module {module})"
                    )
                    bar.update(1)
                    continue
                try:
                    options = project.options_for(task.stage)
                    if task.option_overrides:
                        options = dataclasses.replace(options, **task.option_overrides)
                    upstream = {**digests}
                    for soft in task.soft_deps:
                        if outcomes[soft].status not in ("done", "skipped"):
                            upstream[soft] = outcomes[soft].status
                    digest = task_digest(task, options, upstream, hashes, context)
                except WreckmapError as error:
                    outcomes[task.key] = _outcome(task, "failed", str(error))
                    bar.update(1)
                    continue
                digests[task.key] = digest
                if not force and stamp_digest(task.out) == digest:
                    outcomes[task.key] = _outcome(task, "skipped", "up to date")
                    say(f"  {task.key}: up to date")
                    bar.update(1)
                    continue
                spec = TaskSpec(
                    key=task.key,
                    stage=task.stage,
                    adapter=adapters[task.stage],
                    options=options,
                    inputs=task.inputs,
                    out=task.out,
                    digest=digest,
                    log_path=project.output / "logs" / f"{task.key.replace(':', '_')}.log",
                    context={
                        k: context[k] for k in ("camchain", "imu_yaml", "targets", "parallel")
                    },
                    force=force,
                    stamp={
                        "stage": task.stage,
                        "session": task.session,
                        "digest": digest,
                        "deps": {d: upstream[d] for d in (*task.deps, *task.soft_deps)},
                        "options": jsonable(dataclasses.asdict(options))
                        if dataclasses.is_dataclass(options)
                        else jsonable(options),
                    },
                )
                say(f"  {task.key}: started ({backend.description})")
                handle = backend.submit(task.key, execute_task, spec)
                running[handle] = (task, time.monotonic())
                submitted = True
            if not running:
                if not submitted and len(outcomes) < len(tasks):
                    # Nothing runnable and nothing running: a dependency cycle cannot happen
                    # with plan(); stop rather than spin.
                    for task in tasks:
                        outcomes.setdefault(task.key, _outcome(task, "blocked", "not reachable"))
                continue
            for handle in backend.wait_any(list(running)):
                task, started = running.pop(handle)
                try:
                    report = backend.result(handle)
                except WreckmapError as error:
                    outcome = _outcome(task, "failed", str(error))
                except Exception as error:  # a bug in a stage: keep the others going, log it
                    log.exception("%s crashed", task.key)
                    outcome = _outcome(task, "failed", f"{type(error).__name__}: {error}")
                else:
                    outcome = _outcome(task, "done", "", worker=str(report.get("worker", "")))
                    outcome.seconds = float(report.get("seconds", time.monotonic() - started))
                outcomes[task.key] = outcome
                if outcome.status == "failed":
                    _remove_stale(task)
                bar.update(1)
                line = f"  {task.key}: {outcome.status}"
                if outcome.status == "done":
                    line += f" in {outcome.seconds:.1f} s"
                if outcome.message:
                    line += f" ({outcome.message})"
                say(line)
                say("  progress: " + session_progress(tasks, outcomes))
    finally:
        bar.close()
        hashes.save()
        if own_backend:
            backend.close()
    _remove_partials(tasks)
    result = RunResult([outcomes[t.key] for t in tasks], notes, missing_modules)
    for stage, module in missing_modules.items():
        not_run = sorted({o.stage for o in result.outcomes if o.status in ("missing", "blocked")})
        say(
            f"stopped at {stage}: module {module} is not built yet; not run: "
            + ", ".join(s for s in STAGE_ORDER if s in not_run)
        )
    return result


def session_progress(tasks: list[Task], outcomes: dict[str, TaskOutcome]) -> str:
    """One line: per session the stages finished of those planned, then the project stages."""
    parts = []
    sessions: dict[str | None, list[Task]] = {}
    for task in tasks:
        sessions.setdefault(task.session, []).append(task)
    for session, group in sessions.items():
        done = sum(
            1 for t in group if t.key in outcomes and outcomes[t.key].status in ("done", "skipped")
        )
        label = session if session is not None else "project"
        parts.append(f"{label} {done}/{len(group)}")
    return ", ".join(parts)


def _outcome(task: Task, status: str, message: str, *, worker: str = "") -> TaskOutcome:
    return TaskOutcome(task.key, task.stage, task.session, status, 0.0, message, worker)


def _remove_stale(task: Task) -> None:
    """A failed stage's output from an earlier run no longer matches its inputs and options:
    remove it so that no downstream stage reads it (soft dependencies look for it)."""
    if (task.out / STAMP_NAME).is_file():
        log.info("%s: removing the stale output of an earlier run (%s)", task.key, task.out)
        shutil.rmtree(task.out, ignore_errors=True)


def _remove_partials(tasks: list[Task]) -> None:
    """Leftover partial folders of killed attempts (nothing runs any more)."""
    for parent in {t.out.parent for t in tasks}:
        if not parent.is_dir():
            continue
        for path in parent.glob(".*.partial-*"):
            shutil.rmtree(path, ignore_errors=True)


def stamp_digest(out: Path) -> str | None:
    """The digest recorded in a finished stage folder, or None."""
    try:
        return str(json.loads((out / STAMP_NAME).read_text(encoding="utf-8"))["digest"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def task_digest(
    task: Task,
    options: Any,
    upstream: dict[str, str],
    hashes: ContentHashCache,
    context: dict[str, Any],
) -> str:
    """SHA-256 of the stage, its options, its raw inputs' contents and its upstream digests."""
    raw = [*task.raw_inputs]
    if task.stage in ("import", "slam"):
        # A calibrated camchain comes through the calibrate task's digest instead.
        given = [context.get("imu_yaml")]
        if "calibrate" not in task.deps:
            given.append(context.get("camchain"))
        raw += [p for p in given if p is not None]
    document = {
        "format": FORMAT_VERSION,
        "stage": task.stage,
        "options": jsonable(dataclasses.asdict(options))
        if dataclasses.is_dataclass(options)
        else jsonable(options),
        "raw": sorted(hashes.digest(p) for p in raw),
        "upstream": {d: upstream[d] for d in (*task.deps, *task.soft_deps)},
        "input_names": sorted(task.inputs),
    }
    return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()


def jsonable(value: Any) -> Any:
    """Options as JSON: Paths as strings, tuples as lists, anything else by repr."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return jsonable(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return repr(value)


class ContentHashCache:
    """SHA-256 of files and folders by content, cached by (path, size, mtime) between runs."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.entries: dict[str, list[Any]] = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            self.entries = {}
        self.changed = False

    def _file(self, path: Path) -> str:
        stat = path.stat()
        key = str(path.resolve())
        cached = self.entries.get(key)
        if cached is not None and cached[0] == stat.st_size and cached[1] == stat.st_mtime_ns:
            return str(cached[2])
        h = hashlib.sha256()
        with path.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        self.entries[key] = [stat.st_size, stat.st_mtime_ns, h.hexdigest()]
        self.changed = True
        return h.hexdigest()

    def digest(self, path: Path) -> str:
        """Content digest of a file, or of a folder (relative names and file digests)."""
        path = Path(path)
        if path.is_file():
            return self._file(path)
        if not path.is_dir():
            raise InputError(f"{path}: input missing (expected a file or a folder)")
        h = hashlib.sha256()
        for file in sorted(p for p in path.rglob("*") if p.is_file()):
            h.update(str(file.relative_to(path)).encode() + b"\0" + self._file(file).encode())
        return h.hexdigest()

    def save(self) -> None:
        if self.changed:
            write_text_atomic(self.path, json.dumps(self.entries), overwrite=True)


def execute_task(spec: TaskSpec) -> dict[str, Any]:
    """Run one stage on this worker: partial folder, adapter, stamp, atomic rename.

    Returns {"seconds", "worker"}. The partial folder is unique to this attempt, so a
    rerun after a killed worker never mixes with the dead attempt's files.
    """
    if not spec.force and stamp_digest(spec.out) == spec.digest:
        # Done already by an earlier attempt whose result the scheduler lost (its worker
        # died after finishing): rerunning would swap the folder under running readers.
        stamp = json.loads((spec.out / STAMP_NAME).read_text(encoding="utf-8"))
        return {"seconds": float(stamp.get("seconds", 0.0)), "worker": stamp.get("worker", "")}
    module_name, function_name = spec.adapter.split(":")
    adapter = getattr(importlib.import_module(module_name), function_name)
    spec.out.parent.mkdir(parents=True, exist_ok=True)
    partial = (
        spec.out.parent / f".{spec.out.name}.partial-{spec.digest[:12]}-{uuid.uuid4().hex[:8]}"
    )
    worker = f"{socket.gethostname()}:{os.getpid()}"
    started = time.monotonic()
    with _task_log(spec.log_path) as task_log:
        task_log.info("%s on %s: digest %s, output %s", spec.key, worker, spec.digest, spec.out)
        try:
            adapter(copy.deepcopy(spec.options), spec.inputs, partial, context=spec.context)
            from postproc.pipeline.stages import check_output

            check_output(spec.stage, partial)
            seconds = time.monotonic() - started
            stamp = {**spec.stamp, "seconds": seconds, "worker": worker, "finished": time.time()}
            write_text_atomic(partial / STAMP_NAME, json.dumps(stamp, indent=2) + "\n")
            with atomic_path(spec.out, overwrite=True) as tmp:
                partial.rename(tmp)
        except WreckmapError as error:
            task_log.error("%s failed: %s", spec.key, error)
            shutil.rmtree(partial, ignore_errors=True)
            raise
        except BaseException:
            task_log.exception("%s failed", spec.key)
            shutil.rmtree(partial, ignore_errors=True)
            raise
        task_log.info("%s done in %.1f s", spec.key, seconds)
    return {"seconds": seconds, "worker": worker}


class _ThreadFilter(logging.Filter):
    def __init__(self, thread: int) -> None:
        super().__init__()
        self.thread = thread

    def filter(self, record: logging.LogRecord) -> bool:
        return record.thread == self.thread


class _task_log:  # noqa: N801 (a context manager used like a function)
    """Send this thread's log records to `path` for the duration of the block."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> logging.Logger:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.handler = logging.FileHandler(self.path, mode="w", encoding="utf-8")
        self.handler.setLevel(logging.INFO)
        self.handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
        )
        self.handler.addFilter(_ThreadFilter(threading.get_ident()))
        root = logging.getLogger()
        self.level = root.level
        if root.level > logging.INFO or root.level == logging.NOTSET:
            root.setLevel(logging.INFO)
        root.addHandler(self.handler)
        # The runner's own lines about the task go to its log only (the console gets one
        # line per task from the runner), tracebacks included.
        self.task_logger = logging.getLogger("wreckmap.pipeline.task")
        self.task_logger.propagate = False
        self.task_logger.setLevel(logging.INFO)
        self.task_logger.addHandler(self.handler)
        return self.task_logger

    def __exit__(self, *exc: object) -> None:
        root = logging.getLogger()
        root.removeHandler(self.handler)
        self.task_logger.removeHandler(self.handler)
        root.setLevel(self.level)
        self.handler.close()
