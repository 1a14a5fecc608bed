"""The folders stages hand to each other, one class per kind (conventions.md, "Folders").

Each class owns the file names of its kind and its completeness marker: the file a
writer puts there last, so that a folder holding it is complete. Nothing else spells
these names; a reader asks the folder (`SlamFolder(path).trajectory`), a writer too
(`SlamFolder(tmp).stats`). The classes are light (paths only, no heavy import) so that
the field side, the pipeline's scheduler and the command lines can all use them.

- `SessionFolder`: a field recording (`wreckmap-field record` or `gopro import`).
- `CalibrationFolder`: the pipeline's calibrate stage (a Kalibr camchain).
- `SlamFolder`: `wreckmap-post slam`; its depth stage lives inside it (`depth/`).
- `DepthFolder`, `MergeFolder`, `SfmFolder`, `DenseFolder`: the later stages.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar

from shared.errors import InputError


class HandoffFolder:
    """A folder of one kind at `path` (which may not exist yet)."""

    kind: ClassVar[str] = "folder"
    # The file written last: the folder is complete when it exists.
    marker: ClassVar[str] = ""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, HandoffFolder)
            and type(other) is type(self)
            and other.path == self.path
        )

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.path))

    @property
    def name(self) -> str:
        """The folder's own name (sessions are named after their SLAM folders)."""
        return self.path.name

    @property
    def marker_path(self) -> Path:
        return self.path / self.marker

    def is_complete(self) -> bool:
        """Whether the writer finished (the marker file exists)."""
        return self.marker_path.is_file()

    def require(self) -> None:
        """Raise InputError naming the folder unless it is complete."""
        if not self.path.is_dir():
            raise InputError(f"{self.path}: not a folder (expected a {self.kind} folder)")
        if not self.is_complete():
            raise InputError(
                f"{self.path}: {self.marker} missing (expected a complete {self.kind} folder)"
            )

    def read_json(self, path: Path) -> dict[str, Any]:
        """One of this folder's JSON files as a mapping; InputError naming it otherwise."""
        try:
            document = json.loads(path.read_text(encoding="utf-8"))
        except OSError as error:
            raise InputError(f"{path}: cannot read ({error.strerror})") from None
        except ValueError as error:
            raise InputError(f"{path}: not valid JSON ({error})") from None
        if not isinstance(document, dict):
            raise InputError(f"{path}: expected a JSON object")
        return document


class SessionFolder(HandoffFolder):
    """A field session: session.yaml, recording.mcap (or recording_NNN.mcap), calib/."""

    kind = "session"
    marker = "session.yaml"

    @property
    def session_yaml(self) -> Path:
        return self.path / "session.yaml"

    @property
    def recording(self) -> Path:
        return self.path / "recording.mcap"

    @property
    def calib(self) -> Path:
        return self.path / "calib"

    @property
    def camchain(self) -> Path:
        return self.calib / "camchain.yaml"

    @property
    def imu_yaml(self) -> Path:
        return self.calib / "imu.yaml"


class CalibrationFolder(HandoffFolder):
    """The calibrate stage: camchain.yaml (Kalibr), camera/ and imu/ with their reports."""

    kind = "calibration"
    marker = "camchain.yaml"

    @property
    def camchain(self) -> Path:
        return self.path / "camchain.yaml"

    @property
    def camera(self) -> Path:
        """The intrinsics step's own folder."""
        return self.path / "camera"

    @property
    def imu(self) -> Path:
        """The camera-IMU step's own folder."""
        return self.path / "imu"


class DepthFolder(HandoffFolder):
    """The depth stage: sync.json, trajectory_world.tum, trajectory_world_fused.tum,
    depth_sync.png."""

    kind = "depth"
    marker = "sync.json"

    @property
    def sync(self) -> Path:
        return self.path / "sync.json"

    @property
    def trajectory_world(self) -> Path:
        return self.path / "trajectory_world.tum"

    @property
    def trajectory_world_fused(self) -> Path:
        return self.path / "trajectory_world_fused.tum"

    @property
    def plot(self) -> Path:
        return self.path / "depth_sync.png"


