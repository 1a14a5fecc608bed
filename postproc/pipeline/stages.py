"""The stage registry: every stage of `wreckmap-post run` declared once, in `STAGES`.

An entry (`Stage`) says what the stage is called, its options dataclass, the function
that runs it, the hand-off folder kind it writes (`shared.folders`) and the kinds it
reads, where its folder goes in the run's output, and what it takes from the project
file. The runner's plan, digests and completeness checks, the `wreckmap-post`
subcommands and the report's sections all derive from it: adding a stage is one entry
here and one module.

Every run function has the signature `(options, inputs, out, *, context) -> Path` where
`inputs` maps input names to paths (or lists of paths), `out` is a folder that does not
exist yet (the runner renames it into place when the function returns) and `context`
carries project-wide paths (calibration) and how per-image work spreads over the
workers (`parallel`: SfM and dense get a map function, `postproc.pipeline.parallel`).
They run on whichever worker the scheduler picks, so they take only paths and options
(data moves through the shared filesystem) and are top-level functions: a task carries
its function to a Dask worker by reference.

The registry imports no stage module: each entry names its options class through a
small function that imports it when the options are needed, so that `--help` and the
scheduler stay light. `import` runs `wreckmap-field gopro import` as a subprocess: the
post-processing side never imports the field package.
"""

from __future__ import annotations

import functools
import importlib
import logging
import shutil
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from postproc.commands import calibrate as calibrate_command
from postproc.commands import dense as dense_command
from postproc.commands import depth as depth_command
from postproc.commands import merge as merge_command
from postproc.commands import sfm as sfm_command
from postproc.commands import slam as slam_command
from shared.errors import StageError
from shared.folders import (
    CalibrationFolder,
    DenseFolder,
    DepthFolder,
    HandoffFolder,
    MergeFolder,
    SessionFolder,
    SfmFolder,
    SlamFolder,
)

if TYPE_CHECKING:
    from postproc.pipeline.project import Project, SessionSpec
    from shared.progress import MapFn

log = logging.getLogger(__name__)

RunFn = Callable[..., Path]
_F = TypeVar("_F", bound=HandoffFolder)


@dataclass(frozen=True, kw_only=True)
class Read:
    """A folder kind a stage reads, under the input name `name`.

    The folder comes from the planned task that writes that kind (the same session's
    for a session stage; every session's, as a list, for a project stage reading a
    session kind); without one, from the project file (`Stage.sources`), else nothing.
    optional: the stage runs without it. soft: only waited for and digested, never
    passed (the stage finds it itself, like depth/ inside a SLAM folder); its failure
    does not block the stage.
    """

    kind: type[HandoffFolder]
    name: str
    optional: bool = False
    soft: bool = False


@dataclass(frozen=True, kw_only=True)
class Sources:
    """What the project file gives one task: inputs by name, the files hashed by
    content, and options set for this task only (part of the digest)."""

    inputs: dict[str, Any] = field(default_factory=dict)
    raw: tuple[Path, ...] = ()
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class NotPlanned:
    """Why a stage is left out of the plan (for a session or the project); quiet: say
    nothing (the stage does not apply, like the import of a session that is no GoPro)."""

    reason: str = ""
    quiet: bool = False


@dataclass(frozen=True, kw_only=True)
class Stage:
    """One stage of the pipeline (see the module docstring).

    options_type: returns the options dataclass (imports the stage module).
    per_session: one task per session (else one for the project).
    place: where the stage's folder goes, from the run's output folder and the session.
    sources: what the project file gives the task, or why it is not planned.
    command: the `wreckmap-post` subcommand module of the stage (None: no subcommand).
    """

    name: str
    options_type: Callable[[], type]
    run: RunFn
    writes: type[HandoffFolder]
    reads: tuple[Read, ...] = ()
    per_session: bool = False
    place: Callable[[Path, str | None], Path]
    sources: Callable[[Project, SessionSpec | None], Sources | NotPlanned]
    command: ModuleType | None = None


# ------------------------------------------------------------------------------ options


