"""The evaluation's camera -> true time offset for each kind of session: the simulator's
EuRoC copy is on the camera clock; a GoPro import, and a session folder cut from one, on
the GoPro's clock; a recorder's session folder without a GoPro clock on the camera's."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from postproc.pipeline.evaluate import camera_to_true_ns
from shared.errors import InputError

SHIFT_NS = 2_500_000
ENTRY = {"first_frame_cam_ns": 1_000_000_000_000}
CREATION_NS = 1_718_443_824_000_000_000


def _session(source: str, folder: Path) -> SimpleNamespace:
    return SimpleNamespace(name="dive1", source=source, paths=[folder])


def _write_session_yaml(folder: Path, text: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "session.yaml").write_text(text, encoding="utf-8")


def test_euroc_copy_is_on_the_camera_clock(tmp_path: Path) -> None:
    project = SimpleNamespace(output=tmp_path / "run")
    assert camera_to_true_ns(project, _session("euroc", tmp_path), ENTRY, SHIFT_NS) == SHIFT_NS


def test_gopro_import_and_a_session_cut_from_it_share_the_gopro_clock(tmp_path: Path) -> None:
    gopro_clock = f"clocks:\n  gopro:\n    creation_time_ns: {CREATION_NS}\n"
    project = SimpleNamespace(output=tmp_path / "run")
    _write_session_yaml(tmp_path / "run" / "imports" / "dive1", gopro_clock)
    expected = ENTRY["first_frame_cam_ns"] + SHIFT_NS - CREATION_NS
    imported = camera_to_true_ns(project, _session("gopro", tmp_path / "x"), ENTRY, SHIFT_NS)
    assert imported == expected
    _write_session_yaml(tmp_path / "cut", gopro_clock)
    cut = camera_to_true_ns(project, _session("session", tmp_path / "cut"), ENTRY, SHIFT_NS)
    assert cut == expected


def test_recorder_session_without_a_gopro_clock_is_on_the_camera_clock(tmp_path: Path) -> None:
    project = SimpleNamespace(output=tmp_path / "run")
    _write_session_yaml(tmp_path / "rec", "clocks:\n  host:\n    description: x\n")
    session = _session("session", tmp_path / "rec")
    assert camera_to_true_ns(project, session, ENTRY, SHIFT_NS) == SHIFT_NS
    empty = _session("session", tmp_path / "no_yaml")
    assert camera_to_true_ns(project, empty, ENTRY, SHIFT_NS) == SHIFT_NS


def test_gopro_import_without_its_clock_is_refused(tmp_path: Path) -> None:
    project = SimpleNamespace(output=tmp_path / "run")
    _write_session_yaml(tmp_path / "run" / "imports" / "dive1", "clocks: {}\n")
    with pytest.raises(InputError, match="creation_time_ns"):
        camera_to_true_ns(project, _session("gopro", tmp_path / "x"), ENTRY, SHIFT_NS)
