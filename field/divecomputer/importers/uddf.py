"""UDDF 2.x/3.x logbooks (Subsurface, Shearwater Cloud, other logbooks), with or without namespace.

UDDF is SI: depth in metres, time in seconds, temperature in kelvin. A dive's start is
its `informationbeforedive/datetime` (also spelled `2014-4-2 10:0:0` or
`20140402T100000`; the old `<date><year>...` and `<time><hour>...` parts are read too),
taken as the dive computer's wall clock: a zone suffix is dropped (Shearwater Cloud
writes local time with a 'Z'). Samples are `samples/waypoint` with `divetime`, `depth`
and `temperature`.

A `<dive>` without a start (some writers put a placeholder dive holding only a surface
interval beside the real one) or without samples is skipped with a warning that names
it; a waypoint that cannot be read is skipped with one warning per dive.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from field.divecomputer.importers.common import (
    LogbookReading,
    SampleProblems,
    WallClock,
    children,
    depth_m_from_text,
    descendants,
    duration_s_from_text,
    local_name,
    make_profile,
    parse_logbook_date,
    parse_xml,
    start_fingerprint,
    temperature_c_from_text,
)
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile


def _child(element: Any, *names: str) -> Any | None:
    current = element
    for name in names:
        found = children(current, name)
        if not found:
            return None
        current = found[0]
    return current


def _text(element: Any, *names: str) -> str | None:
    found = _child(element, *names)
    if found is None or found.text is None or not str(found.text).strip():
        return None
    return str(found.text).strip()


def _datetime_text(dive: Any) -> str | None:
    before = _child(dive, "informationbeforedive")
    if before is not None and _text(before, "datetime") is not None:
        return _text(before, "datetime")
    for element in descendants(dive, "datetime"):  # some writers put it elsewhere in the dive
        if element.text is not None and element.text.strip():
            return str(element.text).strip()
    return None


def _parts_start(dive: Any) -> WallClock | None:
    """The UDDF 2 spelling: <date><year/><month/><day/></date><time><hour/><minute/></time>."""
    date = next(iter(descendants(dive, "date")), None)
    if date is None:
        return None
    numbers = {}
    for name in ("year", "month", "day"):
        text = _text(date, name)
        if text is None or not text.isdigit():
            return None
        numbers[name] = int(text)
    time = next(iter(descendants(dive, "time")), None)
    hour = _text(time, "hour") if time is not None else None
    minute = _text(time, "minute") if time is not None else None
    return WallClock(
        numbers["year"],
        numbers["month"],
        numbers["day"],
        int(hour) if hour and hour.isdigit() else 0,
        int(minute) if minute and minute.isdigit() else 0,
    )


def _start_iso(dive: Any) -> str | None:
    """ISO start of the dive, None when it has none; ValueError when it cannot be read."""
    text = _datetime_text(dive)
    try:
        moment = parse_logbook_date(text) if text is not None else _parts_start(dive)
        return None if moment is None else moment.iso()
    except (ValueError, OverflowError):
        shown = repr(text[:80]) if text is not None else "in <date>/<time>"
        raise ValueError(f"datetime {shown} is not a date (expected y-m-dTh:m:s)") from None


def _number(text: str | None) -> float:
    if text is None or text == "":
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{text[:40]!r} is not a number") from None


def _waypoints(dive: Any, problems: SampleProblems) -> tuple[list[float], ...]:
    offsets: list[float] = []
    depths: list[float] = []
    temps: list[float] = []
    samples = _child(dive, "samples")
    for number, waypoint in enumerate(
        [] if samples is None else children(samples, "waypoint"), start=1
    ):
        where = f"waypoint {number}"
        try:
            time_text = _text(waypoint, "divetime")
            if time_text is None:
                raise ValueError("no divetime")
            offset = duration_s_from_text(time_text)
            depth_text = _text(waypoint, "depth")
            depth = math.nan if depth_text is None else depth_m_from_text(depth_text)
            temp_text = _text(waypoint, "temperature")
            temp = (
                math.nan if temp_text is None else temperature_c_from_text(temp_text, bare_unit="k")
            )
        except ValueError as error:
            problems.add(where, str(error))
            continue
        offsets.append(offset)
        depths.append(depth)
        temps.append(temp)
    return offsets, depths, temps


def _computers(root: Any) -> dict[str, tuple[str, str]]:
    computers: dict[str, tuple[str, str]] = {}
    for element in descendants(root, "divecomputer"):
        if element.get("id"):
            model = _text(element, "model") or _text(element, "name") or ""
            computers[element.get("id")] = (model, _text(element, "serialnumber") or "")
    return computers


def read_uddf(path: Path) -> list[DiveProfile]:
    """Every dive in the UDDF file, in file order."""
    root = parse_xml(path).getroot()
    if local_name(root.tag).lower() != "uddf":
        raise InputError(f"{path}: root element <{local_name(root.tag)}> (expected <uddf>)")
    generator = _text(root, "generator", "name") or ""
    shearwater = "shearwater" in generator.lower()
    computers = _computers(root)
    reading = LogbookReading(path)
    for index, dive in enumerate(descendants(root, "dive"), start=1):
        where = f"{path}: dive {dive.get('id') or index}"
        try:
            start_iso = _start_iso(dive)
        except ValueError as error:
            reading.skip(where, f"informationbeforedive/{error}")
            continue
        if start_iso is None:
            reading.skip(where, "no informationbeforedive/datetime")
            continue
        model, serial = generator, ""
        before = _child(dive, "informationbeforedive")
        if before is not None:
            used = _child(before, "equipmentused")
            links = [] if used is None else children(used, "link")
            for link in [*links, *children(before, "link")]:
                if link.get("ref") in computers:
                    model, serial = computers[link.get("ref")]
                    break
        problems = SampleProblems()
        offsets, depths, temps = _waypoints(dive, problems)
        reading.warn_samples(where, problems)
        if not offsets:
            reading.skip_unreadable(where, problems)
            continue
        fingerprint = start_fingerprint(start_iso) if shearwater else dive.get("id")
        if shearwater and model and not model.lower().startswith("shearwater"):
            model = f"Shearwater {model}"
        reading.profiles.append(
            make_profile(
                start_iso=start_iso,
                offsets_s=offsets,
                depth_m=depths,
                temperature_c=temps,
                model=model,
                serial=serial,
                fingerprint=fingerprint,
                source=f"import {path.name}",
                where=where,
            )
        )
    return reading.result(none_found="no <dive> in this UDDF file")
