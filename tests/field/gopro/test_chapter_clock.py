"""Chapters whose creation times disagree with their durations: the camera's clock stepped
between chapters (GPS fix, phone-app sync). The import keeps one media clock, reports the
step (session.yaml warning and chapter row, a clock_step event on /health), and `inspect`
shows it."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import yaml

from field.gopro.importer import ImportOptions, chapter_clock_step_ns, import_recording
from field.gopro.writer import write_gopro_chapters
from field.record.inspect import inspect_file
from shared.archive import ArchiveReader
from tests.field.gopro.test_import import CREATED, _synthetic


@pytest.fixture(scope="module")
def recording() -> dict[str, object]:
    return _synthetic()


def _chapters(folder: Path, recording: dict[str, object], second_created_at: object) -> list[Path]:
    first = write_gopro_chapters(folder / "a", file_number=42, payloads_per_chapter=3, **recording)  # type: ignore[arg-type]
    second = write_gopro_chapters(
        folder / "b",
        file_number=42,
        payloads_per_chapter=3,
        **{**recording, "creation_time": second_created_at},  # type: ignore[arg-type]
    )
    return [first[0], second[1]]


def _stamps(session: Path) -> np.ndarray:
    with ArchiveReader(session / "recording.mcap") as reader:
        return np.array([m.stamp_ns for _, _, m in reader.messages(["/cam0/video"])])


def test_step_rule() -> None:
    start, chapter = 1_000 * 10**9, 1_300 * 10**9
    assert chapter_clock_step_ns(None, chapter, start) is None
    assert chapter_clock_step_ns(chapter + 10**9, chapter, start) is None  # its own start
    assert chapter_clock_step_ns(start - 10**9, chapter, start) is None  # the recording's
    assert chapter_clock_step_ns(chapter + 60 * 10**9, chapter, start) == 60 * 10**9
    assert chapter_clock_step_ns(start - 3600 * 10**9, chapter, start) == -3900 * 10**9


@pytest.mark.parametrize(
    ("shift", "step_s"),
    [
        (timedelta(0), None),  # every chapter stamped with the recording's start
        (timedelta(seconds=3), None),  # each chapter stamped with its own start
        (timedelta(hours=-1), -3600 - 3.003),  # the clock went back an hour
        (timedelta(seconds=300), 300 - 3.003),  # or forward five minutes
    ],
    ids=["same", "own-start", "back-1h", "forward-5min"],
)
def test_chapter_creation_times_that_disagree_are_reported_not_followed(
    tmp_path: Path, recording: dict[str, object], shift: timedelta, step_s: float | None
) -> None:
    chapters = _chapters(tmp_path, recording, CREATED + shift)
    reference = _chapters(tmp_path / "ref", recording, CREATED)
    import_recording(ImportOptions(), reference, tmp_path / "ref-session")
    result = import_recording(ImportOptions(), chapters, tmp_path / "session")
    stamps = _stamps(tmp_path / "session")
    # One media clock whatever the creation times say: the same stamps as the reference.
    np.testing.assert_array_equal(stamps, _stamps(tmp_path / "ref-session"))
    assert np.all(np.diff(stamps) > 0)
    doc = yaml.safe_load((tmp_path / "session" / "session.yaml").read_text())
    rows = doc["chapters"]
    events = inspect_file(tmp_path / "session" / "recording.mcap").clock_steps
    if step_s is None:
        assert rows[1]["clock_step_s"] is None and not events
        assert not any("camera clock stepped" in w for w in doc.get("warnings") or [])
        return
    assert rows[1]["clock_step_s"] == pytest.approx(step_s, abs=1.01)
    assert any("GX020042.MP4" in w and "clock stepped" in w for w in doc["warnings"])
    (event,) = events
    assert event.details["chapter"] == "GX020042.MP4"
    assert event.details["step_s"] == pytest.approx(step_s, abs=1.01)
    assert event.stamp_ns == rows[1]["start_ns"]
    assert result.frames == len(stamps)
