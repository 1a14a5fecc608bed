"""What the logbook importers share: safe XML, the spellings logbooks use, building profiles.

The spellings follow what Subsurface's own reader (core/parse-xml.cpp) accepts, since
Subsurface writes most of the XML logbooks in the wild and reads back what it wrote:

* dates `2014-4-1` or `1.4.2014` (no zero padding), optionally followed by a time;
* times `10:0:0` or `10:00` (seconds optional);
* sample times `12:34 min`, `1:02:03` or plain seconds `754`;
* numbers with a unit after them (`12.3 m`, `15.0 C`, `1.013 bar`) and a decimal comma;
* temperatures outside -40..+70 degC are no reading (Subsurface drops them too).

One odd sample is skipped with a warning; one odd dive is skipped with a warning that
names it; only a file with nothing importable is refused, in one line naming the file.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, iso_to_stamp_s, stamp_s_to_iso

log = logging.getLogger("field.divecomputer.importers")

FEET_TO_M = 0.3048
# Subsurface ignores water temperatures outside this band (sensor garbage, unit mix-ups).
MIN_TEMPERATURE_C = -40.0
MAX_TEMPERATURE_C = 70.0


def parse_xml(path: Path, data: bytes | None = None) -> Any:
    """Parse `path` (or `data` read from it) with defusedxml: no DTD entities, no external
    references.

    Raises `InputError` naming the file for malformed XML and for entity declarations
    (billion laughs) or external entities, which a logbook never needs.
    """
    import xml.etree.ElementTree as ET

    import defusedxml
    import defusedxml.ElementTree as SafeET

    safe = {"forbid_dtd": False, "forbid_entities": True, "forbid_external": True}
    try:
        if data is not None:
            return ET.ElementTree(SafeET.fromstring(data, **safe))
        return SafeET.parse(path, **safe)
    except defusedxml.DefusedXmlException as error:
        raise InputError(
            f"{path}: refused unsafe XML ({type(error).__name__}: entity declarations and "
            "external references are not allowed in a logbook)"
        ) from None
    except ET.ParseError as error:
        line, column = error.position
        raise InputError(f"{path}:{line}:{column}: malformed XML ({error})") from None
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror})") from None


def local_name(tag: Any) -> str:
    """Tag without its `{namespace}` (UDDF files come with and without one)."""
    text = str(tag)
    return text.rsplit("}", 1)[-1]


def children(element: Any, name: str) -> list[Any]:
    """Direct children called `name` (any namespace, any letter case)."""
    wanted = name.lower()
    return [child for child in element if local_name(child.tag).lower() == wanted]


def descendants(element: Any, name: str) -> list[Any]:
    """Every element called `name` below `element` (any namespace, any letter case)."""
    wanted = name.lower()
    return [
        child
        for child in element.iter()
        if child is not element and local_name(child.tag).lower() == wanted
    ]


def field_text(element: Any, name: str) -> str | None:
    """The value `name` of `element`: an attribute, else a child element's text.

    Subsurface matches both spellings (`<sample time='1:00 min'/>` and
    `<sample><time>1:00 min</time></sample>`) and ignores letter case.
    """
    wanted = name.lower()
    for key, value in element.attrib.items():
        if local_name(key).lower() == wanted:
            return str(value).strip()
    for child in children(element, name):
        if child.text is not None and child.text.strip():
            return str(child.text).strip()
    return None


# ----------------------------------------------------------------------------- spellings

_QUANTITY = re.compile(
    r"^\s*([-+]?(?:\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z°%/]*)\s*$"
)


def parse_quantity(text: str) -> tuple[float, str]:
    """'12.3 m' -> (12.3, 'm'); '15,5 C' -> (15.5, 'c'); raises ValueError otherwise.

    The unit comes back in lower case without a degree sign; '' when there is none.
    """
    match = _QUANTITY.match(text)
    if match is None:
        raise ValueError(f"{text[:40]!r} is not a number with a unit")
    value = float(match.group(1).replace(",", "."))
    return value, match.group(2).lower().lstrip("°")


def depth_m_from_text(text: str) -> float:
    """A depth in metres from '12.3 m', '40 ft' or a bare number (metres)."""
    value, unit = parse_quantity(text)
    if unit in ("", "m"):
        depth = value
    elif unit in ("ft", "feet"):
        depth = value * FEET_TO_M
    else:
        raise ValueError(f"depth unit {unit!r} in {text[:40]!r} (expected m or ft)")
    if not math.isfinite(depth):
        raise ValueError(f"depth {text[:40]!r} is not a finite number")
    return depth


def temperature_c_from_text(text: str, *, bare_unit: str = "c") -> float:
    """A water temperature in degC from '15.0 C', '59 F', '288.15 K'; NaN when implausible.

    `bare_unit` is the unit of a number without one ('c' in Subsurface XML, 'k' in UDDF).
    """
    value, unit = parse_quantity(text)
    unit = unit or bare_unit
    if unit == "c":
        celsius = value
    elif unit == "f":
        celsius = (value - 32.0) * 5.0 / 9.0
    elif unit == "k":
        celsius = kelvin_to_c(value)
    else:
        raise ValueError(f"temperature unit {unit!r} in {text[:40]!r} (expected C, F or K)")
    if not MIN_TEMPERATURE_C <= celsius <= MAX_TEMPERATURE_C:  # NaN fails too
        return math.nan
    return celsius


def kelvin_to_c(kelvin: float) -> float:
    """Kelvin to degC through millikelvin, as Subsurface does (283.15 K is exactly 10.0)."""
    if not math.isfinite(kelvin):  # NaN stays NaN; round() cannot take an infinity
        return kelvin if math.isnan(kelvin) else kelvin - 273.15
    return (round(kelvin * 1000.0) - 273_150) / 1000.0


_CLOCK = re.compile(r"^\s*(\d+)\s*:\s*(\d+)(?:\s*:\s*(\d+(?:[.,]\d*)?))?")


def duration_s_from_text(text: str) -> float:
    """'12:34 min', '1:02:03', '754 s', '754' -> seconds (a bare number is seconds).

    A bare number with a 'min' unit ('30 min') is minutes; Subsurface itself always
    writes 'm:ss min'.
    """
    body = text.strip()
    if ":" in body:
        parts = body.split()[0].replace(",", ".").split(":")
        try:
            numbers = [float(part) for part in parts]
        except ValueError:
            raise ValueError(f"time {text[:40]!r} is not mm:ss") from None
        if len(numbers) > 3 or any(n < 0 or not math.isfinite(n) for n in numbers):
            raise ValueError(f"time {text[:40]!r} is not mm:ss or h:mm:ss")
        seconds = 0.0
        for number in numbers:
            seconds = seconds * 60.0 + number
        return seconds
    try:
        value, unit = parse_quantity(body)
    except ValueError:
        raise ValueError(f"time {text[:40]!r} is not mm:ss or seconds") from None
    scale = {"": 1.0, "s": 1.0, "sec": 1.0, "min": 60.0, "h": 3600.0}.get(unit)
    if scale is None or not math.isfinite(value):
        raise ValueError(f"time {text[:40]!r} is not mm:ss or seconds")
    return value * scale


_DATE_YMD = re.compile(r"^\s*(\d{1,4})-(\d{1,2})-(\d{1,2})")
_DATE_DMY = re.compile(r"^\s*(\d{1,2})\.(\d{1,2})\.(\d{1,4})")
_COMPACT = re.compile(r"^\s*(\d{4})(\d{2})(\d{2})(?:[T ](\d{2})(\d{2})(\d{2})?)?")


@dataclass(frozen=True)
class WallClock:
    """A wall-clock moment as a logbook spells it (no zone)."""

    year: int
    month: int
    day: int
    hour: int = 0
    minute: int = 0
    second: float = 0.0

    def iso(self) -> str:
        """ISO 8601 with no zone; raises ValueError for an impossible date or time."""
        whole = int(self.second)
        moment = datetime(self.year, self.month, self.day, self.hour, self.minute, whole)
        microseconds = round((self.second - whole) * 1e6)
        if microseconds:
            return moment.replace(microsecond=min(microseconds, 999_999)).isoformat()
        return moment.isoformat(timespec="seconds")


def _time_of_day(text: str) -> tuple[int, int, float] | None:
    match = _CLOCK.match(text)
    if match is None:
        return None
    second = float((match.group(3) or "0").replace(",", "."))
    return int(match.group(1)), int(match.group(2)), second


def parse_logbook_date(text: str) -> WallClock:
    """'2014-4-1', '2014-04-01 10:0:0', '1.4.2014', '20140401T100000' -> WallClock.

    A time after the date (space or 'T' between) is kept; a zone after it is ignored
    (dive computers keep local wall-clock time).
    """
    body = text.strip()
    for pattern, order in ((_DATE_YMD, "ymd"), (_DATE_DMY, "dmy")):
        match = pattern.match(body)
        if match is None:
            continue
        numbers = dict(zip(order, (int(g) for g in match.groups()), strict=True))
        rest = body[match.end() :].lstrip("T ")
        clock = _time_of_day(rest) if rest else None
        hour, minute, second = clock or (0, 0, 0.0)
        return WallClock(numbers["y"], numbers["m"], numbers["d"], hour, minute, second)
    match = _COMPACT.match(body)
    if match is not None:
        y, m, d, hh, mm, ss = match.groups()
        return WallClock(int(y), int(m), int(d), int(hh or 0), int(mm or 0), float(ss or 0))
    raise ValueError(f"date {text[:40]!r} is not y-m-d or d.m.y")


def combine_date_time(date_text: str, time_text: str | None) -> str:
    """ISO 8601 start from a logbook's date and (optional) time fields."""
    moment = parse_logbook_date(date_text)
    if time_text is not None:
        clock = _time_of_day(time_text)
        if clock is None:
            raise ValueError(f"time {time_text[:40]!r} is not h:m[:s]")
        moment = WallClock(moment.year, moment.month, moment.day, *clock)
    try:
        return moment.iso()
    except (ValueError, OverflowError) as error:
        raise ValueError(
            f"no such date or time {date_text[:40]!r} {time_text or ''} ({error})"
        ) from None


