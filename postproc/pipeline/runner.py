"""The stage graph of a project, run with content-hash skipping and atomic outputs.

The stages and their graph come from the registry (`postproc.pipeline.stages.STAGES`):
each entry says which hand-off folder kind it writes (`shared.folders`), which it reads
and where its folder goes. Layout of the output folder (`project.output`)::

    calibration/              calibrate (CalibrationFolder), when calibrated from a recording
    imports/<session>/        GoPro chapters imported (SessionFolder), when needed
    sessions/<session>/       SLAM result (SlamFolder)
    sessions/<session>/depth/ depth stage (DepthFolder)
    merge/  sfm/  dense/      the project stages (MergeFolder, SfmFolder, DenseFolder)
    logs/<stage>[_<session>].log    one log per stage run
    report.html, evaluation.json    (`report`)

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
import json
import logging
import os
import shutil
import socket
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from postproc.pipeline.project import Project, SessionSpec
from postproc.pipeline.stages import STAGES, NotPlanned, RunFn, Stage, check_output
from shared.errors import InputError, WreckmapError
from shared.folders import jsonable
from shared.fsutil import atomic_path, write_text_atomic
from shared.memory import PeakMemory

log = logging.getLogger(__name__)

STAMP_NAME = ".wreckmap-stage.json"
FORMAT_VERSION = 2


@dataclass(kw_only=True)
class Task:
    """One stage run: `stage` for `session` (None: the whole project) into `out`.

    inputs: name -> path or list of paths, as the stage's run function receives them.
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
    """What a worker needs to run a task (picklable: paths, options, and the stage's run
    function and folder kind, which travel by reference)."""

    key: str
    stage: str
    run: RunFn
    writes: type
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
    """How a task ended: status is done, skipped (up to date), failed or blocked."""

    key: str
    stage: str
    session: str | None
    status: str
    seconds: float = 0.0
    message: str = ""
    worker: str = ""
    peak_rss_mib: float = 0.0