@dataclass(kw_only=True)
class ImportOptions:
    """Options of the GoPro import (`wreckmap-field gopro import`).

    medium: "water" (flat-port housing) or "air", for the intrinsics guess when the
        project gives no calibration.
    require_imu: fail when a chapter has no GPMF IMU data.
    compression: MCAP chunk compression ("none", "zstd", "lz4").
    """

    medium: Literal["water", "air"] = "water"
    require_imu: bool = True
    compression: Literal["none", "zstd", "lz4"] = "none"


def options_class(module: str, name: str) -> Callable[[], type]:
    """A stage's `options_type`: imports `module` only when asked (the light options
    modules of slam, dense and calibrate; the stage module of the others)."""
    return functools.partial(_import_class, module, name)


def _import_class(module: str, name: str) -> type:
    found = getattr(importlib.import_module(module), name)
    if not isinstance(found, type):
        raise TypeError(f"{module}.{name} is not a class")
    return found


def _import_options() -> type:
    return ImportOptions


# ------------------------------------------------------------------------------ run functions


def _camchain(inputs: dict[str, Any], context: dict[str, Any]) -> Path | None:
    """The calibrate stage's camchain when the project calibrates, else the project's."""
    if inputs.get("calibration") is not None:
        return CalibrationFolder(inputs["calibration"]).camchain
    camchain = context.get("camchain")
    return Path(camchain) if camchain is not None else None


def run_calibrate(
    options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]
) -> Path:
    """A calibration recording and its AprilGrid -> a calibration folder `out` (Kalibr).

    options: `postproc.calibrate.stage.CalibrateOptions`."""
    from postproc.calibrate.stage import run_camera, run_imu

    folder = CalibrationFolder(out)
    camchain = run_camera(options.camera, inputs["recording"], inputs["target"], folder.camera)
    if options.estimate_imu:
        camchain = run_imu(options.imu, inputs["recording"], camchain, inputs["target"], folder.imu)
    shutil.copyfile(camchain, folder.camchain)
    return out


def run_import(
    options: ImportOptions, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]
) -> Path:
    """GoPro chapters (`inputs["videos"]`) -> a field session folder `out`."""
    command = [
        sys.executable,
        "-m",
        "field.cli",
        "gopro",
        "import",
        *[str(p) for p in inputs["videos"]],
        "--out",
        str(out),
        "--medium",
        options.medium,
        "--compression",
        options.compression,
    ]
    if options.require_imu:
        command.append("--require-imu")
    camchain = _camchain(inputs, context)
    if camchain is not None:
        command += ["--camchain", str(camchain)]
    if context.get("imu_yaml") is not None:
        command += ["--imu-yaml", str(context["imu_yaml"])]
    log.info("running %s", " ".join(command))
    completed = subprocess.run(command, capture_output=True, text=True, check=False)
    for line in (completed.stdout + completed.stderr).splitlines():
        log.info("gopro import: %s", line)
    if completed.returncode != 0:
        tail = (completed.stderr or completed.stdout).strip().splitlines()[-1:] or ["no output"]
        raise StageError(
            f"gopro import of {', '.join(Path(p).name for p in inputs['videos'])} failed "
            f"(exit {completed.returncode}): {tail[0]}"
        )
    if not out.is_dir():
        raise StageError(f"gopro import wrote no session folder at {out}")
    return out


