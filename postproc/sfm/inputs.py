"""Reading the SfM stage's inputs: SLAM result folders and merge output.

A SLAM result folder holds `keyframes.tum` (camera poses `T_S_C`),
`keyframes/<timestamp_ns>.png` (as recorded), `calib/camchain.yaml` and
`stats.json`. A merge folder holds `transforms.json`, which maps each SLAM
folder's name to its `T_W_S` (4x4 nested lists), a 6x6 covariance and whether
the session could be placed (`"placed": false` when it shares no target with
the others). The reader accepts the sessions at the top level of that file or
under a "sessions" key; an entry may name its folder ("path", relative to the
merge folder or absolute), otherwise the SLAM folder is found among the other
inputs by name, or beside the merge folder.

A SLAM folder next to a depth-stage folder (`<dive>/slam` and `<dive>/depth`
with `trajectory_world.tum`) can be put at its true depth: the rigid transform
from `trajectory.tum` to `trajectory_world.tum` is its `T_W_S`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.calibration.cameras import CameraModel
from shared.errors import InputError
from shared.folders import MergeFolder, SlamFolder
from shared.trajectory import Trajectory

FloatArray = npt.NDArray[np.float64]

_NAMES = SlamFolder(".")  # the names of a SLAM folder's files, for the messages
_SLAM_HINT = (
    f"expected a SLAM result folder ({_NAMES.relative(_NAMES.keyframes_tum)}, "
    f"{_NAMES.relative(_NAMES.keyframes)}/, {_NAMES.relative(_NAMES.camchain)})"
)


@dataclass
class SessionInput:
    """One SLAM session as the SfM stage sees it.

    name: unique session name (the folder name, made unique). folder: the SLAM folder.
    keyframes: `T_S_C` keyframe poses (int64 ns stamps, camera clock). images: the
    keyframe image files, in the order of `keyframes`. camera: the camera model of the
    images. world_from_session: `T_W_S` when known (merge or depth), else None.
    world_sigma_m: one-sigma position error of `T_W_S`, metres. drift_per_m: the SLAM's
    drift rate (fraction of the distance travelled) if its stats.json gives one.
    """

    name: str
    folder: Path
    keyframes: Trajectory
    images: list[Path]
    camera: CameraModel
    world_from_session: FloatArray | None = None
    world_sigma_m: float = 0.0
    world_keyframes: Trajectory | None = None
    drift_per_m: float | None = None
    source: str = "slam"
    extra: dict[str, Any] = field(default_factory=dict)


def is_slam_folder(folder: Path) -> bool:
    return SlamFolder(folder).keyframes_tum.is_file()


def is_merge_folder(folder: Path) -> bool:
    return MergeFolder(folder).transforms.is_file() and not is_slam_folder(folder)


def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG header, None if the file is not a PNG."""
    with path.open("rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _image_size(path: Path) -> tuple[int, int]:
    size = _png_size(path)
    if size is not None:
        return size
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: cannot read image (expected a PNG or JPEG keyframe)")
    return int(image.shape[1]), int(image.shape[0])


def read_slam_folder(folder: Path, name: str) -> SessionInput:
    """Read one SLAM result folder; checks that every keyframe has its image at the size
    of the calibration (InputError naming the file otherwise)."""
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder ({_SLAM_HINT})")
    slam = SlamFolder(folder)
    if not is_slam_folder(folder):
        raise InputError(f"{folder}: no {slam.keyframes_tum.name} ({_SLAM_HINT})")
    calib = slam.camchain
    if not calib.is_file():
        raise InputError(
            f"{calib}: missing (expected the Kalibr camera chain the keyframes were taken with)"
        )
    camera = slam.read_camchain()[0].camera
    keyframes = slam.read_keyframes()
    images: list[Path] = []
    missing: list[str] = []
    for stamp in keyframes.stamps_ns.tolist():
        path = slam.keyframe_image(stamp)
        if not path.is_file():
            missing.append(path.name)
        images.append(path)
    if missing:
        raise InputError(
            f"{slam.keyframes}: {len(missing)} of {len(keyframes)} keyframe images missing, "
            f"first {missing[0]} (expected {slam.relative(slam.keyframes)}/<timestamp_ns>.png "
            f"for every line of {slam.keyframes_tum.name})"
        )
    expected = (int(camera.width), int(camera.height))
    for path in images:
        size = _image_size(path)
        if size != expected:
            raise InputError(
                f"{path}: image is {size[0]}x{size[1]} px but {calib.name} says "
                f"{expected[0]}x{expected[1]} (expected the images the calibration belongs to)"
            )
    drift = None
    if slam.stats.is_file():
        value = slam.read_stats().get("drift_per_m")
        if isinstance(value, int | float) and math.isfinite(value) and value > 0:
            drift = float(value)
    return SessionInput(
        name=name,
        folder=folder,
        keyframes=keyframes,
        images=images,
        camera=camera,
        drift_per_m=drift,
    )


def _matrix4(value: Any, where: str) -> FloatArray:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise InputError(f"{where}: T_W_S is not a 4x4 matrix of numbers") from error
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise InputError(f"{where}: T_W_S must be a finite 4x4 matrix, got shape {matrix.shape}")
    if not np.allclose(matrix[3], [0, 0, 0, 1]) or not np.allclose(
        matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-4
    ):
        raise InputError(f"{where}: T_W_S is not a rigid transform (expected [R t; 0 0 0 1])")
    return matrix


def read_merge_transforms(folder: Path) -> dict[str, dict[str, Any]]:
    """Session name -> {"placed", "world_from_session", "sigma_m", "path"} from transforms.json.

    The position sigma of `T_W_S` is the entry's "sigma_translation_m", else the root of
    the trace of the translation block of its 6x6 covariance (rotation first, as the
    merge stage writes it); 0 without either.
    """
    merge = MergeFolder(folder)
    path = merge.transforms
    document = merge.read_transforms()
    sessions = document.get("sessions", document)
    if not isinstance(sessions, dict) or not sessions:
        raise InputError(f"{path}: no sessions (expected {{name: {{T_W_S, covariance, placed}}}})")
    result: dict[str, dict[str, Any]] = {}
    for name, entry in sessions.items():
        where = f"{path}: {name}"
        if not isinstance(entry, dict):
            raise InputError(f"{where}: expected an object with T_W_S, covariance, placed")
        matrix = entry.get("T_W_S")
        placed = bool(entry.get("placed", matrix is not None)) and matrix is not None
        sigma = 0.0
        covariance = entry.get("covariance")
        given = entry.get("sigma_translation_m")
        if placed and isinstance(given, int | float) and math.isfinite(given) and given >= 0:
            sigma = float(given)
        elif placed and covariance is not None:
            cov = np.asarray(covariance, dtype=np.float64)
            if cov.shape == (6, 6) and np.all(np.isfinite(cov)):
                # The merge stage's convention: rotation first (rad), then translation (m).
                sigma = float(np.sqrt(max(float(np.trace(cov[3:, 3:])), 0.0)))
        source = entry.get("path") or entry.get("folder") or entry.get("input")
        result[str(name)] = {
            "placed": placed,
            "world_from_session": _matrix4(matrix, where) if placed else None,
            "sigma_m": sigma,
            "path": (folder / str(source)) if source else None,
        }
    return result


def read_place_links(
    input_dirs: list[Path], sessions: list[SessionInput]
) -> list[tuple[str, int, str, int]]:
    """The merge folder's verified cross-session keyframe pairs, in `sessions`' names.

    (session a, stamp a ns, session b, stamp b ns) per place natural-feature merging
    verified (`MergeFolder.read_place_pairs`), for `pairs.place_pairs`; empty without a
    merge folder among `input_dirs` or when it matched no natural features.
    """
    merges = [Path(f) for f in input_dirs if is_merge_folder(Path(f))]
    if not merges:
        return []
    name_of = {s.folder.name: s.name for s in sessions}
    return [
        (name_of[a], stamp_a, name_of[b], stamp_b)
        for a, stamp_a, b, stamp_b in MergeFolder(merges[0]).read_place_pairs()
        if a in name_of and b in name_of
    ]


def depth_world_from_session(slam_folder: Path) -> FloatArray | None:
    """`T_W_S` from the SLAM folder's depth stage (inside it, the pipeline's layout, or
    beside it, the command line's), or None when there is none.

    Fits the rigid transform taking `trajectory.tum` (T_S_B) onto the depth stage's
    `trajectory_world.tum` (T_W_B) over their common stamps.
    """
    from shared.geometry import make_pose, umeyama
    from shared.trajectory import associate

    slam = SlamFolder(slam_folder)
    body_path = slam.trajectory
    found = [d for d in slam.depth_folders() if d.trajectory_world.is_file()]
    if not (found and body_path.is_file()):
        return None
    world_path = found[0].trajectory_world
    world = found[0].read_world()
    body = slam.read_trajectory()
    i, j = associate(body.stamps_ns, world.stamps_ns, max_dt_ns=1_000_000)
    if i.size < 3:
        raise InputError(
            f"{world_path}: shares {i.size} stamps with {body_path.name} "
            "(expected the depth stage's output for this SLAM trajectory)"
        )
    R, t, _ = umeyama(body.positions[i], world.positions[j], with_scale=False)
    return make_pose(R, t)


def _merged_keyframes(merge: MergeFolder, session: SessionInput) -> Trajectory:
    path = merge.merged_keyframes(session.folder.name)
    merged = merge.read_merged_keyframes(session.folder.name)
    if not np.array_equal(merged.stamps_ns, session.keyframes.stamps_ns):
        raise InputError(
            f"{path}: {len(merged)} poses whose stamps differ from the {len(session.keyframes)} "
            f"of {SlamFolder(session.folder).keyframes_tum} (expected the same keyframes)"
        )
    return merged


def _unique_names(folders: list[Path]) -> list[str]:
    names = [f.name for f in folders]
    for k, folder in enumerate(folders):
        if names.count(folder.name) > 1:
            names[k] = f"{folder.parent.name}_{folder.name}"
    seen: dict[str, int] = {}
    for k, name in enumerate(names):
        if name in seen:
            seen[name] += 1
            names[k] = f"{name}_{seen[name]}"
        else:
            seen[name] = 0
    return names


def read_inputs(input_dirs: list[Path]) -> list[SessionInput]:
    """Every session of the given SLAM and merge folders, with `T_W_S` where known.

    With a merge folder, its placed sessions are in its world frame and the others
    unplaced. Without one, the first session defines the world (`T_W_S` from a depth
    folder beside it, or the identity) and the others are unplaced.
    """
    if not input_dirs:
        raise InputError("no input folders (expected SLAM result folders or a merge folder)")
    slam_dirs: list[Path] = []
    merges: list[tuple[Path, dict[str, dict[str, Any]]]] = []
    for folder in input_dirs:
        folder = Path(folder)
        if not folder.is_dir():
            raise InputError(f"{folder}: no such folder ({_SLAM_HINT}, or a merge folder)")
        if is_merge_folder(folder):
            merges.append((folder, read_merge_transforms(folder)))
        elif is_slam_folder(folder):
            slam_dirs.append(folder)
        else:
            slam_file = _NAMES.keyframes_tum.name
            merge_file = MergeFolder(folder).transforms.name
            raise InputError(
                f"{folder}: neither {slam_file} nor {merge_file} ({_SLAM_HINT}, "
                f"or a merge folder with {merge_file})"
            )
    if len(merges) > 1:
        raise InputError(
            f"{merges[1][0]}: more than one merge folder (expected one world frame; "
            f"{merges[0][0]} is already given)"
        )
    transforms = merges[0][1] if merges else {}
    by_name = {f.name: f for f in slam_dirs}
    for name, entry in transforms.items():
        if name in by_name:
            continue
        candidates = [entry["path"], merges[0][0].parent / name, merges[0][0] / name]
        found = next((c for c in candidates if c is not None and is_slam_folder(c)), None)
        if found is None:
            raise InputError(
                f"{MergeFolder(merges[0][0]).transforms}: session {name!r} has no SLAM folder "
                "(expected it among the inputs, at its 'path', or beside the merge folder)"
            )
        slam_dirs.append(found)
        by_name[name] = found
    names = _unique_names(slam_dirs)
    sessions = [read_slam_folder(f, n) for f, n in zip(slam_dirs, names, strict=True)]
    if transforms:
        for session in sessions:
            placement = transforms.get(session.folder.name)
            if placement is not None and placement["placed"]:
                session.world_from_session = placement["world_from_session"]
                session.world_sigma_m = placement["sigma_m"]
                session.source = "merge"
            merge = MergeFolder(merges[0][0])
            merged = merge.merged_keyframes(session.folder.name)
            if session.world_from_session is not None and merged.is_file():
                session.world_keyframes = _merged_keyframes(merge, session)
        if not any(s.world_from_session is not None for s in sessions):
            raise InputError(
                f"{MergeFolder(merges[0][0]).transforms}: no session is placed "
                "(expected at least one session with a T_W_S)"
            )
    else:
        first = sessions[0]
        depth = depth_world_from_session(first.folder)
        first.world_from_session = depth if depth is not None else np.eye(4)
        first.source = "depth" if depth is not None else "reference"
    return sessions
