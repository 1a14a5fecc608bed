"""The hand-off folder kinds and the one resume rule every stage goes through."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest

from shared.errors import OutputExistsError, StageError
from shared.folders import (
    FOLDER_KINDS,
    RESULT_STAMP,
    DepthFolder,
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
