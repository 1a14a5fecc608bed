"""Dive folders: write-then-read round trips and every refusal of bad content."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from shared.errors import InputError, OutputExistsError
from shared.formats.diveprofile import (
    DiveProfile,
    dive_csv_text,
    read_csv_rows,
    read_dive_csv,
    read_dive_folder,
    read_dive_index,
    read_profile,
    stamp_s_to_iso,
    write_dive,
)

START = 1_700_000_000.0  # 2023-11-14T22:13:20 on the computer's wall clock


def make_dive(start_s: float = START, *, fingerprint: str = "6553F100", n: int = 6) -> DiveProfile:
    rng = np.random.default_rng(7)
    stamps = np.asarray(start_s + 10.0 * np.arange(1, n + 1), dtype=np.float64)
    depth = rng.uniform(0, 40, n) * 0.3048  # imperial-style values: many digits
    temp = rng.uniform(2, 25, n)
    temp[1] = np.nan
    depth[2] = np.nan
    return DiveProfile(
        stamps_s=stamps,
        depth_m=depth,
        temperature_c=temp,
        start_iso=stamp_s_to_iso(start_s),
        model="Shearwater Perdix AI",
        serial="1234ABCD",
        fingerprint=fingerprint,
        source="test",
        sample_interval_s=10.0,
    )


def test_round_trip_is_exact_and_indexed(tmp_path: Path) -> None:
    dive = make_dive()
    csv_path = write_dive(tmp_path, dive, raw=b"\x10raw")
    assert csv_path.name == "2023-11-14T221320_6553F100.csv"
    assert (tmp_path / "2023-11-14T221320_6553F100.bin").read_bytes() == b"\x10raw"
    back = read_dive_csv(csv_path)
    np.testing.assert_array_equal(back.stamps_s, dive.stamps_s)
    np.testing.assert_array_equal(back.depth_m, dive.depth_m)  # NaN positions equal too
    np.testing.assert_array_equal(back.temperature_c, dive.temperature_c)
    assert (back.model, back.serial, back.fingerprint, back.sample_interval_s) == (
        dive.model,
        dive.serial,
        dive.fingerprint,
        10.0,
    )
    lines = csv_path.read_text().splitlines()
    assert lines[0] == "timestamp_s,depth_m,temperature_c"
    assert lines[2].split(",")[2] == "" and lines[3].split(",")[1] == ""
    assert lines[1].startswith("1700000010.000000000,")
    (entry,) = read_dive_index(tmp_path)
    assert entry["start"] == "2023-11-14T22:13:20"
    assert entry["duration_s"] == 60.0
    assert entry["samples"] == 6
    assert entry["max_depth_m"] == pytest.approx(float(np.nanmax(dive.depth_m)))
    assert entry["raw"] == "2023-11-14T221320_6553F100.bin"


def test_folder_sorted_by_start_and_read_profile(tmp_path: Path) -> None:
    write_dive(tmp_path, make_dive(START + 86_400, fingerprint="0000000B"))
    write_dive(tmp_path, make_dive(START, fingerprint="0000000A"))
    dives = read_dive_folder(tmp_path)
    assert [d.fingerprint for d in dives] == ["0000000A", "0000000B"]
    with pytest.raises(InputError, match=r"exactly one dive, found 2.*0000000A.*0000000B"):
        read_profile(tmp_path)
    one = tmp_path / "one"
    write_dive(one, make_dive())
    assert read_profile(one).fingerprint == "6553F100"
    csv_name = read_dive_index(one)[0]["csv"]
    assert read_profile(one / csv_name).duration_s == 60.0


def test_never_overwrites(tmp_path: Path) -> None:
    write_dive(tmp_path, make_dive())
    with pytest.raises(OutputExistsError, match="already recorded"):
        write_dive(tmp_path, make_dive())
    other = make_dive()
    other.serial = "FFFF0000"  # another unit, same start: the CSV name collides
    with pytest.raises(OutputExistsError, match="refusing to overwrite"):
        write_dive(tmp_path, other)
    assert len(read_dive_index(tmp_path)) == 1


def test_csv_without_index(tmp_path: Path) -> None:
    path = tmp_path / "lone.csv"
    path.write_text("timestamp_s,depth_m,temperature_c\n100.5,1.0,\n110.5,2.0,20\n")
    dive = read_profile(path)
    assert dive.start_iso == "1970-01-01T00:01:40.500000"
    assert dive.sample_interval_s == 10.0
    assert math.isnan(dive.temperature_c[0]) and dive.max_depth_m == 2.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("time,depth\n1,2\n", r"lone.csv:1: expected the header"),
        ("", r"lone.csv:1: expected the header .* found an empty file"),
        ("timestamp_s,depth_m,temperature_c\n1,abc,\n", r"lone.csv:2: depth_m 'abc'"),
        ("timestamp_s,depth_m,temperature_c\n1,2\n", r"lone.csv:2: expected 3 cells"),
        ("timestamp_s,depth_m,temperature_c\n,2,3\n", r"lone.csv:2: timestamp_s is empty"),
        ("timestamp_s,depth_m,temperature_c\n5,2,3\n4,2,3\n", r"lone.csv:3: .*goes backwards"),
        ("timestamp_s,depth_m,temperature_c\n", r"no samples and no dives.json"),
    ],
)
def test_bad_csv(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "lone.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=match):
        read_dive_csv(path)


def test_unreadable_inputs(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such dive CSV"):
        read_dive_csv(tmp_path / "missing.csv")
    with pytest.raises(InputError, match="no such dive CSV or dive folder"):
        read_profile(tmp_path / "missing.csv")
    (tmp_path / "latin.csv").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match="not UTF-8"):
        read_dive_csv(tmp_path / "latin.csv")
    with pytest.raises(InputError, match=r"no dives\.json"):
        read_dive_folder(tmp_path)
    with pytest.raises(ValueError, match="one length"):
        DiveProfile(np.zeros(2), np.zeros(3), np.zeros(2), start_iso="2024-01-01T00:00:00")


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ('{"dives": [\n  {"csv": ', r"dives.json:2: not valid JSON"),
        ("[]", "expected an object with a 'dives' list"),
        ('{"dives": [3]}', r"dives\[0\] is not an object"),
        ('{"dives": [{"start": "2024-01-01T00:00:00"}]}', r"dives\[0\] has no 'csv'"),
        ('{"dives": [{"csv": "../x.csv", "start": "2024"}]}', "must be a file name"),
        ('{"dives": [{"csv": "x.csv", "start": "June"}]}', r"dives\[0\].start 'June'"),
    ],
)
def test_bad_index(tmp_path: Path, content: str, match: str) -> None:
    (tmp_path / "dives.json").write_text(content)
    with pytest.raises(InputError, match=match):
        read_dive_folder(tmp_path)


def test_bad_index_bytes_and_missing_csv(tmp_path: Path) -> None:
    (tmp_path / "dives.json").write_bytes(b"\xff\xfe")
    with pytest.raises(InputError, match="not UTF-8"):
        read_dive_folder(tmp_path)
    (tmp_path / "dives.json").write_text(
        json.dumps({"dives": [{"csv": "gone.csv", "start": "2024-01-01T00:00:00"}]})
    )
    with pytest.raises(InputError, match=r"gone\.csv: no such dive CSV"):
        read_dive_folder(tmp_path)


def test_csv_text_of_empty_dive() -> None:
    empty = DiveProfile(np.zeros(0), np.zeros(0), np.zeros(0), start_iso="2024-01-01T00:00:00")
    assert dive_csv_text(empty) == "timestamp_s,depth_m,temperature_c\n"
    assert empty.duration_s == 0.0 and math.isnan(empty.max_depth_m)


def test_csv_rows_and_every_way_a_file_is_not_one(tmp_path: Path) -> None:
    path = tmp_path / "log.csv"
    path.write_bytes("\ufeffa,b\n1,2\n".encode())
    assert read_csv_rows(path, what="dive CSV", encoding="utf-8-sig") == [["a", "b"], ["1", "2"]]
    with pytest.raises(InputError, match=r"gone\.csv: no such dive CSV$"):
        read_csv_rows(tmp_path / "gone.csv", what="dive CSV")
    with pytest.raises(InputError, match=r": cannot read \("):
        read_csv_rows(tmp_path, what="dive CSV")
    path.write_bytes(b"a,b\n\xff\n")
    with pytest.raises(InputError, match=r"log\.csv: not UTF-8 text at byte 4 \(expected a dive"):
        read_csv_rows(path, what="dive CSV")
    path.write_text('a,b\n"x' + "y" * 200_000 + '"\n')
    with pytest.raises(InputError, match=r"log\.csv:\d+: not a valid CSV line"):
        read_csv_rows(path, what="dive CSV")