class SlamFolder(HandoffFolder):
    """A SLAM result: trajectory.tum (body poses), keyframes.tum (camera poses of the
    keyframes), keyframes/<timestamp_ns>.png, calib/camchain.yaml, map.ply, stats.json;
    the depth stage's folder `depth/` inside."""

    kind = "SLAM result"
    marker = "stats.json"

    @property
    def trajectory(self) -> Path:
        return self.path / "trajectory.tum"

    @property
    def keyframes_tum(self) -> Path:
        return self.path / "keyframes.tum"

    @property
    def keyframes(self) -> Path:
        """The keyframe images, `<timestamp_ns>.png`."""
        return self.path / "keyframes"

    def keyframe_image(self, timestamp_ns: int) -> Path:
        return self.keyframes / f"{timestamp_ns}.png"

    @property
    def calib(self) -> Path:
        return self.path / "calib"

    @property
    def camchain(self) -> Path:
        return self.calib / "camchain.yaml"

    @property
    def map_ply(self) -> Path:
        return self.path / "map.ply"

    @property
    def stats(self) -> Path:
        return self.path / "stats.json"

    @property
    def depth(self) -> DepthFolder:
        return DepthFolder(self.path / "depth")

    def read_stats(self) -> dict[str, Any]:
        return self.read_json(self.stats)


class MergeFolder(HandoffFolder):
    """The merge stage: transforms.json (T_W_S per session), targets.json,
    <session>/keyframes_merged.tum, merge_top.png, merge_side.png."""

    kind = "merge"
    marker = "transforms.json"

    @property
    def transforms(self) -> Path:
        return self.path / "transforms.json"

    @property
    def targets(self) -> Path:
        return self.path / "targets.json"

    def merged_keyframes(self, session: str) -> Path:
        return self.path / session / "keyframes_merged.tum"

    @property
    def top_plot(self) -> Path:
        return self.path / "merge_top.png"

    @property
    def side_plot(self) -> Path:
        return self.path / "merge_side.png"

    def read_transforms(self) -> dict[str, Any]:
        return self.read_json(self.transforms)


class SfmFolder(HandoffFolder):
    """The SfM stage: sparse/0 (COLMAP binary model), images/, database.db, pairs.txt,
    sessions/<name>/keyframes.tum, transforms.json, stats.json."""

    kind = "SfM"
    marker = "stats.json"

    @property
    def stats(self) -> Path:
        return self.path / "stats.json"

    @property
    def model(self) -> Path:
        return self.path / "sparse" / "0"

    @property
    def images(self) -> Path:
        return self.path / "images"

    @property
    def database(self) -> Path:
        return self.path / "database.db"

    @property
    def pairs(self) -> Path:
        return self.path / "pairs.txt"

    @property
    def transforms(self) -> Path:
        return self.path / "transforms.json"

    def session(self, name: str) -> Path:
        """The folder of one session's refined keyframes."""
        return self.path / "sessions" / name

    def read_stats(self) -> dict[str, Any]:
        return self.read_json(self.stats)


class DenseFolder(HandoffFolder):
    """The dense stage: workspace/ (COLMAP dense workspace), fused.ply, mesh.ply,
    fused_corrected.ply (with colour correction), dense.json."""

    kind = "dense"
    marker = "dense.json"

    @property
    def report(self) -> Path:
        return self.path / "dense.json"

    @property
    def workspace(self) -> Path:
        return self.path / "workspace"

    @property
    def fused(self) -> Path:
        return self.path / "fused.ply"

    @property
    def mesh(self) -> Path:
        return self.path / "mesh.ply"

    @property
    def fused_corrected(self) -> Path:
        return self.path / "fused_corrected.ply"

    def read_report(self) -> dict[str, Any]:
        return self.read_json(self.report)


FOLDER_KINDS: tuple[type[HandoffFolder], ...] = (
    SessionFolder,
    CalibrationFolder,
    SlamFolder,
    DepthFolder,
    MergeFolder,
    SfmFolder,
    DenseFolder,
)
