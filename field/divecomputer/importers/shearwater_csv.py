"""Shearwater Cloud CSV exports: a summary header line, its values, then samples.

Units: metric or imperial, from the column headers when they carry units ("Depth (ft)",
"Water Temp (F)") and otherwise from the summary's "Imperial Units" flag.
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path

from field.divecomputer.importers.common import (
    SampleProblems,
    log,
    make_profile,
    start_fingerprint,
)
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, read_csv_rows

FEET_TO_M = 0.3048
_DATE_FORMATS = ("%m/%d/%Y %I:%M:%S %p", "%Y-%m-%d %H:%M:%S", "%d/%m/%Y %H:%M:%S", "%m/%d/%Y %H:%M")
_MISSING = {"", "n/a", "na", "none", "-"}


def _first_index(header: list[str], *prefixes: str) -> int | None:
    for index, name in enumerate(header):
        lowered = name.strip().lower()
        if any(lowered == p or lowered.startswith(p + " (") for p in prefixes):
            return index
    return None


def _unit(name: str) -> str:
    if "(" in name and name.endswith(")"):
        return name[name.rindex("(") + 1 : -1].strip().lower().lstrip("°")
    return ""


def _cell(row: list[str], index: int | None, where: str) -> float:
    if index is None or index >= len(row) or row[index].strip().lower() in _MISSING:
        return math.nan
    try:
        return float(row[index])
    except ValueError:
        raise InputError(f"{where}: {row[index]!r} is not a number") from None


def _parse_date(text: str, where: str) -> str:
    for pattern in _DATE_FORMATS:
        try:
            return datetime.strptime(text.strip(), pattern).isoformat(timespec="seconds")
        except ValueError:
            continue
    raise InputError(
        f"{where}: start date {text!r} not understood (expected e.g. 10/31/2025 11:51:49 AM)"
    )


def read_shearwater_csv(path: Path) -> list[DiveProfile]:
    """The one dive of a Shearwater Cloud CSV export."""
    rows = read_csv_rows(path, what="Shearwater Cloud CSV", encoding="utf-8-sig")
    if len(rows) < 3 or "Start Date" not in [c.strip() for c in rows[0]]:
        raise InputError(
            f"{path}:1: not a Shearwater Cloud CSV (expected a summary header with 'Start Date')"
        )
    summary_header = [c.strip() for c in rows[0]]
    summary: dict[str, str] = {}
    for name, value in zip(summary_header, rows[1], strict=False):
        summary.setdefault(name, value.strip())
    sample_header = [c.strip() for c in rows[2]]
    time_index = _first_index(sample_header, "time (sec)", "time")
    depth_index = _first_index(sample_header, "depth")
    temp_index = _first_index(sample_header, "water temp")
    if time_index is None or depth_index is None:
        raise InputError(f"{path}:3: sample header without 'Time (sec)' and 'Depth' columns")
    imperial_flag = summary.get("Imperial Units", "").lower() == "true"
    depth_unit = _unit(sample_header[depth_index])
    imperial_depth = depth_unit == "ft" or (depth_unit == "" and imperial_flag)
    temp_unit = "" if temp_index is None else _unit(sample_header[temp_index])
    imperial_temp = temp_unit == "f" or (temp_unit == "" and imperial_flag)
    start_iso = _parse_date(summary.get("Start Date", ""), f"{path}:2")
    offsets, depths, temps = [], [], []
    problems = SampleProblems()
    for line_no, row in enumerate(rows[3:], start=4):
        if not any(cell.strip() for cell in row):
            continue
        where = f"{path}:{line_no}"
        try:  # one odd line is skipped (with one warning for the file), not the dive
            offset = _cell(row, time_index, where)
            if math.isnan(offset):
                raise InputError(f"{where}: sample without a time")
            depth = _cell(row, depth_index, where)
            temp = _cell(row, temp_index, where)
        except InputError as error:
            problems.add(f"line {line_no}", str(error).removeprefix(f"{where}: "))
            continue
        offsets.append(offset)
        depths.append(depth * FEET_TO_M if imperial_depth else depth)
        temps.append((temp - 32.0) * 5.0 / 9.0 if imperial_temp else temp)
    if problems.count:
        log.warning(
            "%s: %d sample line%s skipped (first: %s)",
            path,
            problems.count,
            "" if problems.count == 1 else "s",
            problems.first,
        )
    if not offsets:
        detail = f" ({problems.first})" if problems.count else ""
        raise InputError(f"{path}: no readable sample line{detail}")
    product = summary.get("Product", "")
    return [
        make_profile(
            start_iso=start_iso,
            offsets_s=offsets,
            depth_m=depths,
            temperature_c=temps,
            model=f"Shearwater {product}".strip(),
            serial=summary.get("Computer Serial Number", ""),
            fingerprint=start_fingerprint(start_iso),
            source=f"import {path.name}",
            where=str(path),
        )
    ]
