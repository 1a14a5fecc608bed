"""The project file of `wreckmap-post run`: what to process and how (YAML).

Every key is documented, with its unit, in `deploy/project.example.yaml`. In short::

    name: wreck-survey          # report title
    output: results             # output folder (relative paths: to this file's folder)
    calibration: {camchain: calib/camchain.yaml, imu: calib/imu.yaml}   # optional
    # or calibration: {recording: calib_dive/, target: grid.yaml}: calibrated first
    targets: [targets/grid_a.yaml, targets/grid_b.yaml]                  # merge targets
    truth: sim/truth.json       # optional: simulator truth, for the errors in the report
    sessions:
      - name: dive1
        euroc: sim/session_01/euroc        # exactly one of euroc / session / gopro
        dive: dives/dive1                  # dive folder or CSV (optional: no depth stage)
    stages:
      slam: {max_frames: 2000}             # keys of each stage's options dataclass
      dense: {max_image_size_px: 640}

Loading checks the structure and types and builds each stage's options dataclass (nested
dataclasses from nested mappings; the stages and their options types come from the
registry, `postproc.pipeline.stages.STAGES`); any error names the file and the key
(`project.yaml: stages.slam.frontend.max_corners: unknown key (expected one of ...)`).
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from postproc.pipeline.stages import STAGES, Stage
from shared.errors import InputError

SESSION_SOURCES: tuple[Literal["euroc", "session", "gopro"], ...] = ("euroc", "session", "gopro")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(kw_only=True)
class SessionSpec:
    """One dive's recording.

    name: unique, letters, digits, `_.-` (folder names under `output/sessions/`).
    source: "euroc" (EuRoC ASL folder), "session" (field session folder) or "gopro"
        (the MP4 chapters of one recording, imported first with `wreckmap-field gopro import`).
    paths: the folder (euroc, session) or the chapter files in order (gopro).
    dive: dive folder (`dives.json` + CSVs) or one dive CSV; None: no depth stage.
    truth_session: index of this session in the simulator's truth.json (default: order).
    dive_time_offset_s: the dive computer's clock minus the camera's, s, when known (the
        depth stage then skips its search; for a dive too short to sync, which the depth
        stage refuses).
    """

    name: str
    source: Literal["euroc", "session", "gopro"]
    paths: list[Path]
    dive: Path | None = None
    truth_session: int | None = None
    dive_time_offset_s: float | None = None


@dataclass(kw_only=True)
class ClusterSpec:
    """Dask-jobqueue SLURM settings (`--scheduler slurm`); see deploy/project.example.yaml."""

    queue: str | None = None
    account: str | None = None
    cores: int = 4
    memory: str = "16GB"
    walltime: str = "04:00:00"
    jobs: int = 2
    job_extra_directives: list[str] = field(default_factory=list)


@dataclass(kw_only=True)
class Project:
    """A loaded project: absolute paths, options as the stages' dataclasses."""

    path: Path
    name: str
    output: Path
    sessions: list[SessionSpec]
    targets: list[Path] = field(default_factory=list)
    camchain: Path | None = None
    imu_yaml: Path | None = None
    calibration_recording: Path | None = None
    calibration_target: Path | None = None
    truth: Path | None = None
    stage_options: dict[str, Any] = field(default_factory=dict)
    cluster: ClusterSpec = field(default_factory=ClusterSpec)

    def options_for(self, stage: str, entry: Stage | None = None) -> Any:
        """The options dataclass of `stage` (its defaults when the project gives none);
        entry: the stage's registry entry, when not one of `STAGES`."""
        if stage not in self.stage_options:
            self.stage_options[stage] = build_stage_options(self.path, stage, {}, entry=entry)
        return self.stage_options[stage]


