"""What the logbook importers share: safe XML parsing and building a DiveProfile."""

from __future__ import annotations

import hashlib
import itertools
import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, iso_to_stamp_s, stamp_s_to_iso


def parse_xml(path: Path) -> Any:
    """Parse `path` with defusedxml: no DTD entities, no external references.

    Raises `InputError` naming the file for malformed XML and for entity declarations
    (billion laughs) or external entities, which a logbook never needs.
    """
    import xml.etree.ElementTree as ET

    import defusedxml
    import defusedxml.ElementTree as SafeET

    try:
        return SafeET.parse(path, forbid_dtd=False, forbid_entities=True, forbid_external=True)
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


def kelvin_to_c(kelvin: float) -> float:
    # UDDF stores kelvin; go through millikelvin as Subsurface does, so 283.15 K is 10.0.
    if not math.isfinite(kelvin):  # NaN stays NaN; round() cannot take an infinity
        return kelvin if math.isnan(kelvin) else kelvin - 273.15
    return (round(kelvin * 1000.0) - 273_150) / 1000.0
