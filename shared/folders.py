"""The folders stages hand to each other, one class per kind (conventions.md, "Folders").

Each class owns the file names of its kind and its completeness marker: the file a
writer puts there last, so that a folder holding it is complete. Nothing else spells
these names; a reader asks the folder (`SlamFolder(path).trajectory`), a writer too
(`SlamFolder(tmp).stats`). The main files have typed readers and writers
(`SlamFolder(path).read_keyframes()`, `DepthFolder(tmp).write_world(trajectory)`): a
missing or unreadable file is an InputError naming it, and every write is atomic
(a temporary name, then a rename). The classes are light (their format modules, which
import NumPy, are imported by the methods that need them) so that the field side, the
pipeline's scheduler and the command lines can all use them.

- `SessionFolder`: a field recording (`wreckmap-field record` or `gopro import`).
- `CalibrationFolder`: the pipeline's calibrate stage (a Kalibr camchain).
- `SlamFolder`: `wreckmap-post slam`; its depth stage lives inside it (`depth/`).
- `DepthFolder`, `MergeFolder`, `SfmFolder`, `DenseFolder`: the later stages.

The resume rule, the same for every stage (`rebuild`): a complete result made from the
same inputs with the same options (its stamp, `.wreckmap-result.json`, says so) is kept;
anything else in the way is refused unless overwrite. With overwrite (or nothing there)
the result is built under a temporary name beside its place and swapped in whole when
complete. The temporary name follows from the
stamp, so an interrupted build of a stage that can resume its own work (per-image depth
maps, SfM features) resumes there on the next run with the same inputs and options.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

from shared.errors import InputError, OutputExistsError, StageError
from shared.fsutil import atomic_path, write_text_atomic

if TYPE_CHECKING:
    from shared.calibration.kalibr import CameraCalibration, ImuNoise
    from shared.trajectory import Trajectory

log = logging.getLogger(__name__)

RESULT_STAMP = ".wreckmap-result.json"


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

    def relative(self, path: Path) -> str:
        """`path` (one of this folder's) as the name relative to the folder, with `/`."""
        return path.relative_to(self.path).as_posix()

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

    def _expect_file(self, path: Path, what: str) -> None:
        if not path.is_file():
            raise InputError(f"{path}: missing (expected the {self.kind} folder's {what})")

    def _write_json(
        self, path: Path, document: Any, *, overwrite: bool = False, default: Any = None
    ) -> Path:
        """A JSON file as every stage writes it: indented by 2, a newline at the end."""
        text = json.dumps(document, indent=2, default=default) + "\n"
        return write_text_atomic(path, text, overwrite=overwrite)

    def _read_tum(self, path: Path, what: str) -> Trajectory:
        from shared.formats.tum import read_tum

        self._expect_file(path, what)
        try:
            return read_tum(path)
        except InputError as error:  # read_tum names the file only: say which folder
            raise InputError(f"{self.path}: {error}") from None

    def _write_tum(self, path: Path, trajectory: Trajectory, *, overwrite: bool) -> Path:
        from shared.formats.tum import write_tum

        return write_tum(path, trajectory, overwrite=overwrite)

    def _read_camchain(self, path: Path) -> list[CameraCalibration]:
        from shared.calibration.kalibr import read_camchain

        self._expect_file(path, "camera chain (Kalibr camchain YAML)")
        return read_camchain(path)

    def _write_camchain(
        self, path: Path, cameras: list[CameraCalibration], *, overwrite: bool
    ) -> Path:
        from shared.calibration.kalibr import write_camchain

        return write_camchain(path, cameras, overwrite=overwrite)

    def _read_imu_noise(self, path: Path) -> ImuNoise:
        from shared.calibration.kalibr import read_imu_yaml

        self._expect_file(path, "IMU noise model (Kalibr imu.yaml)")
        return read_imu_yaml(path)

    def _write_imu_noise(self, path: Path, noise: ImuNoise, *, overwrite: bool) -> Path:
        from shared.calibration.kalibr import write_imu_yaml

        return write_imu_yaml(path, noise, overwrite=overwrite)


class SessionFolder(HandoffFolder):
    """A field session: session.yaml, recording.mcap (or recording_NNN.mcap), calib/."""

    kind = "session"
    marker = "session.yaml"

    @property
    def session_yaml(self) -> Path:
        return self.path / "session.yaml"

    @property
    def recording(self) -> Path:
        """The single recording of an imported session."""
        return self.path / "recording.mcap"

    def recording_part(self, index: int) -> Path:
        """The recorder's `index`th file (it rotates them by size or time)."""
        return self.path / f"recording_{index:03d}.mcap"

    def recording_parts(self) -> list[Path]:
        """The recorder's complete files, `recording_NNN.mcap`, in order."""
        return sorted(self.path.glob("recording_*.mcap"))

    @staticmethod
    def is_recording_part(name: str) -> bool:
        """Whether `name` is one of the recorder's files (complete or `.part`)."""
        return name.startswith("recording_")

    @property
    def bag_metadata(self) -> Path:
        """rosbag2's description of the MCAP files (the name is rosbag2's)."""
        return self.path / "metadata.yaml"

    @property
    def calib(self) -> Path:
        return self.path / "calib"

    @property
    def camchain(self) -> Path:
        return self.calib / "camchain.yaml"

    @property
    def imu_yaml(self) -> Path:
        return self.calib / "imu.yaml"

    def read_camchain(self) -> list[CameraCalibration]:
        """The cameras of calib/camchain.yaml, cam0 first."""
        return self._read_camchain(self.camchain)

    def write_camchain(self, cameras: list[CameraCalibration], *, overwrite: bool = False) -> Path:
        return self._write_camchain(self.camchain, cameras, overwrite=overwrite)

    def read_imu_noise(self) -> ImuNoise:
        """calib/imu.yaml: the IMU's noise model."""
        return self._read_imu_noise(self.imu_yaml)

    def write_imu_noise(self, noise: ImuNoise, *, overwrite: bool = False) -> Path:
        return self._write_imu_noise(self.imu_yaml, noise, overwrite=overwrite)


class CalibrationFolder(HandoffFolder):
    """The calibrate stage: camchain.yaml (Kalibr); in the pipeline camera/ and imu/ hold
    the two steps' own outputs.

    The steps of `wreckmap-post calibrate` may share one folder, each with its own
    outputs: camera (camchain.yaml, camera_calibration.json, coverage.png), imu
    (camchain-imucam.yaml, camera_imu.json, camera_imu.png) and rig (camchain-rig.yaml,
    rig.json); each step's camchain is its marker (`rebuild_files`).
    """

    kind = "calibration"
    marker = "camchain.yaml"

    @property
    def camchain(self) -> Path:
        return self.path / "camchain.yaml"

    @property
    def camera_report(self) -> Path:
        return self.path / "camera_calibration.json"

    @property
    def coverage_plot(self) -> Path:
        return self.path / "coverage.png"

    @property
    def imu_camchain(self) -> Path:
        """The camera-IMU step's camchain (T_cam_imu, timeshift_cam_imu)."""
        return self.path / "camchain-imucam.yaml"

    @property
    def imu_report(self) -> Path:
        return self.path / "camera_imu.json"

    @property
    def imu_plot(self) -> Path:
        return self.path / "camera_imu.png"

    @property
    def rig_camchain(self) -> Path:
        return self.path / "camchain-rig.yaml"

    @property
    def rig_report(self) -> Path:
        return self.path / "rig.json"

    @property
    def camera(self) -> Path:
        """The intrinsics step's own folder."""
        return self.path / "camera"

    @property
    def imu(self) -> Path:
        """The camera-IMU step's own folder."""
        return self.path / "imu"

    def read_camchain(self) -> list[CameraCalibration]:
        """The camera step's cameras (intrinsics; T_cam_imu the identity)."""
        return self._read_camchain(self.camchain)

    def write_camchain(self, cameras: list[CameraCalibration], *, overwrite: bool = False) -> Path:
        return self._write_camchain(self.camchain, cameras, overwrite=overwrite)

    def read_imu_camchain(self) -> list[CameraCalibration]:
        """The camera-IMU step's cameras (with T_cam_imu and timeshift_cam_imu)."""
        return self._read_camchain(self.imu_camchain)

    def write_imu_camchain(
        self, cameras: list[CameraCalibration], *, overwrite: bool = False
    ) -> Path:
        return self._write_camchain(self.imu_camchain, cameras, overwrite=overwrite)

    def read_rig_camchain(self) -> list[CameraCalibration]:
        """The rig step's two cameras, cam1 chained from cam0."""
        return self._read_camchain(self.rig_camchain)

    def write_rig_camchain(
        self, cameras: list[CameraCalibration], *, overwrite: bool = False
    ) -> Path:
        return self._write_camchain(self.rig_camchain, cameras, overwrite=overwrite)


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

    def read_sync(self) -> dict[str, Any]:
        """sync.json: the clock offset, drift and depth relation (`postproc.depth.stage`)."""
        return self.read_json(self.sync)

    def write_sync(self, document: dict[str, Any], *, overwrite: bool = False) -> Path:
        """sync.json, the folder's marker: write it last."""
        return self._write_json(self.sync, document, overwrite=overwrite)

    def read_world(self) -> Trajectory:
        """The trajectory at true depth (T_W_B or T_W_C, as the input was)."""
        return self._read_tum(self.trajectory_world, "trajectory at true depth")

    def write_world(self, trajectory: Trajectory, *, overwrite: bool = False) -> Path:
        return self._write_tum(self.trajectory_world, trajectory, overwrite=overwrite)

    def read_world_fused(self) -> Trajectory:
        """The trajectory re-optimised with depth factors (only when the stage fused)."""
        return self._read_tum(self.trajectory_world_fused, "depth-fused trajectory")

    def write_world_fused(self, trajectory: Trajectory, *, overwrite: bool = False) -> Path:
        return self._write_tum(self.trajectory_world_fused, trajectory, overwrite=overwrite)


class SlamFolder(HandoffFolder):
    """A SLAM result: trajectory.tum (body poses), keyframes.tum (camera poses of the
    keyframes), keyframes/<timestamp_ns>.png, calib/camchain.yaml, map.ply, stats.json;
    the depth stage's folder `depth/` inside."""

    kind = "SLAM"
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
    def imu_yaml(self) -> Path:
        """The IMU noise model used (absent for a visual-only run)."""
        return self.calib / "imu.yaml"

    @property
    def map_ply(self) -> Path:
        return self.path / "map.ply"

    @property
    def stats(self) -> Path:
        return self.path / "stats.json"

    @property
    def depth(self) -> DepthFolder:
        return DepthFolder(self.path / "depth")

    @property
    def depth_beside(self) -> DepthFolder:
        """A depth folder beside this one (`<dive>/slam`, `<dive>/depth`), where the SfM
        stage also looks for one (the pipeline's is `depth`, inside)."""
        return DepthFolder(self.path.parent / "depth")

    def depth_folders(self) -> tuple[DepthFolder, DepthFolder]:
        """Where this SLAM folder's depth stage may be, in the order to try: inside it
        (the pipeline's layout) and beside it (the command line's)."""
        return self.depth, self.depth_beside

    def read_stats(self) -> dict[str, Any]:
        return self.read_json(self.stats)

    def write_stats(self, stats: dict[str, Any], *, overwrite: bool = False) -> Path:
        """stats.json, the folder's marker: write it last (values JSON cannot hold as text)."""
        return self._write_json(self.stats, stats, overwrite=overwrite, default=str)

    def read_trajectory(self) -> Trajectory:
        """Every tracked frame's body pose in the session frame (T_S_B)."""
        return self._read_tum(self.trajectory, "trajectory (body poses)")

    def write_trajectory(self, trajectory: Trajectory, *, overwrite: bool = False) -> Path:
        return self._write_tum(self.trajectory, trajectory, overwrite=overwrite)

    def read_keyframes(self) -> Trajectory:
        """The keyframes' camera poses in the session frame (T_S_C)."""
        return self._read_tum(self.keyframes_tum, "keyframe poses")

    def write_keyframes(self, trajectory: Trajectory, *, overwrite: bool = False) -> Path:
        return self._write_tum(self.keyframes_tum, trajectory, overwrite=overwrite)

    def read_camchain(self) -> list[CameraCalibration]:
        """The cameras the keyframes were taken with (calib/camchain.yaml), cam0 first."""
        return self._read_camchain(self.camchain)

    def write_camchain(self, cameras: list[CameraCalibration], *, overwrite: bool = False) -> Path:
        return self._write_camchain(self.camchain, cameras, overwrite=overwrite)

    def read_imu_noise(self) -> ImuNoise:
        """The IMU noise model used (calib/imu.yaml; none for a visual-only run)."""
        return self._read_imu_noise(self.imu_yaml)

    def write_imu_noise(self, noise: ImuNoise, *, overwrite: bool = False) -> Path:
        return self._write_imu_noise(self.imu_yaml, noise, overwrite=overwrite)


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

    def write_transforms(self, transforms: dict[str, Any], *, overwrite: bool = False) -> Path:
        """transforms.json, the folder's marker: write it last."""
        return self._write_json(self.transforms, transforms, overwrite=overwrite)

    def read_targets(self) -> dict[str, Any]:
        return self.read_json(self.targets)

    def write_targets(self, targets: dict[str, Any], *, overwrite: bool = False) -> Path:
        """targets.json: each target's world pose and the sightings behind it."""
        return self._write_json(self.targets, targets, overwrite=overwrite)

    def read_place_pairs(self) -> list[tuple[str, int, str, int]]:
        """The keyframe pairs natural-feature merging verified across sessions:
        (session a, stamp a ns, session b, stamp b ns), from the mergeable pairs'
        "consistent_stamps_ns" ([stamp in b, stamp in a]) in transforms.json; empty
        when the merge matched no natural features."""
        links: list[tuple[str, int, str, int]] = []
        for pair in self.read_transforms().get("pairs", []):
            if not (isinstance(pair, dict) and pair.get("mergeable")):
                continue
            a, b = pair["sessions"]
            for stamp_b, stamp_a in pair.get("consistent_stamps_ns", []):
                links.append((str(a), int(stamp_a), str(b), int(stamp_b)))
        return links

    def read_merged_keyframes(self, session: str) -> Trajectory:
        """One session's keyframe camera poses in the world frame (T_W_C)."""
        return self._read_tum(self.merged_keyframes(session), f"merged keyframes of {session}")

    def write_merged_keyframes(
        self, session: str, trajectory: Trajectory, *, overwrite: bool = False
    ) -> Path:
        return self._write_tum(self.merged_keyframes(session), trajectory, overwrite=overwrite)


class SfmFolder(HandoffFolder):
    """The SfM stage: sparse/0 (COLMAP binary model), images/, database.db, pairs.txt,
    sessions/<name>/keyframes.tum and keyframes_world.tum, keyframes.tum (one session),
    transforms.json, stats.json."""

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

    @property
    def keyframes_tum(self) -> Path:
        """The refined keyframe poses of a single-session run, in the input's frame."""
        return self.path / "keyframes.tum"

    def session(self, name: str) -> Path:
        """The folder of one session's refined keyframes."""
        return self.path / "sessions" / name

    def session_keyframes(self, name: str) -> Path:
        """One session's refined keyframe poses in the input's frame (T_S_C or T_W_C)."""
        return self.session(name) / "keyframes.tum"

    def session_keyframes_world(self, name: str) -> Path:
        """One session's refined keyframe poses in the world frame (T_W_C)."""
        return self.session(name) / "keyframes_world.tum"

    def read_stats(self) -> dict[str, Any]:
        return self.read_json(self.stats)

    def write_stats(self, stats: dict[str, Any], *, overwrite: bool = False) -> Path:
        """stats.json, the folder's marker: write it last."""
        return self._write_json(self.stats, stats, overwrite=overwrite)

    def read_transforms(self) -> dict[str, Any]:
        return self.read_json(self.transforms)

    def write_transforms(self, transforms: dict[str, Any], *, overwrite: bool = False) -> Path:
        return self._write_json(self.transforms, transforms, overwrite=overwrite)

    def read_keyframes(self) -> Trajectory:
        """A single-session run's refined keyframe poses in the input's frame."""
        return self._read_tum(self.keyframes_tum, "refined keyframe poses")

    def write_keyframes(self, trajectory: Trajectory, *, overwrite: bool = False) -> Path:
        return self._write_tum(self.keyframes_tum, trajectory, overwrite=overwrite)

    def read_session_keyframes(self, name: str) -> Trajectory:
        """One session's refined keyframe poses in the input's frame (T_S_C or T_W_C)."""
        return self._read_tum(self.session_keyframes(name), f"refined keyframes of {name}")

    def write_session_keyframes(
        self, name: str, trajectory: Trajectory, *, overwrite: bool = False
    ) -> Path:
        return self._write_tum(self.session_keyframes(name), trajectory, overwrite=overwrite)

    def read_session_keyframes_world(self, name: str) -> Trajectory:
        """One session's refined keyframe poses in the world frame (T_W_C)."""
        path = self.session_keyframes_world(name)
        return self._read_tum(path, f"refined world keyframes of {name}")

    def write_session_keyframes_world(
        self, name: str, trajectory: Trajectory, *, overwrite: bool = False
    ) -> Path:
        path = self.session_keyframes_world(name)
        return self._write_tum(path, trajectory, overwrite=overwrite)


class DenseFolder(HandoffFolder):
    """The dense stage: workspace/ (COLMAP dense workspace), fused.ply (+ .vis), mesh.ply,
    fused_corrected.ply (with colour correction), fused_supported.ply, dense.json."""

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
    def fused_visibility(self) -> Path:
        """COLMAP's list of the images each fused point was seen in."""
        return self.path / "fused.ply.vis"

    @property
    def fused_corrected(self) -> Path:
        return self.path / "fused_corrected.ply"

    @property
    def fused_supported(self) -> Path:
        """The fused points seen in enough images, which the mesh is built from."""
        return self.path / "fused_supported.ply"

    def read_report(self) -> dict[str, Any]:
        return self.read_json(self.report)

    def write_report(self, report: dict[str, Any], *, overwrite: bool = False) -> Path:
        """dense.json, the folder's marker: write it last."""
        return self._write_json(self.report, report, overwrite=overwrite)


FOLDER_KINDS: tuple[type[HandoffFolder], ...] = (
    SessionFolder,
    CalibrationFolder,
    SlamFolder,
    DepthFolder,
    MergeFolder,
    SfmFolder,
    DenseFolder,
)


# ------------------------------------------------------------------------------ resume rule

F = TypeVar("F", bound=HandoffFolder)


def jsonable(value: Any) -> Any:
    """Options as JSON: dataclasses as mappings, Paths as strings, tuples as lists,
    NumPy scalars as Python numbers, anything else by repr."""
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
    item = getattr(value, "item", None)
    if callable(item) and getattr(value, "shape", None) == ():  # a NumPy scalar
        return jsonable(item())
    return repr(value)


def fingerprint(path: Path | str | None) -> str | None:
    """What an input looks like without reading it: the resolved path, size and
    modification time of the file, or of every file under the folder (None: no input;
    a path that does not exist is fingerprinted as missing)."""
    if path is None:
        return None
    path = Path(path)
    if not path.exists():
        return f"missing {path}"  # the stage's own reader says what it expected there
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha256(str(path.resolve()).encode())
    for file in files:
        stat = file.stat()
        h.update(f"\0{file.relative_to(path)}\0{stat.st_size}\0{stat.st_mtime_ns}".encode())
    return h.hexdigest()


def result_stamp(stage: str, options: Any, **inputs: Any) -> dict[str, Any]:
    """The stamp of a result: the stage, its options and a fingerprint of each input
    (a path, a list of paths or None)."""

    def prints(value: Any) -> Any:
        if isinstance(value, list | tuple):
            return [fingerprint(v) for v in value]
        return fingerprint(value)

    return {
        "stage": stage,
        "options": jsonable(options),
        "inputs": {name: prints(value) for name, value in sorted(inputs.items())},
    }


def read_result_stamp(folder: HandoffFolder) -> dict[str, Any] | None:
    """The stamp a finished result was written with, or None."""
    try:
        document = json.loads((folder.path / RESULT_STAMP).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return document if isinstance(document, dict) else None


def _partial(folder: F, stamp: dict[str, Any]) -> F:
    digest = hashlib.sha256(json.dumps(stamp, sort_keys=True).encode()).hexdigest()[:12]
    name = f".{folder.path.name}.partial-{digest}"
    return type(folder)(folder.path.with_name(name))


@contextlib.contextmanager
def rebuild(
    folder: F, stamp: dict[str, Any], *, overwrite: bool = False, resumable: bool = False
) -> Iterator[F | None]:
    """The resume rule (module docstring) around a stage's writing.

    Yields None when `folder` already holds a complete result with this `stamp` and not
    `overwrite` (keep it, write nothing); else a partial folder of the same kind to write
    the result into, which is stamped, checked for the kind's marker and swapped in for
    `folder` when the block ends. Raises OutputExistsError when something else is in the way and not
    `overwrite`. resumable: the stage resumes an interrupted build from what its partial
    folder holds (else a partial left by an interrupted build is emptied first).
    """
    out = folder.path
    present = out.is_dir() and any(out.iterdir())
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out}: a file is in the way (expected a {folder.kind} folder)")
    if present:
        if not overwrite and folder.is_complete() and read_result_stamp(folder) == stamp:
            log.info("%s: %s result up to date (same inputs and options): kept", out, folder.kind)
            yield None
            return
        if not overwrite:
            what = (
                f"holds a {folder.kind} result of other inputs or options"
                if folder.is_complete()
                else f"holds other files, not a complete {folder.kind} folder"
            )
            raise OutputExistsError(f"{out}: {what} (refusing to overwrite; pass overwrite)")
    partial = _partial(folder, stamp)
    if partial.path.exists() and not resumable:
        shutil.rmtree(partial.path)
    partial.path.mkdir(parents=True, exist_ok=True)
    try:
        yield partial
    except BaseException:
        if not resumable:
            shutil.rmtree(partial.path, ignore_errors=True)
        raise
    if not partial.is_complete():
        shutil.rmtree(partial.path, ignore_errors=True)
        raise StageError(f"{out}: the {folder.kind} stage finished without writing {folder.marker}")
    write_text_atomic(
        partial.path / RESULT_STAMP, json.dumps(stamp, indent=2) + "\n", overwrite=True
    )
    with atomic_path(out, overwrite=True) as tmp:
        partial.path.rename(tmp)


@contextlib.contextmanager
def rebuild_files(
    folder: F, marker: Path, stamp: dict[str, Any], *, overwrite: bool = False
) -> Iterator[F | None]:
    """The resume rule for one step of several that share a folder (the calibration
    steps): the step's outputs, `marker` the one it writes last, are its result.

    Yields None when `marker` exists from a run with this `stamp` and not `overwrite`;
    raises OutputExistsError when it exists from another run and not `overwrite`; else
    yields a partial folder of the same kind beside `folder` to write the step's files
    into, which are moved into `folder` when the block ends (the marker last) and the
    step's stamp written beside them. Other files in `folder` are left alone.
    """
    stamp_path = folder.path / f".wreckmap-result-{marker.stem}.json"
    if marker.exists() and not overwrite:
        try:
            previous = json.loads(stamp_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            previous = None
        if previous == stamp:
            log.info("%s: up to date (same inputs and options): kept", marker)
            yield None
            return
        raise OutputExistsError(
            f"{marker}: a result of other inputs or options (refusing to overwrite; pass overwrite)"
        )
    if folder.path.exists() and not folder.path.is_dir():
        raise OutputExistsError(f"{folder.path}: a file is in the way (expected a folder)")
    partial = _partial(folder, {**stamp, "marker": marker.name})
    shutil.rmtree(partial.path, ignore_errors=True)
    partial.path.mkdir(parents=True)
    try:
        yield partial
        if not (partial.path / marker.name).is_file():
            raise StageError(f"{folder.path}: the step finished without writing {marker.name}")
        folder.path.mkdir(parents=True, exist_ok=True)
        entries = sorted(partial.path.iterdir(), key=lambda p: p.name == marker.name)
        for entry in entries:
            target = folder.path / entry.name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            entry.replace(target)
        write_text_atomic(stamp_path, json.dumps(stamp, indent=2) + "\n", overwrite=True)
    finally:
        shutil.rmtree(partial.path, ignore_errors=True)
