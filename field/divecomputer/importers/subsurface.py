"""Subsurface XML logbooks (.xml, .ssrf): every divecomputer entry of every dive."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from field.divecomputer.importers.common import (
    kelvin_to_c,
    local_name,
    make_profile,
    parse_xml,
)
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile

FEET_TO_M = 0.3048
_NUMBER = re.compile(r"^\s*([-+]?\d+(?:\.\d*)?|[-+]?\.\d+)\s*([A-Za-z°]*)\s*$")


def _quantity(text: str | None, where: str) -> tuple[float, str]:
    if text is None:
        return math.nan, ""
    match = _NUMBER.match(text)
    if match is None:
        raise InputError(f"{where}: {text!r} is not a number with a unit")
    return float(match.group(1)), match.group(2).lower()


def _depth_m(text: str | None, where: str) -> float:
    value, unit = _quantity(text, where)
    if unit in ("", "m"):
        return value
    if unit == "ft":
        return value * FEET_TO_M
    raise InputError(f"{where}: depth unit {unit!r} (expected m or ft)")


def _temperature_c(text: str | None, where: str) -> float:
    value, unit = _quantity(text, where)
    if unit in ("", "c", "°c"):
        return value
    if unit in ("f", "°f"):
        return (value - 32.0) * 5.0 / 9.0
    if unit == "k":
        return kelvin_to_c(value)
    raise InputError(f"{where}: temperature unit {unit!r} (expected C, F or K)")


def _time_s(text: str | None, where: str) -> float:
    """'12:34 min', '1:02:03', '754 s', '754' -> seconds."""
    if text is None:
        raise InputError(f"{where}: sample without a time")
    body = text.strip()
    for suffix in (" min", "min", " s", "s"):
        if body.endswith(suffix):
            body = body[: -len(suffix)].strip()
            break
    try:
        parts = [float(part) for part in body.split(":")]
    except ValueError:
        raise InputError(f"{where}: time {text!r} is not mm:ss") from None
    if len(parts) == 1:
        return parts[0] * (60.0 if text.strip().endswith("min") else 1.0)
    seconds = 0.0
    for part in parts:
        seconds = seconds * 60.0 + part
    return seconds


def _start(element: Any, fallback: tuple[str | None, str | None]) -> tuple[str | None, str | None]:
    date = element.get("date") or fallback[0]
    time = element.get("time") or fallback[1]
    return date, time


def read_subsurface(path: Path) -> list[DiveProfile]:
    """Every divecomputer of every dive, in file order (trips included)."""
    root = parse_xml(path).getroot()
    if local_name(root.tag) != "divelog":
        raise InputError(
            f"{path}: root element <{local_name(root.tag)}> (expected Subsurface's <divelog>)"
        )
    serials: dict[tuple[str, str], str] = {}
    for device in root.iter("divecomputerid"):
        serials[(device.get("model", ""), device.get("deviceid", ""))] = device.get("serial", "")
    profiles = []
    for dive_index, dive in enumerate(root.iter("dive"), start=1):
        where_dive = f"{path}: dive {dive.get('number', dive_index)}"
        computers = dive.findall("divecomputer") or [dive]  # very old files: samples in <dive>
        for dc_index, computer in enumerate(computers, start=1):
            where = f"{where_dive} divecomputer {dc_index}"
            date, time = _start(computer, _start(dive, (None, None)))
            if date is None:
                raise InputError(f"{where}: no date")
            start_iso = f"{date}T{time or '00:00:00'}"
            offsets, depths, temps = [], [], []
            for sample in computer.findall("sample"):
                sample_where = f"{where} sample at {sample.get('time')}"
                offsets.append(_time_s(sample.get("time"), sample_where))
                depths.append(_depth_m(sample.get("depth"), sample_where))
                temps.append(_temperature_c(sample.get("temp"), sample_where))
            model = computer.get("model", "")
            extradata = {
                item.get("key", ""): item.get("value", "") for item in computer.findall("extradata")
            }
            serial = extradata.get("Serial") or serials.get(
                (model, computer.get("deviceid", "")), ""
            )
            profiles.append(
                make_profile(
                    start_iso=start_iso,
                    offsets_s=offsets,
                    depth_m=depths,
                    temperature_c=temps,
                    model=model,
                    serial=serial,
                    fingerprint=(computer.get("diveid") or "").upper() or None,
                    source=f"import {path.name}",
                    where=where,
                )
            )
    if not profiles:
        raise InputError(f"{path}: no <dive> in this Subsurface logbook")
    return profiles
