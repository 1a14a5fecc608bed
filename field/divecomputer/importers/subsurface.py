"""Subsurface XML logbooks (.xml, .ssrf): every divecomputer entry of every dive.

Read as Subsurface reads its own files (core/parse-xml.cpp): `<divelog>` (or the
`<dives>` root of the first versions) holding `<dives>`, `<trip>` and `<dive>` at any
nesting; a value is an attribute or a child element of that name, in any letter case;
the start is the dive's (or its divecomputer's) `date` and `time`, or `datetime`; the
samples are `<sample time depth temp>` inside each `<divecomputer>`, or inside `<dive>`
in files older than divecomputers. Dates come unpadded (`2014-4-1`, `10:0:0`); values
carry their unit (`12.3 m`, `40 ft`, `15.0 C`, `59 F`, `288.15 K`).

Subsurface's first input is read too: libdivecomputer's XML dump, one or more top-level
`<dive>` elements with no root (so not well-formed XML as a whole), each with `<number>`,
`<datetime>2011-07-16 14:19:15</datetime>` and `<sample><time>00:20</time><depth>2.05
</depth><temperature>16.00</temperature></sample>` children. Every dive of the dump is read.

A dive without a date or without samples is skipped with a warning; a sample whose
time or depth cannot be read is skipped with one warning per dive. A temperature that
cannot be read (an empty `temp=' C'`) leaves its sample without one, as in Subsurface,
with one warning per dive.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from field.divecomputer.importers.common import (
    LogbookReading,
    SampleProblems,
    children,
    combine_date_time,
    depth_m_from_text,
    descendants,
    duration_s_from_text,
    field_text,
    local_name,
    make_profile,
    parse_xml,
    temperature_c_from_text,
)
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile

ROOTS = ("divelog", "dives")

# The prolog (declaration, processing instructions, comments, DOCTYPE) before the first
# element, and a first element <dive>: libdivecomputer's dump, read inside a <dives> root.
_PROLOG = re.compile(
    rb"(?:\xef\xbb\xbf)?(?:\s+|<\?.*?\?>|<!--.*?-->|<!DOCTYPE[^>]*>)*", re.DOTALL | re.IGNORECASE
)
_DIVE_START = re.compile(rb"<dive[\s>/]", re.IGNORECASE)
_HEAD_BYTES = 64 * 1024


def _parse_logbook(path: Path) -> Any:
    """The logbook's tree; a libdivecomputer dump (top-level <dive> elements) is read as
    the children of a <dives> root, as Subsurface's first parser read it."""
    try:
        with path.open("rb") as stream:
            head = stream.read(_HEAD_BYTES)
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from None
    start = _PROLOG.match(head)
    end = start.end() if start is not None else 0
    if _DIVE_START.match(head, end) is None:
        return parse_xml(path)
    data = path.read_bytes()
    return parse_xml(path, data[:end] + b"<dives>" + data[end:] + b"</dives>")


def _start_iso(element: Any, inherited: str | None) -> str | None:
    """The start written on `element` (date + time, or datetime), else `inherited`.

    Raises ValueError when a date is written but cannot be read.
    """
    combined = field_text(element, "datetime")
    date = field_text(element, "date")
    time = field_text(element, "time")
    if date is not None:
        return combine_date_time(date, time)
    if combined is not None:
        return combine_date_time(combined, None)
    if time is not None and inherited is not None:
        return combine_date_time(inherited.split("T")[0], time)
    return inherited


