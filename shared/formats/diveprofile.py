"""Dive folders: one CSV per dive plus `dives.json`, the hand-off from the dive computer.

A dive folder holds, for each dive:

* `<start>_<fingerprint>.csv` with the header `timestamp_s,depth_m,temperature_c`, one
  sample a line. `timestamp_s` is the dive computer's clock as logged: seconds since
  1970-01-01 of the computer's *local wall clock*, read as if it were UTC (dive computers
  store no zone). Depth is metres positive down, temperature degrees Celsius; an empty
  cell means the value was not logged for that sample.
* optionally the raw bytes the computer sent (`<start>_<fingerprint>.bin`), so a parser
  fix can re-read them;
* an entry in `dives.json` (start in ISO 8601 with no zone, duration_s, max_depth_m,
  samples, model, serial, fingerprint, source, sample_interval_s, csv, raw).

`write_dive` adds a dive and updates `dives.json` atomically; it never overwrites an
existing dive CSV. `read_dive_folder` and `read_profile` read them back.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.errors import InputError, OutputExistsError
from shared.fsutil import write_bytes_atomic, write_text_atomic

INDEX_NAME = "dives.json"
CSV_HEADER = ("timestamp_s", "depth_m", "temperature_c")
INDEX_FORMAT = "wreckmap-dives"
INDEX_VERSION = 1
CLOCK_NOTE = "dive-computer local wall clock, no zone; timestamps are seconds as if UTC"


@dataclass
class DiveProfile:
    """One dive as logged by one dive computer.

    stamps_s: (N,) float64, dive-computer clock, seconds since 1970-01-01 of the
        computer's local wall clock read as UTC (no zone).
    depth_m: (N,) float64, metres positive down; NaN where not logged.
    temperature_c: (N,) float64, water temperature in degrees Celsius; NaN where not logged.
    start_iso: dive start on the same clock, ISO 8601 with no zone ("2023-11-15T22:13:20").
        The first sample may come one sample interval after the start (Shearwater does so).
    model, serial: the dive computer ("Shearwater Perdix AI", "1234ABCD"); "" if unknown.
    fingerprint: identifies the dive on its computer (Shearwater: start time, 8 hex digits).
    source: where the dive came from ("download socket://...", "import test42.uddf").
    sample_interval_s: logged sample interval in seconds, None when irregular or unknown.
    """

    stamps_s: NDArray[np.float64]
    depth_m: NDArray[np.float64]
    temperature_c: NDArray[np.float64]
    start_iso: str
    model: str = ""
    serial: str = ""
    fingerprint: str = ""
    source: str = ""
    sample_interval_s: float | None = None

    def __post_init__(self) -> None:
        self.stamps_s = np.asarray(self.stamps_s, dtype=np.float64)
        self.depth_m = np.asarray(self.depth_m, dtype=np.float64)
        self.temperature_c = np.asarray(self.temperature_c, dtype=np.float64)
        n = self.stamps_s.shape
        if self.stamps_s.ndim != 1 or self.depth_m.shape != n or self.temperature_c.shape != n:
            raise ValueError(
                "DiveProfile: stamps_s, depth_m and temperature_c must be 1-D arrays of one "
                f"length (got {self.stamps_s.shape}, {self.depth_m.shape}, "
                f"{self.temperature_c.shape})"
            )

    @property
    def start_s(self) -> float:
        """The start as seconds on the dive-computer clock (local wall clock read as UTC)."""
        return iso_to_stamp_s(self.start_iso)

    @property
    def duration_s(self) -> float:
        """Seconds from the start to the last sample (0 for a dive without samples)."""
        if self.stamps_s.size == 0:
            return 0.0
        return float(self.stamps_s[-1] - self.start_s)

    @property
    def max_depth_m(self) -> float:
        """Greatest logged depth in metres (NaN when no depth was logged)."""
        if self.depth_m.size == 0 or bool(np.all(np.isnan(self.depth_m))):
            return math.nan
        return float(np.nanmax(self.depth_m))


def iso_to_stamp_s(start_iso: str) -> float:
    """ISO 8601 wall-clock time (no zone, or a zone that is ignored) -> seconds, read as UTC."""
    text = start_iso.strip()
    if text.endswith("Z"):
        text = text[:-1]
    parsed = datetime.fromisoformat(text)
    return parsed.replace(tzinfo=UTC).timestamp()


def stamp_s_to_iso(stamp_s: float) -> str:
    """Seconds on a wall clock read as UTC -> ISO 8601 with no zone (whole seconds kept)."""
    moment = datetime.fromtimestamp(stamp_s, tz=UTC).replace(tzinfo=None)
    if moment.microsecond == 0:
        return moment.isoformat(timespec="seconds")
    return moment.isoformat()


def _format_value(value: float) -> str:
    # repr() is the shortest text that reads back to the same float: exact and short.
    return "" if math.isnan(value) else repr(float(value))


def dive_csv_text(profile: DiveProfile) -> str:
    """The CSV text of one dive (header, then one sample a line)."""
    out = io.StringIO()
    out.write(",".join(CSV_HEADER) + "\n")
    for stamp, depth, temp in zip(
        profile.stamps_s, profile.depth_m, profile.temperature_c, strict=True
    ):
        # At least 9 decimals for seconds (conventions.md); this still reads back exactly.
        out.write(f"{float(stamp):.9f},{_format_value(depth)},{_format_value(temp)}\n")
    return out.getvalue()


def _parse_cell(path: Path, line_no: int, column: str, cell: str) -> float:
    cell = cell.strip()
    if cell == "":
        return math.nan
    try:
        return float(cell)
    except ValueError:
        raise InputError(
            f"{path}:{line_no}: {column} {cell!r} is not a number (expected a decimal or an "
            "empty cell)"
        ) from None


def read_csv_rows(path: Path, *, what: str, encoding: str = "utf-8") -> list[list[str]]:
    """The rows of a CSV file from outside (a dive computer's, a logbook's export); an
    InputError naming the file (and the line) when it is missing, unreadable, not UTF-8
    text or not CSV. what: the kind of file expected ("dive CSV"); encoding: "utf-8-sig"
    to drop a byte-order mark."""
    try:
        text = path.read_text(encoding=encoding)
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except UnicodeDecodeError as error:
        raise InputError(
            f"{path}: not UTF-8 text at byte {error.start} (expected a {what})"
        ) from None
    except OSError as error:  # a folder, no permission...
        raise InputError(f"{path}: cannot read ({error.strerror})") from None
    reader = csv.reader(io.StringIO(text))
    try:
        return list(reader)
    except csv.Error as error:  # a cell beyond the csv module's field size limit, for example
        raise InputError(f"{path}:{reader.line_num}: not a valid CSV line ({error})") from None


def read_dive_csv_arrays(
    path: Path | str,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Read one dive CSV into (stamps_s, depth_m, temperature_c), NaN for empty cells."""
    path = Path(path)
    rows = read_csv_rows(path, what="dive CSV")
    if not rows or tuple(cell.strip() for cell in rows[0]) != CSV_HEADER:
        found = ",".join(rows[0]) if rows else "an empty file"
        raise InputError(f"{path}:1: expected the header {','.join(CSV_HEADER)}, found {found}")
    stamps: list[float] = []
    depths: list[float] = []
    temps: list[float] = []
    for line_no, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != 3:
            raise InputError(f"{path}:{line_no}: expected 3 cells, found {len(row)}")
        stamp = _parse_cell(path, line_no, "timestamp_s", row[0])
        if math.isnan(stamp):
            raise InputError(f"{path}:{line_no}: timestamp_s is empty (every sample needs one)")
        if not _MIN_STAMP_S <= stamp <= _MAX_STAMP_S:
            raise InputError(
                f"{path}:{line_no}: timestamp_s {stamp} is not a date (expected seconds since "
                "1970 between years 1 and 9999)"
            )
        if stamps and stamp < stamps[-1]:
            raise InputError(
                f"{path}:{line_no}: timestamp_s {stamp} goes backwards (previous {stamps[-1]})"
            )
        stamps.append(stamp)
        depths.append(_parse_cell(path, line_no, "depth_m", row[1]))
        temps.append(_parse_cell(path, line_no, "temperature_c", row[2]))
    return (
        np.asarray(stamps, dtype=np.float64),
        np.asarray(depths, dtype=np.float64),
        np.asarray(temps, dtype=np.float64),
    )