@dataclass
class RunResult:
    """Every task's outcome, in plan order, plus notes on stages left out of the plan."""

    outcomes: list[TaskOutcome]
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(o.status in ("done", "skipped") for o in self.outcomes)

    @property
    def failed(self) -> list[TaskOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def exit_code(self) -> int:
        """0 every stage done or up to date, 1 a stage failed (or was blocked)."""
        return 0 if self.ok else 1


def plan(
    project: Project, stages: Mapping[str, Stage] | None = None
) -> tuple[list[Task], list[str]]:
    """The tasks of `project` in dependency order, and notes on stages not planned (why).

    Derived from the registry (`stages`, default `STAGES`): its order, with each run of
    consecutive session stages laid out session by session; each read resolved to the
    planned task that writes that folder kind, else to what the project file gives.
    """
    registry = STAGES if stages is None else stages
    out = project.output
    tasks: list[Task] = []
    notes: list[str] = []
    # Folder kind -> the tasks writing it, by session (None: the project's task).
    writers: dict[type, dict[str | None, Task]] = {}

    def add(stage: Stage, session: SessionSpec | None) -> str | None:
        given = stage.sources(project, session)
        if isinstance(given, NotPlanned):
            return None if given.quiet else given.reason
        name = session.name if session is not None else None
        inputs = dict(given.inputs)
        deps: list[str] = []
        soft: list[str] = []
        for read in stage.reads:
            by_session = writers.get(read.kind, {})
            if stage.per_session or None in by_session:
                found = [by_session[k] for k in (name, None) if k in by_session][:1]
                value: Any = found[0].out if found else None
            else:  # a project stage reading a session kind: every session's
                found = list(by_session.values())
                value = [t.out for t in found]
            if read.soft:
                soft += [t.key for t in found]
                continue
            if found:
                deps += [t.key for t in found]
                inputs[read.name] = value
            elif read.name not in inputs and not read.optional:
                raise InputError(
                    f"{project.path}: stage {stage.name} reads a {read.kind.kind} folder "
                    "that no planned stage writes and the project does not give"
                )
        key = stage.name if name is None else f"{stage.name}:{name}"
        task = Task(
            key=key,
            stage=stage.name,
            session=name,
            out=stage.place(out, name),
            inputs=inputs,
            raw_inputs=tuple(given.raw),
            deps=tuple(deps),
            soft_deps=tuple(soft),
            option_overrides=dict(given.overrides),
        )
        tasks.append(task)
        writers.setdefault(stage.writes, {})[name] = task
        return None

    entries = list(registry.values())
    k = 0
    while k < len(entries):
        if not entries[k].per_session:
            reason = add(entries[k], None)
            if reason:
                notes.append(f"{entries[k].name}: {reason} (not planned)")
            k += 1
            continue
        group = []
        while k < len(entries) and entries[k].per_session:
            group.append(entries[k])
            k += 1
        left_out: dict[str, dict[str, list[str]]] = {}
        for session in project.sessions:
            for stage in group:
                reason = add(stage, session)
                if reason:
                    left_out.setdefault(stage.name, {}).setdefault(reason, []).append(session.name)
        for stage in group:
            for reason, names in left_out.get(stage.name, {}).items():
                notes.append(f"{stage.name}: {reason} for {', '.join(names)} (not planned)")
    return tasks, notes


def run_project(
    project: Project,
    *,
    backend: Any | None = None,
    stages: Mapping[str, Stage] | None = None,
    force: bool = False,
    echo: Callable[[str], None] | None = None,
) -> RunResult:
    """Run every task of `project` not already up to date; returns every task's outcome.

    backend: where tasks run (`dask_backend.make_backend`); None runs them in this process.
    stages: the stage registry (default `STAGES`; tests give entries with other run
        functions).
    force: rerun every stage even when up to date.
    echo: where progress lines go (default: log.info).
    """
    from postproc.pipeline.dask_backend import InlineBackend
    from shared.progress import progress_bar

    say = echo or log.info
    registry = STAGES if stages is None else stages
    own_backend = backend is None
    backend = backend or InlineBackend()
    tasks, notes = plan(project, registry)
    project.output.mkdir(parents=True, exist_ok=True)
    (project.output / "logs").mkdir(exist_ok=True)
    hashes = ContentHashCache(project.output / ".wreckmap" / "hash-cache.json")
    outcomes: dict[str, TaskOutcome] = {}
    digests: dict[str, str] = {}
    running: dict[Any, tuple[Task, float]] = {}
    context = {
        # A camchain calibrated from a recording comes as the calibrate task's folder.
        "camchain": project.camchain,
        "imu_yaml": project.imu_yaml,
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
                try:
                    options = project.options_for(task.stage, registry[task.stage])
                    if task.option_overrides:
                        options = dataclasses.replace(options, **task.option_overrides)
                    upstream = {**digests}
                    for soft in task.soft_deps:
                        if outcomes[soft].status not in ("done", "skipped"):
                            upstream[soft] = outcomes[soft].status
                    digest = task_digest(task, options, upstream, hashes)
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
                    run=registry[task.stage].run,
                    writes=registry[task.stage].writes,
                    options=options,
                    inputs=task.inputs,
                    out=task.out,
                    digest=digest,
                    log_path=project.output / "logs" / f"{task.key.replace(':', '_')}.log",
                    context={k: context[k] for k in ("camchain", "imu_yaml", "parallel")},
                    force=force,
                    stamp={
                        "stage": task.stage,
                        "session": task.session,
                        "digest": digest,
                        "deps": {d: upstream[d] for d in (*task.deps, *task.soft_deps)},
                        "options": jsonable(options),
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
                    outcome.peak_rss_mib = float(report.get("peak_rss_mib", 0.0))
                outcomes[task.key] = outcome
                if outcome.status == "failed":
                    _remove_stale(task)
                bar.update(1)
                line = f"  {task.key}: {outcome.status}"
                if outcome.status == "done":
                    line += f" in {outcome.seconds:.1f} s, peak {outcome.peak_rss_mib:.0f} MiB"
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
    return RunResult([outcomes[t.key] for t in tasks], notes)


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
) -> str:
    """SHA-256 of the stage, its options, its raw inputs' contents and its upstream digests."""
    raw = [*task.raw_inputs]
    document = {
        "format": FORMAT_VERSION,
        "stage": task.stage,
        "options": jsonable(options),
        "raw": sorted(hashes.digest(p) for p in raw),
        "upstream": {d: upstream[d] for d in (*task.deps, *task.soft_deps)},
        "input_names": sorted(task.inputs),
    }
    return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()


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
    """Run one stage on this worker: partial folder, run function, stamp, atomic rename.

    Returns {"seconds", "worker"}. The partial folder is unique to this attempt, so a
    rerun after a killed worker never mixes with the dead attempt's files.
    """
    if not spec.force and stamp_digest(spec.out) == spec.digest:
        # Done already by an earlier attempt whose result the scheduler lost (its worker
        # died after finishing): rerunning would swap the folder under running readers.
        stamp = json.loads((spec.out / STAMP_NAME).read_text(encoding="utf-8"))
        return {
            "seconds": float(stamp.get("seconds", 0.0)),
            "worker": stamp.get("worker", ""),
            "peak_rss_mib": float(stamp.get("peak_rss_mib", 0.0)),
        }
    spec.out.parent.mkdir(parents=True, exist_ok=True)
    partial = (
        spec.out.parent / f".{spec.out.name}.partial-{spec.digest[:12]}-{uuid.uuid4().hex[:8]}"
    )
    worker = f"{socket.gethostname()}:{os.getpid()}"
    started = time.monotonic()
    with _task_log(spec.log_path) as task_log:
        task_log.info("%s on %s: digest %s, output %s", spec.key, worker, spec.digest, spec.out)
        try:
            with PeakMemory() as peak:
                spec.run(copy.deepcopy(spec.options), spec.inputs, partial, context=spec.context)
            check_output(spec.stage, spec.writes, partial)
            seconds = time.monotonic() - started
            stamp = {
                **spec.stamp,
                "seconds": seconds,
                # The worker process's peak during the task (shared with any task that ran
                # beside it on the same worker).
                "peak_rss_mib": round(peak.mib, 1),
                "peak_rss_since_start": peak.since_start,
                "worker": worker,
                "finished": time.time(),
            }
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
        task_log.info(
            "%s done in %.1f s, peak resident memory %.0f MiB", spec.key, seconds, peak.mib
        )
    return {"seconds": seconds, "worker": worker, "peak_rss_mib": peak.mib}


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