def _samples(
    computer: Any, problems: SampleProblems
) -> tuple[list[float], list[float], list[float]]:
    """(offsets s, depths m, temperatures degC) of the readable samples of `computer`."""
    offsets: list[float] = []
    depths: list[float] = []
    temps: list[float] = []
    for number, sample in enumerate(children(computer, "sample"), start=1):
        time_text = field_text(sample, "time") or field_text(sample, "sampletime")
        sample_where = f"sample at {time_text}" if time_text else f"sample {number}"
        try:
            if time_text is None:
                raise ValueError("no time (a sample without a time)")
            offset = duration_s_from_text(time_text)
            depth_text = field_text(sample, "depth")
            depth = float("nan") if depth_text is None else depth_m_from_text(depth_text)
        except ValueError as error:
            problems.add(sample_where, str(error))
            continue
        temp_text = field_text(sample, "temp") or field_text(sample, "temperature")
        try:
            temp = float("nan") if temp_text is None else temperature_c_from_text(temp_text)
        except ValueError as error:
            # Subsurface's temperature() reports a "strange temperature reading" and
            # leaves the sample without one: Subsurface's own CSV imports write an empty
            # reading with its unit (temp=' C' in the Poseidon MkVI import).
            problems.leave_out_value(sample_where, f"temperature: {error}")
            temp = float("nan")
        offsets.append(offset)
        depths.append(depth)
        temps.append(temp)
    return offsets, depths, temps


def _serials(root: Any) -> dict[tuple[str, str], str]:
    """(model, deviceid) -> serial from the <settings><divecomputerid> entries."""
    serials: dict[tuple[str, str], str] = {}
    for device in descendants(root, "divecomputerid"):
        model = field_text(device, "model") or ""
        deviceid = (field_text(device, "deviceid") or "").lower()
        serials[(model, deviceid)] = field_text(device, "serial") or ""
    return serials


def read_subsurface(path: Path) -> list[DiveProfile]:
    """Every divecomputer of every dive, in file order (trips included)."""
    root = _parse_logbook(path).getroot()
    if local_name(root.tag).lower() not in ROOTS:
        raise InputError(
            f"{path}: root element <{local_name(root.tag)}> (expected Subsurface's <divelog>)"
        )
    serials = _serials(root)
    reading = LogbookReading(path)
    dives = descendants(root, "dive")
    numbers = [field_text(dive, "number") for dive in dives]
    for dive_index, (dive, number) in enumerate(zip(dives, numbers, strict=True), start=1):
        # Dives are named by their number; by their place in the file when it has none or
        # shares it with another dive (hand-edited logbooks repeat numbers).
        if number is None:
            label = str(dive_index)
        elif numbers.count(number) == 1:
            label = number
        else:
            label = f"#{dive_index} (number {number})"
        where_dive = f"{path}: dive {label}"
        try:
            dive_start = _start_iso(dive, None)
        except ValueError as error:
            reading.skip(where_dive, str(error))
            continue
        computers = children(dive, "divecomputer")
        for dc_index, computer in enumerate(computers or [dive], start=1):
            where = f"{where_dive} divecomputer {dc_index}" if computers else where_dive
            try:
                start_iso = dive_start if computer is dive else _start_iso(computer, dive_start)
            except ValueError as error:
                reading.skip(where, str(error))
                continue
            if start_iso is None:
                reading.skip(where, "no date")
                continue
            problems = SampleProblems()
            offsets, depths, temps = _samples(computer, problems)
            reading.warn_samples(where, problems)
            if not offsets:
                reading.skip_unreadable(where, problems)
                continue
            model = field_text(computer, "model") or ""
            extradata = {
                (field_text(item, "key") or ""): (field_text(item, "value") or "")
                for item in children(computer, "extradata")
            }
            deviceid = (field_text(computer, "deviceid") or "").lower()
            serial = extradata.get("Serial") or serials.get((model, deviceid), "")
            reading.profiles.append(
                make_profile(
                    start_iso=start_iso,
                    offsets_s=offsets,
                    depth_m=depths,
                    temperature_c=temps,
                    model=model,
                    serial=serial,
                    fingerprint=(field_text(computer, "diveid") or "").upper() or None,
                    source=f"import {path.name}",
                    where=where,
                )
            )
    return reading.result(none_found="no <dive> in this Subsurface logbook")