def _regular_interval_s(stamps_s: NDArray[np.float64]) -> float | None:
    if stamps_s.size < 2:
        return None
    steps = np.diff(stamps_s)
    if float(np.ptp(steps)) <= 1e-6 * max(1.0, float(np.abs(steps).max())):
        return float(steps[0])
    return None


def read_dive_csv(path: Path | str) -> DiveProfile:
    """Read one dive CSV; metadata comes from `dives.json` beside it when it lists the file.

    Without an index entry the start is the first sample, the sample interval is the
    step between samples when regular, and model/serial/fingerprint are empty.
    """
    path = Path(path)
    stamps, depths, temps = read_dive_csv_arrays(path)
    entry: dict[str, Any] | None = None
    index_path = path.parent / INDEX_NAME
    if index_path.is_file():
        for candidate in _read_index(index_path):
            if candidate["csv"] == path.name:
                entry = candidate
    if entry is None:
        if stamps.size == 0:
            raise InputError(f"{path}: no samples and no {INDEX_NAME} entry (cannot date it)")
        return DiveProfile(
            stamps_s=stamps,
            depth_m=depths,
            temperature_c=temps,
            start_iso=stamp_s_to_iso(float(stamps[0])),
            source=path.name,
            sample_interval_s=_regular_interval_s(stamps),
        )
    return _profile_from_entry(entry, stamps, depths, temps)