# ----------------------------------------------------------------------------- collecting


@dataclass
class SampleProblems:
    """Samples of one dive that were skipped, and values left out of samples that were
    kept, for one warning each per dive."""

    count: int = 0
    first: str = ""
    values_left_out: int = 0
    first_value: str = ""

    def add(self, where: str, reason: str) -> None:
        """Count one skipped sample; the first reason is kept for the warning."""
        if self.count == 0:
            self.first = f"{where}: {reason}"
        self.count += 1

    def leave_out_value(self, where: str, reason: str) -> None:
        """Count one value read as absent in a sample that is kept (its time and depth
        were read); the first reason is kept for the warning."""
        if self.values_left_out == 0:
            self.first_value = f"{where}: {reason}"
        self.values_left_out += 1


@dataclass
class LogbookReading:
    """Dives read from one logbook file, and the dives skipped on the way (with why)."""

    path: Path
    profiles: list[DiveProfile] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def skip(self, where: str, reason: str) -> None:
        """Skip one dive with a warning that names it; the file's other dives go on."""
        log.warning("%s: skipped (%s)", where, reason)
        self.skipped.append((where, reason))

    def skip_unreadable(self, where: str, problems: SampleProblems) -> None:
        """Skip a dive with no sample at all, or none that could be read."""
        if problems.count:
            self.skip(where, f"no readable sample; first: {problems.first}")
        else:
            self.skip(where, "no samples")

    def warn_samples(self, where: str, problems: SampleProblems) -> None:
        """One warning for the samples of a dive that could not be read, one for the
        values left out of samples that were kept."""
        if problems.count:
            log.warning(
                "%s: %d sample%s skipped (first: %s)",
                where,
                problems.count,
                "" if problems.count == 1 else "s",
                problems.first,
            )
        if problems.values_left_out:
            log.warning(
                "%s: %d sample value%s unreadable, the samples kept without %s (first: %s)",
                where,
                problems.values_left_out,
                "" if problems.values_left_out == 1 else "s",
                "it" if problems.values_left_out == 1 else "them",
                problems.first_value,
            )

    def result(self, *, none_found: str) -> list[DiveProfile]:
        """The dives, or an InputError when the file had nothing importable."""
        if self.profiles:
            _separate_shared_ids(self.path, self.profiles)
            return self.profiles
        if self.skipped:
            where, reason = self.skipped[0]
            where = where.removeprefix(f"{self.path}: ")
            others = len(self.skipped) - 1
            more = f"; {others} more dive{'s' if others > 1 else ''} skipped" if others else ""
            raise InputError(f"{self.path}: no importable dive ({where}: {reason}{more})")
        raise InputError(f"{self.path}: {none_found}")


