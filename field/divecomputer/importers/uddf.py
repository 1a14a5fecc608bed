"""UDDF 3.x logbooks (Subsurface, Shearwater Cloud, other logbooks), with or without namespace.

UDDF is SI: depth in metres, time in seconds, temperature in kelvin. A dive's start is
its `informationbeforedive/datetime`, read as the dive computer's wall clock: a zone
suffix is dropped (Shearwater Cloud writes local time with a 'Z').
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from field.divecomputer.importers.common import (
    kelvin_to_c,
    local_name,
    make_profile,
    parse_xml,
    start_fingerprint,
)
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, iso_to_stamp_s


def _children(element: Any, name: str) -> list[Any]:
    return [child for child in element if local_name(child.tag) == name]


def _child(element: Any, *names: str) -> Any | None:
    current = element
    for name in names:
        found = _children(current, name)
        if not found:
            return None
        current = found[0]
    return current


def _text(element: Any, *names: str) -> str | None:
    found = _child(element, *names)
    if found is None or found.text is None:
        return None
    return str(found.text).strip()


def _number(text: str | None, where: str) -> float:
    if text is None or text == "":
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise InputError(f"{where}: {text!r} is not a number") from None


def _iso_wall_clock(text: str, where: str) -> str:
    body = text.strip()
    if body.endswith("Z"):
        body = body[:-1]
    elif len(body) > 19 and body[19] in "+-":
        body = body[:19]  # drop a zone offset: the computer's wall clock is what counts
    if "T" not in body:
        body = f"{body}T00:00:00"
    return body


def read_uddf(path: Path) -> list[DiveProfile]:
    """Every dive in the UDDF file, in file order."""
    root = parse_xml(path).getroot()
    if local_name(root.tag) != "uddf":
        raise InputError(f"{path}: root element <{local_name(root.tag)}> (expected <uddf>)")
    generator = _text(root, "generator", "name") or ""
    computers: dict[str, tuple[str, str]] = {}
    for element in root.iter():
        if local_name(element.tag) == "divecomputer" and element.get("id"):
            model = _text(element, "model") or _text(element, "name") or ""
            computers[element.get("id")] = (model, _text(element, "serialnumber") or "")
    profiles = []
    dives = [element for element in root.iter() if local_name(element.tag) == "dive"]
    for index, dive in enumerate(dives, start=1):
        where = f"{path}: dive {dive.get('id') or index}"
        before = _child(dive, "informationbeforedive")
        datetime_text = None if before is None else _text(before, "datetime")
        if datetime_text is None:
            raise InputError(f"{where}: no informationbeforedive/datetime")
        start_iso = _iso_wall_clock(datetime_text, where)
        try:
            iso_to_stamp_s(start_iso)  # checked here: the Shearwater fingerprint needs it
        except (ValueError, OverflowError):
            raise InputError(
                f"{where}: informationbeforedive/datetime {datetime_text[:80]!r} is not ISO 8601"
            ) from None
        model, serial = generator, ""
        if before is not None:
            used = _child(before, "equipmentused")
            links = [] if used is None else _children(used, "link")
            for link in [*links, *_children(before, "link")]:
                if link.get("ref") in computers:
                    model, serial = computers[link.get("ref")]
                    break
        offsets, depths, temps = [], [], []
        samples = _child(dive, "samples")
        for waypoint in [] if samples is None else _children(samples, "waypoint"):
            time_text = _text(waypoint, "divetime")
            sample_where = f"{where} waypoint {len(offsets) + 1}"
            if time_text is None:
                raise InputError(f"{sample_where}: no divetime")
            offsets.append(_number(time_text, sample_where))
            depths.append(_number(_text(waypoint, "depth"), sample_where))
            temps.append(kelvin_to_c(_number(_text(waypoint, "temperature"), sample_where)))
        shearwater = "shearwater" in generator.lower()
        fingerprint = start_fingerprint(start_iso) if shearwater else dive.get("id")
        if shearwater and model and not model.lower().startswith("shearwater"):
            model = f"Shearwater {model}"
        profiles.append(
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
    if not profiles:
        raise InputError(f"{path}: no <dive> in this UDDF file")
    return profiles