def _profile_from_entry(
    entry: dict[str, Any],
    stamps: NDArray[np.float64],
    depths: NDArray[np.float64],
    temps: NDArray[np.float64],
) -> DiveProfile:
    interval = entry.get("sample_interval_s")
    return DiveProfile(
        stamps_s=stamps,
        depth_m=depths,
        temperature_c=temps,
        start_iso=str(entry["start"]),
        model=str(entry.get("model", "")),
        serial=str(entry.get("serial", "")),
        fingerprint=str(entry.get("fingerprint", "")),
        source=str(entry.get("source", "")),
        sample_interval_s=None if interval is None else float(interval),
    )


_REQUIRED_KEYS = ("csv", "start")
# Seconds of 0001-01-01 and 9999-12-31 (UTC): the range `stamp_s_to_iso` can print.
_MIN_STAMP_S = -62_135_596_800.0
_MAX_STAMP_S = 253_402_300_799.0


def _is_number_or_none(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond float range
        return False


def _read_index(index_path: Path) -> list[dict[str, Any]]:
    try:
        document = json.loads(index_path.read_text(encoding="utf-8"))
    except RecursionError:
        raise InputError(f"{index_path}: not valid JSON (nested too deeply)") from None
    except json.JSONDecodeError as error:
        raise InputError(
            f"{index_path}:{error.lineno}: not valid JSON ({error.msg}; expected the dive index)"
        ) from None
    except UnicodeDecodeError as error:
        raise InputError(
            f"{index_path}: not UTF-8 text at byte {error.start} (expected the dive index)"
        ) from None
    if not isinstance(document, dict) or not isinstance(document.get("dives"), list):
        raise InputError(f"{index_path}: expected an object with a 'dives' list")
    dives: list[dict[str, Any]] = []
    for number, entry in enumerate(document["dives"]):
        if not isinstance(entry, dict):
            raise InputError(f"{index_path}: dives[{number}] is not an object")
        for key in _REQUIRED_KEYS:
            if not isinstance(entry.get(key), str):
                raise InputError(f"{index_path}: dives[{number}] has no '{key}' string")
        name = entry["csv"]
        if Path(name).name != name or name in ("", ".", ".."):
            raise InputError(
                f"{index_path}: dives[{number}].csv {name!r} must be a file name in the folder"
            )
        try:
            iso_to_stamp_s(entry["start"])
        except (ValueError, OverflowError):
            raise InputError(
                f"{index_path}: dives[{number}].start {entry['start'][:80]!r} is not ISO 8601"
            ) from None
        if not _is_number_or_none(entry.get("sample_interval_s")):
            raise InputError(
                f"{index_path}: dives[{number}].sample_interval_s is not a number or null"
            )
        dives.append(entry)
    return dives


def read_dive_index(folder: Path | str) -> list[dict[str, Any]]:
    """The entries of `folder/dives.json` (an empty list when there is no index yet)."""
    index_path = Path(folder) / INDEX_NAME
    if not index_path.exists():
        return []
    return _read_index(index_path)


def read_dive_folder(folder: Path | str) -> list[DiveProfile]:
    """Every dive of a dive folder, in `dives.json` order."""
    folder = Path(folder)
    index_path = folder / INDEX_NAME
    if not index_path.is_file():
        raise InputError(f"{folder}: no {INDEX_NAME} (expected a dive folder)")
    profiles = []
    for entry in _read_index(index_path):
        stamps, depths, temps = read_dive_csv_arrays(folder / entry["csv"])
        profiles.append(_profile_from_entry(entry, stamps, depths, temps))
    return profiles


def read_profile(path: Path | str) -> DiveProfile:
    """One dive: a dive CSV, or a dive folder holding exactly one dive."""
    path = Path(path)
    if path.is_dir():
        dives = read_dive_folder(path)
        if len(dives) != 1:
            listing = ", ".join(
                f"{d.start_iso} ({d.fingerprint or 'no fingerprint'})" for d in dives
            )
            raise InputError(
                f"{path}: expected exactly one dive, found {len(dives)}"
                + (f": {listing}; pass one CSV instead" if dives else "")
            )
        return dives[0]
    if not path.exists():
        raise InputError(f"{path}: no such dive CSV or dive folder")
    return read_dive_csv(path)


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
_MAX_FINGERPRINT_CHARS = 64


def dive_file_stem(profile: DiveProfile) -> str:
    """`<start>_<fingerprint>`, e.g. `2023-11-15T221320_65554280` (safe on every filesystem)."""
    start = profile.start_iso.replace(":", "").replace(" ", "T")
    fingerprint = _UNSAFE.sub("-", profile.fingerprint) or "nofp"
    if len(fingerprint) > _MAX_FINGERPRINT_CHARS:
        # A logbook may use any text as a dive id; file names stop at 255 bytes. The
        # digest keeps two long ids that share a prefix apart (the index keeps the full id).
        digest = hashlib.sha1(profile.fingerprint.encode("utf-8")).hexdigest()[:8]
        fingerprint = f"{fingerprint[: _MAX_FINGERPRINT_CHARS - 9]}-{digest}"
    return f"{_UNSAFE.sub('-', start)[:40]}_{fingerprint}"


def _json_number(value: float | None) -> float | None:
    if value is None or math.isnan(value):
        return None
    return float(value)


def write_dive(
    folder: Path | str,
    profile: DiveProfile,
    *,
    raw: bytes | None = None,
    raw_suffix: str = ".bin",
) -> Path:
    """Add one dive to a dive folder and return the path of its CSV.

    Writes the CSV (and the raw bytes, when given) through temporary names, then adds the
    dive to `dives.json` (rewritten atomically). Raises `OutputExistsError` when the CSV
    or the raw file already exists, or when `dives.json` already lists a dive with the same
    model, serial and fingerprint; the folder is then unchanged.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries = read_dive_index(folder)
    for entry in entries:
        if (
            profile.fingerprint
            and entry.get("fingerprint") == profile.fingerprint
            and entry.get("serial", "") == profile.serial
            and entry.get("model", "") == profile.model
        ):
            raise OutputExistsError(
                f"{folder / INDEX_NAME}: dive {profile.fingerprint} of {profile.model} "
                f"{profile.serial} is already recorded as {entry['csv']}"
            )
    stem = dive_file_stem(profile)
    csv_path = folder / f"{stem}.csv"
    raw_path = folder / f"{stem}{raw_suffix}" if raw is not None else None
    for target in (csv_path, raw_path):
        if target is not None and target.exists():
            raise OutputExistsError(f"{target}: already exists (refusing to overwrite a dive)")
    if raw is not None and raw_path is not None:
        write_bytes_atomic(raw_path, raw)
    write_text_atomic(csv_path, dive_csv_text(profile))
    entries.append(
        {
            "csv": csv_path.name,
            "raw": None if raw_path is None else raw_path.name,
            "start": profile.start_iso,
            "duration_s": _json_number(profile.duration_s),
            "max_depth_m": _json_number(profile.max_depth_m),
            "samples": int(profile.stamps_s.size),
            "sample_interval_s": _json_number(profile.sample_interval_s),
            "model": profile.model,
            "serial": profile.serial,
            "fingerprint": profile.fingerprint,
            "source": profile.source,
        }
    )
    entries.sort(key=lambda item: (iso_to_stamp_s(str(item["start"])), str(item["csv"])))
    document = {
        "format": INDEX_FORMAT,
        "version": INDEX_VERSION,
        "clock": CLOCK_NOTE,
        "dives": entries,
    }
    write_text_atomic(folder / INDEX_NAME, json.dumps(document, indent=2) + "\n", overwrite=True)
    return csv_path