def _separate_shared_ids(path: Path, profiles: list[DiveProfile]) -> None:
    """Give dives that share a logbook id but start at different times ids of their own.

    A logbook's dive id (Subsurface's `diveid`, a UDDF `id`) is meant to name one dive,
    but hand-made and converted files repeat it; the dive folder tells dives apart by
    model, serial and id, so such dives would be taken for one dive imported twice.
    """
    starts: dict[tuple[str, str, str], set[str]] = {}
    for profile in profiles:
        key = (profile.model, profile.serial, profile.fingerprint)
        starts.setdefault(key, set()).add(profile.start_iso)
    for profile in profiles:
        key = (profile.model, profile.serial, profile.fingerprint)
        if len(starts[key]) > 1:
            own = content_fingerprint(
                profile.start_iso,
                profile.model,
                profile.serial,
                profile.stamps_s.size,
                float(np.nansum(profile.depth_m)),
            )
            log.info(
                "%s: dive id %s names dives at %d different starts; the one at %s is %s",
                path,
                profile.fingerprint,
                len(starts[key]),
                profile.start_iso,
                own,
            )
            profile.fingerprint = own


def regular_interval_s(stamps_s: Sequence[float]) -> float | None:
    """The sample interval when at least 80 % of the steps share one value, else None."""
    steps = [round(b - a, 6) for a, b in itertools.pairwise(stamps_s)]
    if not steps:
        return None
    step, count = Counter(steps).most_common(1)[0]
    return float(step) if step > 0 and count >= 0.8 * len(steps) else None