def run_slam(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """A recording (EuRoC or session folder) -> a SLAM result folder `out`."""
    from postproc.slam.stage import run

    return run(
        options,
        inputs["recording"],
        out,
        camchain=_camchain(inputs, context),
        imu_yaml=context.get("imu_yaml"),
        overwrite=True,
    )


def run_depth(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """A SLAM trajectory and a dive log -> the depth folder `out` (sync.json...)."""
    from postproc.depth.stage import run

    trajectory = SlamFolder(inputs["slam"]).trajectory
    run(options, trajectory, inputs["dive"], out, overwrite=True)
    return out


def run_merge(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """SLAM folders (each with its depth/ inside) and targets -> the merge folder `out`."""
    from postproc.merge.stage import run

    run(options, list(inputs["slam"]), list(inputs["targets"]), out, overwrite=True)
    return out


def run_sfm(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """SLAM folders and the merge folder (when there is one) -> the SfM folder `out`."""
    from postproc.sfm.stage import run

    slam = [SlamFolder(p).path for p in inputs["slam"]]
    merge = MergeFolder(inputs["merge"]).path if inputs.get("merge") else None
    run(options, slam, out, merge=merge, overwrite=True, map_fn=stage_map(context))
    return out


def run_dense(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """The SfM folder -> the dense folder `out` (fused.ply, mesh.ply, dense.json)."""
    from postproc.dense.stage import run

    run(options, Path(inputs["sfm"]), out, overwrite=True, map_fn=stage_map(context))
    return out


def stage_map(context: dict[str, Any]) -> MapFn | None:
    """The map function for a stage's per-image work on the backend it runs on; None on
    the inline backend, where the stage does that work itself as its command does.

    Why not a serial map there: SfM matches a map's items in chunks of pairs, each on its
    own copy of the database (its writes stay apart from other workers'), which in one
    process only costs the copies, and they grow with the dive (chunks x database size):
    on stop 55's 10-minute dive matching took 76.0 s in chunks against 56.2 s in the one
    database, on its 3-minute prefix 18.7 against 16.3 s (one-off script, the same pairs).
    """
    from postproc.pipeline.parallel import make_map

    spec = context.get("parallel")
    if spec is None or spec.kind == "serial":
        return None
    return make_map(spec)


# ------------------------------------------------------------------ what the project gives


def _calibration_files(project: Project) -> tuple[Path, ...]:
    """The calibration files the project gives (hashed by content): a camchain calibrated
    from a recording comes through the calibrate task's digest instead."""
    given = [project.imu_yaml]
    if project.calibration_recording is None:
        given.append(project.camchain)
    return tuple(p for p in given if p is not None)


def _calibrate_sources(project: Project, session: SessionSpec | None) -> Sources | NotPlanned:
    if project.calibration_recording is None or project.calibration_target is None:
        return NotPlanned(quiet=True)
    return Sources(
        inputs={"recording": project.calibration_recording, "target": project.calibration_target},
        raw=(project.calibration_recording, project.calibration_target),
    )


def _import_sources(project: Project, session: SessionSpec | None) -> Sources | NotPlanned:
    assert session is not None  # a session stage
    if session.source != "gopro":
        return NotPlanned(quiet=True)
    return Sources(
        inputs={"videos": list(session.paths)},
        raw=(*session.paths, *_calibration_files(project)),
    )


def _slam_sources(project: Project, session: SessionSpec | None) -> Sources | NotPlanned:
    assert session is not None
    if session.source == "gopro":  # the import task's session folder
        return Sources(raw=_calibration_files(project))
    recording = session.paths[0]
    return Sources(inputs={"recording": recording}, raw=(recording, *_calibration_files(project)))


def _depth_sources(project: Project, session: SessionSpec | None) -> Sources | NotPlanned:
    assert session is not None
    if session.dive is None:
        return NotPlanned(reason="no dive log")
    overrides = {}
    if session.dive_time_offset_s is not None:
        overrides["time_offset_s"] = session.dive_time_offset_s
    return Sources(inputs={"dive": session.dive}, raw=(session.dive,), overrides=overrides)


def _merge_sources(project: Project, session: SessionSpec | None) -> Sources | NotPlanned:
    if not project.targets:
        return NotPlanned(reason="no targets in the project")
    return Sources(inputs={"targets": list(project.targets)}, raw=tuple(project.targets))


def _no_sources(project: Project, session: SessionSpec | None) -> Sources | NotPlanned:
    return Sources()


def _in_output(name: str) -> Callable[[Path, str | None], Path]:
    def place(output: Path, session: str | None) -> Path:
        return output / name

    return place


def _imports_place(output: Path, session: str | None) -> Path:
    return output / "imports" / str(session)


def _slam_place(output: Path, session: str | None) -> Path:
    # Named after the session: merge and SfM name the sessions after their folders.
    return output / "sessions" / str(session)


def _depth_place(output: Path, session: str | None) -> Path:
    # Inside the SLAM folder, where merge and SfM look for it.
    return SlamFolder(_slam_place(output, session)).depth.path


# ------------------------------------------------------------------------------ the registry

_ENTRIES = (
    Stage(
        name="calibrate",
        options_type=options_class("postproc.calibrate.options", "CalibrateOptions"),
        run=run_calibrate,
        writes=CalibrationFolder,
        place=_in_output("calibration"),
        sources=_calibrate_sources,
        command=calibrate_command,
    ),
    Stage(
        name="import",
        options_type=_import_options,
        run=run_import,
        writes=SessionFolder,
        reads=(Read(kind=CalibrationFolder, name="calibration", optional=True),),
        per_session=True,
        place=_imports_place,
        sources=_import_sources,
    ),
    Stage(
        name="slam",
        options_type=options_class("postproc.slam.options", "SlamOptions"),
        run=run_slam,
        writes=SlamFolder,
        reads=(
            Read(kind=SessionFolder, name="recording"),
            Read(kind=CalibrationFolder, name="calibration", optional=True),
        ),
        per_session=True,
        place=_slam_place,
        sources=_slam_sources,
        command=slam_command,
    ),
    Stage(
        name="depth",
        options_type=options_class("postproc.depth.options", "DepthOptions"),
        run=run_depth,
        writes=DepthFolder,
        reads=(Read(kind=SlamFolder, name="slam"),),
        per_session=True,
        place=_depth_place,
        sources=_depth_sources,
        command=depth_command,
    ),
    Stage(
        name="merge",
        options_type=options_class("postproc.merge.options", "MergeOptions"),
        run=run_merge,
        writes=MergeFolder,
        reads=(
            Read(kind=SlamFolder, name="slam"),
            Read(kind=DepthFolder, name="depth", soft=True),
        ),
        place=_in_output("merge"),
        sources=_merge_sources,
        command=merge_command,
    ),
    Stage(
        name="sfm",
        options_type=options_class("postproc.sfm.options", "SfmOptions"),
        run=run_sfm,
        writes=SfmFolder,
        reads=(
            Read(kind=SlamFolder, name="slam"),
            Read(kind=MergeFolder, name="merge", optional=True),
            Read(kind=DepthFolder, name="depth", soft=True),
        ),
        place=_in_output("sfm"),
        sources=_no_sources,
        command=sfm_command,
    ),
    Stage(
        name="dense",
        options_type=options_class("postproc.dense.options", "DenseOptions"),
        run=run_dense,
        writes=DenseFolder,
        reads=(Read(kind=SfmFolder, name="sfm"),),
        place=_in_output("dense"),
        sources=_no_sources,
        command=dense_command,
    ),
)

# Stage name -> entry, in the order data flows (the plan's order).
STAGES: Mapping[str, Stage] = {entry.name: entry for entry in _ENTRIES}


def check_output(stage: str, writes: type[HandoffFolder], out: Path) -> None:
    """Refuse an output folder of `stage` missing the marker of the kind it writes."""
    folder = writes(out)
    if not folder.is_complete():
        raise StageError(f"{stage}: finished without writing {folder.marker} in {out}")


class RunFolders:
    """The hand-off folders of a run's output folder, where the registry places them (the
    report, the evaluation, the viewer and the coverage read a run through this)."""

    def __init__(self, output: Path, stages: Mapping[str, Stage] | None = None) -> None:
        self.output = Path(output)
        self.stages = STAGES if stages is None else stages

    def folder(self, stage: str, session: str | None = None) -> HandoffFolder:
        """The folder `stage` writes (for `session`, for a session stage)."""
        entry = self.stages[stage]
        return entry.writes(entry.place(self.output, session))

    def _typed(self, kind: type[_F], stage: str, session: str | None = None) -> _F:
        folder = self.folder(stage, session)
        if not isinstance(folder, kind):
            raise TypeError(f"stage {stage} writes {type(folder).__name__}, not {kind.__name__}")
        return folder

    def calibration(self) -> CalibrationFolder:
        return self._typed(CalibrationFolder, "calibrate")

    def imported(self, session: str) -> SessionFolder:
        return self._typed(SessionFolder, "import", session)

    def slam(self, session: str) -> SlamFolder:
        return self._typed(SlamFolder, "slam", session)

    def depth(self, session: str) -> DepthFolder:
        return self._typed(DepthFolder, "depth", session)

    def merge(self) -> MergeFolder:
        return self._typed(MergeFolder, "merge")

    def sfm(self) -> SfmFolder:
        return self._typed(SfmFolder, "sfm")

    def dense(self) -> DenseFolder:
        return self._typed(DenseFolder, "dense")
