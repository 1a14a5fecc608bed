"""The hand-off folder kinds and the one resume rule every stage goes through."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import pytest

from shared.errors import InputError, OutputExistsError, StageError
from shared.folders import (
    FOLDER_KINDS,
    RESULT_STAMP,
    CalibrationFolder,
    DenseFolder,
    DepthFolder,
    MergeFolder,
    SessionFolder,
    SfmFolder,
    SlamFolder,
    fingerprint,
    read_result_stamp,
    rebuild,
    result_stamp,
)


def _build(folder: SlamFolder, stamp: dict[str, Any], text: str, **kwargs: object) -> bool:
    """Run the rule once; write a result holding `text`. True when it built."""
    with rebuild(folder, stamp, **kwargs) as work:  # type: ignore[arg-type]
        if work is None:
            return False
        work.trajectory.write_text(text)
        work.stats.write_text(json.dumps({"text": text}))
    return True


def test_every_kind_names_a_marker_it_owns() -> None:
    for kind in FOLDER_KINDS:
        folder = kind(Path("x"))
        assert kind.marker and folder.marker_path == Path("x") / kind.marker
    slam = SlamFolder("run/sessions/dive1")
    assert slam.depth == DepthFolder("run/sessions/dive1/depth") and slam.name == "dive1"
    assert slam.keyframe_image(12) == Path("run/sessions/dive1/keyframes/12.png")


def test_same_stamp_kept_other_refused_then_swapped_in(tmp_path: Path) -> None:
    (tmp_path / "in.txt").write_text("recording")
    folder = SlamFolder(tmp_path / "slam")
    stamp = result_stamp("slam", {"max_frames": 5}, recording=tmp_path / "in.txt")
    assert _build(folder, stamp, "first") is True
    assert folder.is_complete() and read_result_stamp(folder) == stamp
    # Same inputs and options: kept, nothing written.
    before = folder.stats.stat().st_mtime_ns
    assert _build(folder, stamp, "second") is False
    assert folder.stats.stat().st_mtime_ns == before
    # Other options: refused without overwrite, the result untouched.
    other = result_stamp("slam", {"max_frames": 6}, recording=tmp_path / "in.txt")
    with pytest.raises(OutputExistsError, match=r"slam: holds a SLAM result of other inputs"):
        _build(folder, other, "third")
    assert folder.trajectory.read_text() == "first"
    # With overwrite: rebuilt beside it and swapped in; no partial left.
    assert _build(folder, other, "third", overwrite=True) is True
    assert folder.trajectory.read_text() == "third" and read_result_stamp(folder) == other
    # overwrite redoes even an up-to-date result.
    assert _build(folder, other, "fourth", overwrite=True) is True
    assert folder.trajectory.read_text() == "fourth"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.txt", "slam"]


def test_changed_input_is_a_different_result(tmp_path: Path) -> None:
    source = tmp_path / "in.txt"
    source.write_text("a")
    first = result_stamp("depth", None, trajectory=source, dive=None)
    source.write_text("bb")
    assert result_stamp("depth", None, trajectory=source, dive=None) != first
    # Same size, touched: a new modification time is a new input.
    before = fingerprint(source)
    stat = source.stat()
    os.utime(source, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert fingerprint(source) != before
    assert fingerprint(None) is None
    assert fingerprint(tmp_path / "nope") == f"missing {tmp_path / 'nope'}"


def test_a_foreign_folder_is_never_clobbered(tmp_path: Path) -> None:
    folder = SlamFolder(tmp_path / "slam")
    folder.path.mkdir()
    (folder.path / "thesis.tex").write_text("precious")
    with pytest.raises(OutputExistsError, match="holds other files, not a complete SLAM"):
        _build(folder, result_stamp("slam", None), "x")
    assert (folder.path / "thesis.tex").read_text() == "precious"
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputExistsError, match="a file is in the way"):
        _build(SlamFolder(tmp_path / "file"), result_stamp("slam", None), "x")


def test_a_failed_build_leaves_the_old_result(tmp_path: Path) -> None:
    folder = SlamFolder(tmp_path / "slam")
    _build(folder, result_stamp("slam", 1), "old")
    with pytest.raises(RuntimeError), rebuild(folder, result_stamp("slam", 2), overwrite=True) as w:
        assert w is not None
        w.trajectory.write_text("half")
        raise RuntimeError("killed")
    assert folder.trajectory.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slam"]
    # A build that forgets the marker is refused and leaves nothing.
    with (
        pytest.raises(StageError, match=r"finished without writing stats\.json"),
        rebuild(folder, result_stamp("slam", 3), overwrite=True) as w,
    ):
        assert w is not None
        w.trajectory.write_text("no stats")
    assert folder.trajectory.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slam"]


def test_a_resumable_build_finds_its_partial_work(tmp_path: Path) -> None:
    folder = SlamFolder(tmp_path / "slam")
    stamp = result_stamp("sfm", {"n": 1})
    with pytest.raises(KeyboardInterrupt), rebuild(folder, stamp, resumable=True) as w:
        assert w is not None
        (w.path / "step1.done").write_text("expensive")
        raise KeyboardInterrupt
    assert not folder.path.exists()
    with rebuild(folder, stamp, resumable=True) as w:
        assert w is not None
        assert (w.path / "step1.done").read_text() == "expensive"
        w.stats.write_text("{}")
    assert (folder.path / "step1.done").is_file() and (folder.path / RESULT_STAMP).is_file()
    # Other options never see that work.
    with rebuild(folder, result_stamp("sfm", {"n": 2}), overwrite=True, resumable=True) as w:
        assert w is not None and not (w.path / "step1.done").exists()
        w.stats.write_text("{}")


# --------------------------------------------------------------- typed readers and writers


def _trajectory() -> Any:
    import numpy as np

    from shared.geometry import make_pose, so3_exp
    from shared.trajectory import Trajectory

    stamps = np.array([1_700_000_000_000_000_001, 1_700_000_000_050_000_000], dtype=np.int64)
    rotations = np.stack([so3_exp(np.array([0.1, -0.2, 0.3])), np.eye(3)])
    return Trajectory(stamps, make_pose(rotations, np.array([[1.0, 2.0, -3.5], [0.0, 0.0, 0.25]])))


# (folder, reader, writer, the file they own); readers and writers take `*args` first.
TRAJECTORY_FILES = [
    (SlamFolder("s"), "read_trajectory", "write_trajectory", (), "trajectory.tum"),
    (SlamFolder("s"), "read_keyframes", "write_keyframes", (), "keyframes.tum"),
    (DepthFolder("d"), "read_world", "write_world", (), "trajectory_world.tum"),
    (DepthFolder("d"), "read_world_fused", "write_world_fused", (), "trajectory_world_fused.tum"),
    (MergeFolder("m"), "read_merged_keyframes", "write_merged_keyframes", ("dive1",),
     "dive1/keyframes_merged.tum"),
    (SfmFolder("f"), "read_keyframes", "write_keyframes", (), "keyframes.tum"),
    (SfmFolder("f"), "read_session_keyframes", "write_session_keyframes", ("dive1",),
     "sessions/dive1/keyframes.tum"),
    (SfmFolder("f"), "read_session_keyframes_world", "write_session_keyframes_world", ("dive1",),
     "sessions/dive1/keyframes_world.tum"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("folder", "reader", "writer", "args", "name"),
    TRAJECTORY_FILES,
    ids=[f"{type(f).__name__}.{r}" for f, r, *_ in TRAJECTORY_FILES],
)
def test_trajectory_files_round_trip_and_name_the_file_they_cannot_read(
    tmp_path: Path, folder: Any, reader: str, writer: str, args: tuple[str, ...], name: str
) -> None:
    import numpy as np

    from shared.formats.tum import format_tum

    folder = type(folder)(tmp_path / folder.name)
    read = getattr(folder, reader)
    write = getattr(folder, writer)
    expected = rf"{re.escape(name)}: missing \(expected the .+ folder's "
    with pytest.raises(InputError, match=expected) as missing:
        read(*args)
    assert "\n" not in str(missing.value) and str(folder.path / name) in str(missing.value)
    trajectory = _trajectory()
    assert write(*args, trajectory) == folder.path / name
    # The bytes of the TUM writer, and back exactly.
    assert (folder.path / name).read_text() == format_tum(trajectory)
    back = read(*args)
    assert np.array_equal(back.stamps_ns, trajectory.stamps_ns)
    np.testing.assert_allclose(back.poses, trajectory.poses, atol=1e-15)
    with pytest.raises(OutputExistsError):
        write(*args, trajectory)
    write(*args, trajectory, overwrite=True)
    (folder.path / name).write_text("1.0 2.0 3.0\n")
    expected = rf"{re.escape(str(folder.path))}: .*:1: expected 8 numbers"
    with pytest.raises(InputError, match=expected) as invalid:
        read(*args)
    assert "\n" not in str(invalid.value)


JSON_FILES = [
    (SlamFolder("s"), "read_stats", "write_stats", "stats.json"),
    (DepthFolder("d"), "read_sync", "write_sync", "sync.json"),
    (MergeFolder("m"), "read_transforms", "write_transforms", "transforms.json"),
    (SfmFolder("f"), "read_stats", "write_stats", "stats.json"),
    (SfmFolder("f"), "read_transforms", "write_transforms", "transforms.json"),
    (DenseFolder("e"), "read_report", "write_report", "dense.json"),
]


@pytest.mark.parametrize(
    ("folder", "reader", "writer", "name"),
    JSON_FILES,
    ids=[f"{type(f).__name__}.{r}" for f, r, *_ in JSON_FILES],
)
def test_json_files_round_trip_and_name_the_file_they_cannot_read(
    tmp_path: Path, folder: Any, reader: str, writer: str, name: str
) -> None:
    folder = type(folder)(tmp_path / folder.name)
    path = folder.path / name
    with pytest.raises(InputError, match=rf"{re.escape(str(path))}: cannot read"):
        getattr(folder, reader)()
    document = {"frames": 3, "rms_m": 0.25, "sessions": {"dive1": [1, 2]}}
    assert getattr(folder, writer)(document) == path
    assert path.read_text() == json.dumps(document, indent=2) + "\n"
    assert getattr(folder, reader)() == document
    with pytest.raises(OutputExistsError):
        getattr(folder, writer)(document)
    path.write_text("{not json")
    with pytest.raises(InputError, match=rf"{re.escape(str(path))}: not valid JSON"):
        getattr(folder, reader)()
    path.write_text("[1, 2]")
    with pytest.raises(InputError, match=rf"{re.escape(str(path))}: expected a JSON object"):
        getattr(folder, reader)()


def test_slam_stats_write_what_json_cannot_hold_as_text(tmp_path: Path) -> None:
    folder = SlamFolder(tmp_path / "slam")
    folder.write_stats({"input": Path("a/b.mcap"), "frames": 2})
    assert folder.read_stats() == {"input": "a/b.mcap", "frames": 2}


def _cameras() -> list[Any]:
    import numpy as np

    from shared.calibration.cameras import PinholeRadtan
    from shared.calibration.kalibr import CameraCalibration
    from shared.geometry import make_pose, so3_exp

    cam0 = CameraCalibration(camera=PinholeRadtan(64, 48, 50.0, 51.0, 32.0, 24.0, 0.01, -0.002))
    cam1 = CameraCalibration(camera=PinholeRadtan(64, 48, 49.0, 49.5, 31.0, 23.5), name="cam1")
    cam1.cam_from_imu = make_pose(so3_exp(np.array([0.0, 0.01, 0.0])), np.array([-0.1, 0, 0]))
    return [cam0, cam1]


CAMCHAIN_FILES = [
    (SessionFolder("r"), "read_camchain", "write_camchain", "calib/camchain.yaml"),
    (SlamFolder("s"), "read_camchain", "write_camchain", "calib/camchain.yaml"),
    (CalibrationFolder("c"), "read_camchain", "write_camchain", "camchain.yaml"),
    (CalibrationFolder("c"), "read_imu_camchain", "write_imu_camchain", "camchain-imucam.yaml"),
    (CalibrationFolder("c"), "read_rig_camchain", "write_rig_camchain", "camchain-rig.yaml"),
]


@pytest.mark.parametrize(
    ("folder", "reader", "writer", "name"),
    CAMCHAIN_FILES,
    ids=[f"{type(f).__name__}.{r}" for f, r, *_ in CAMCHAIN_FILES],
)
def test_camchains_round_trip_and_name_the_file_they_cannot_read(
    tmp_path: Path, folder: Any, reader: str, writer: str, name: str
) -> None:
    import numpy as np

    from shared.calibration.kalibr import format_camchain

    folder = type(folder)(tmp_path / folder.name)
    path = folder.path / name
    expected = rf"{re.escape(str(path))}: missing \(expected the .+ camera chain"
    with pytest.raises(InputError, match=expected):
        getattr(folder, reader)()
    cameras = _cameras()
    assert getattr(folder, writer)(cameras) == path
    assert path.read_text() == format_camchain(cameras)
    back = getattr(folder, reader)()
    assert [c.name for c in back] == ["cam0", "cam1"]
    assert back[0].camera == cameras[0].camera
    np.testing.assert_allclose(back[1].cam_from_imu, cameras[1].cam_from_imu, atol=1e-12)
    with pytest.raises(OutputExistsError):
        getattr(folder, writer)(cameras)
    path.write_text("cam0: 3\n")
    with pytest.raises(InputError, match=rf"{re.escape(str(path))}") as invalid:
        getattr(folder, reader)()
    assert "\n" not in str(invalid.value)


@pytest.mark.parametrize("kind", [SessionFolder, SlamFolder])
def test_imu_noise_round_trip_and_names_the_file(tmp_path: Path, kind: Any) -> None:
    from shared.calibration.kalibr import ImuNoise

    folder = kind(tmp_path / "f")
    expected = rf"{re.escape(str(folder.imu_yaml))}: missing \(expected .+ IMU noise"
    with pytest.raises(InputError, match=expected):
        folder.read_imu_noise()
    noise = ImuNoise(1.1e-2, 4.3e-4, 1.87e-04, 2.66e-05, 397.5, topic="/gopro/imu")
    assert folder.write_imu_noise(noise) == folder.imu_yaml
    assert folder.read_imu_noise() == noise
    folder.imu_yaml.write_text("update_rate: -1\n")
    with pytest.raises(InputError, match=rf"{re.escape(str(folder.imu_yaml))}"):
        folder.read_imu_noise()


def test_merge_targets_read_as_a_mapping(tmp_path: Path) -> None:
    folder = MergeFolder(tmp_path / "merge")
    with pytest.raises(InputError, match=rf"{re.escape(str(folder.targets))}: cannot read"):
        folder.read_targets()
    folder.path.mkdir()
    folder.targets.write_text('{"grid": {"T_W_m": null}}')
    assert folder.read_targets() == {"grid": {"T_W_m": None}}


def test_the_folder_module_imports_no_numpy() -> None:
    """The scheduler and every `--help` import it: its readers import their formats."""
    import subprocess
    import sys

    code = "import sys, shared.folders; print('numpy' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, timeout=60)  # fmt: skip
    assert done.stdout.strip() == "False"