def content_fingerprint(*parts: object) -> str:
    """8 hex digits identifying a dive without a fingerprint of its own."""
    digest = hashlib.sha1("\x1f".join(str(p) for p in parts).encode("utf-8")).hexdigest()
    return digest[:8].upper()


def start_fingerprint(start_iso: str) -> str:
    """The Shearwater fingerprint: the start time (wall clock as UTC), 8 hex digits."""
    return f"{int(iso_to_stamp_s(start_iso)) & 0xFFFFFFFF:08X}"


def make_profile(
    *,
    start_iso: str,
    offsets_s: Sequence[float],
    depth_m: Sequence[float],
    temperature_c: Sequence[float],
    model: str,
    serial: str,
    fingerprint: str | None,
    source: str,
    where: str,
) -> DiveProfile:
    """A DiveProfile from sample offsets (seconds after the start) on the dive's clock."""
    try:
        start_s = iso_to_stamp_s(start_iso)
    except (ValueError, OverflowError):
        raise InputError(f"{where}: start time {start_iso!r} is not ISO 8601") from None
    order = np.argsort(np.asarray(offsets_s, dtype=np.float64), kind="stable")
    offsets = np.asarray(offsets_s, dtype=np.float64)[order]
    stamps = start_s + offsets
    depths = np.asarray(depth_m, dtype=np.float64)[order]
    temps = np.asarray(temperature_c, dtype=np.float64)[order]
    start_text = stamp_s_to_iso(start_s)
    return DiveProfile(
        stamps_s=stamps,
        depth_m=depths,
        temperature_c=temps,
        start_iso=start_text,
        model=model,
        serial=serial,
        fingerprint=fingerprint
        or content_fingerprint(start_text, model, serial, len(offsets), float(np.nansum(depths))),
        source=source,
        sample_interval_s=regular_interval_s([float(o) for o in offsets]),
    )