def load_project(path: Path | str) -> Project:
    """Read and check a project file; raises InputError naming the file and the key."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise InputError(f"{path}: cannot read the project file ({error.strerror})") from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(document, dict):
        raise InputError(f"{path}: expected a mapping with 'sessions' at the top level")
    return parse_project(document, path)


def parse_project(document: dict[str, Any], path: Path) -> Project:
    """Build a Project from the parsed YAML `document` of the file `path`."""
    base = path.resolve().parent
    known = {"name", "output", "calibration", "targets", "truth", "sessions", "stages", "cluster"}
    _no_unknown(path, "", document, known)

    def where(key: str) -> str:
        return f"{path}: {key}"

    def rel(value: Any, key: str) -> Path:
        if not isinstance(value, str) or not value:
            raise InputError(f"{where(key)}: expected a path (string), got {value!r}")
        p = Path(value).expanduser()
        return p if p.is_absolute() else base / p

    def existing(value: Any, key: str, *, kind: str) -> Path:
        p = rel(value, key)
        ok = p.is_dir() if kind == "folder" else p.is_file() if kind == "file" else p.exists()
        if not ok:
            raise InputError(f"{where(key)}: {p} does not exist (expected a {kind})")
        return p

    name = document.get("name", path.stem)
    if not isinstance(name, str) or not name:
        raise InputError(f"{where('name')}: expected a non-empty string")
    output = rel(document.get("output", "output"), "output")

    camchain = imu_yaml = calibration_recording = calibration_target = None
    calibration = document.get("calibration")
    if calibration is not None:
        if not isinstance(calibration, dict):
            raise InputError(f"{where('calibration')}: expected a mapping (camchain, imu)")
        _no_unknown(path, "calibration", calibration, {"camchain", "imu", "recording", "target"})
        if "camchain" in calibration:
            camchain = existing(calibration["camchain"], "calibration.camchain", kind="file")
        if "imu" in calibration:
            imu_yaml = existing(calibration["imu"], "calibration.imu", kind="file")
        if "recording" in calibration:
            calibration_recording = existing(
                calibration["recording"], "calibration.recording", kind="path"
            )
            if "target" not in calibration:
                raise InputError(
                    f"{where('calibration.target')}: missing (the AprilGrid YAML seen in "
                    "calibration.recording)"
                )
            if "camchain" in calibration:
                raise InputError(
                    f"{where('calibration')}: give camchain (known calibration) or recording "
                    "(calibrate it), not both"
                )
        if "target" in calibration:
            calibration_target = existing(calibration["target"], "calibration.target", kind="file")

    targets_raw = document.get("targets", [])
    if not isinstance(targets_raw, list):
        raise InputError(f"{where('targets')}: expected a list of AprilGrid YAML files")
    targets = [existing(t, f"targets[{k}]", kind="file") for k, t in enumerate(targets_raw)]

    truth = None
    if document.get("truth") is not None:
        truth = existing(document["truth"], "truth", kind="file")

    sessions_raw = document.get("sessions")
    if not isinstance(sessions_raw, list) or not sessions_raw:
        raise InputError(f"{where('sessions')}: expected a non-empty list of sessions")
    sessions: list[SessionSpec] = []
    for k, entry in enumerate(sessions_raw):
        key = f"sessions[{k}]"
        if not isinstance(entry, dict):
            raise InputError(f"{where(key)}: expected a mapping (name, euroc|session|gopro, dive)")
        _no_unknown(
            path,
            key,
            entry,
            {"name", *SESSION_SOURCES, "dive", "truth_session", "dive_time_offset_s"},
        )
        sname = entry.get("name")
        if not isinstance(sname, str) or not _NAME.match(sname):
            raise InputError(
                f"{where(key + '.name')}: expected a name of letters, digits and _.- "
                f"(a folder name), got {sname!r}"
            )
        if any(s.name == sname for s in sessions):
            raise InputError(f"{where(key + '.name')}: session name {sname!r} is used twice")
        given = [s for s in SESSION_SOURCES if s in entry]
        if len(given) != 1:
            raise InputError(
                f"{where(key)}: give exactly one of {', '.join(SESSION_SOURCES)} "
                f"(found: {', '.join(given) or 'none'})"
            )
        source = given[0]
        if source == "gopro":
            files = entry["gopro"]
            files = [files] if isinstance(files, str) else files
            if not isinstance(files, list) or not files:
                raise InputError(f"{where(key + '.gopro')}: expected a list of MP4 chapters")
            paths = [existing(f, f"{key}.gopro[{j}]", kind="file") for j, f in enumerate(files)]
        else:
            paths = [existing(entry[source], f"{key}.{source}", kind="folder")]
        dive = None
        if entry.get("dive") is not None:
            dive = existing(entry["dive"], f"{key}.dive", kind="path")
        truth_session = entry.get("truth_session")
        if truth_session is not None and (
            not isinstance(truth_session, int) or isinstance(truth_session, bool)
        ):
            raise InputError(f"{where(key + '.truth_session')}: expected an integer index")
        time_offset = entry.get("dive_time_offset_s")
        if time_offset is not None:
            if (
                isinstance(time_offset, bool)
                or not isinstance(time_offset, (int, float))
                or not math.isfinite(time_offset)
            ):
                raise InputError(
                    f"{where(key + '.dive_time_offset_s')}: expected a number of seconds, "
                    f"got {time_offset!r}"
                )
            if dive is None:
                raise InputError(
                    f"{where(key + '.dive_time_offset_s')}: given without a dive log (dive:)"
                )
            time_offset = float(time_offset)
        sessions.append(
            SessionSpec(
                name=sname,
                source=source,
                paths=paths,
                dive=dive,
                truth_session=truth_session,
                dive_time_offset_s=time_offset,
            )
        )

    stages_raw = document.get("stages") or {}
    if not isinstance(stages_raw, dict):
        raise InputError(f"{where('stages')}: expected a mapping of stage name to options")
    _no_unknown(path, "stages", stages_raw, set(STAGES))
    built: dict[str, Any] = {}
    for stage in STAGES:
        options = stages_raw.get(stage) or {}
        if not isinstance(options, dict):
            raise InputError(f"{where('stages.' + stage)}: expected a mapping of options")
        built[stage] = build_stage_options(path, stage, options)

    cluster_raw = document.get("cluster") or {}
    if not isinstance(cluster_raw, dict):
        raise InputError(f"{where('cluster')}: expected a mapping (SLURM settings)")
    cluster = dataclass_from_mapping(ClusterSpec, cluster_raw, path=path, key="cluster")

    return Project(
        path=path.resolve(),
        name=name,
        output=output,
        sessions=sessions,
        targets=targets,
        camchain=camchain,
        imu_yaml=imu_yaml,
        calibration_recording=calibration_recording,
        calibration_target=calibration_target,
        truth=truth,
        stage_options=built,
        cluster=cluster,
    )


def build_stage_options(
    path: Path, stage: str, options: dict[str, Any], *, entry: Stage | None = None
) -> Any:
    """The options dataclass of `stage` from the mapping `options` (key errors name `path`)."""
    cls = (entry or STAGES[stage]).options_type()
    return dataclass_from_mapping(cls, options, path=path, key=f"stages.{stage}")


def _no_unknown(path: Path, key: str, mapping: dict[str, Any], known: set[str]) -> None:
    for name in mapping:
        if name not in known:
            where = f"{key}.{name}" if key else str(name)
            raise InputError(
                f"{path}: {where}: unknown key (expected one of: {', '.join(sorted(known))})"
            )


def dataclass_from_mapping(cls: type, mapping: dict[str, Any], *, path: Path, key: str) -> Any:
    """Instantiate dataclass `cls` from `mapping`, recursively; errors name `path` and `key`."""
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    _no_unknown(path, key, mapping, set(fields))
    hints = typing.get_type_hints(cls)
    values = {
        name: _convert(hints[name], value, path=path, key=f"{key}.{name}")
        for name, value in mapping.items()
    }
    try:
        return cls(**values)
    except (TypeError, ValueError) as error:
        raise InputError(f"{path}: {key}: {error}") from None


def _convert(hint: Any, value: Any, *, path: Path, key: str) -> Any:
    """`value` as type `hint` (dataclass, Optional/Union, Literal, list, tuple, scalars)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)

    def fail(expected: str) -> InputError:
        return InputError(f"{path}: {key}: expected {expected}, got {value!r}")

    if hint is Any:
        return value
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        if not isinstance(value, dict):
            raise fail(f"a mapping of {hint.__name__} options")
        return dataclass_from_mapping(hint, value, path=path, key=key)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, path=path, key=key)
            except InputError as error:
                errors.append(str(error))
        raise fail(" or ".join(_describe(a) for a in args))
    if origin is Literal:
        if value not in args:
            raise fail("one of " + ", ".join(repr(a) for a in args))
        return value
    if origin in (list, tuple) or hint in (list, tuple):
        if not isinstance(value, list | tuple):
            raise fail("a list")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise fail(f"a list of {len(args)} values")
            return tuple(
                _convert(a, v, path=path, key=f"{key}[{k}]")
                for k, (a, v) in enumerate(zip(args, value, strict=True))
            )
        item = args[0] if args else Any
        items = [_convert(item, v, path=path, key=f"{key}[{k}]") for k, v in enumerate(value)]
        return tuple(items) if origin is tuple or hint is tuple else items
    if origin is dict or hint is dict:
        if not isinstance(value, dict):
            raise fail("a mapping")
        return dict(value)
    if hint is bool:
        if not isinstance(value, bool):
            raise fail("true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail("an integer")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise fail("a number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise fail("a string")
        return value
    if hint is Path:
        if not isinstance(value, str):
            raise fail("a path (string)")
        p = Path(value).expanduser()
        return p if p.is_absolute() else path.resolve().parent / p
    if isinstance(hint, type) and isinstance(value, hint):
        return value
    raise fail(_describe(hint))


def _describe(hint: Any) -> str:
    if hint is type(None):
        return "null"
    return getattr(hint, "__name__", str(hint))
