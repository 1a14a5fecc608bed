"""Logbook importers: a registry from format name to a reader `Path -> list[DiveProfile]`."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path

from field.divecomputer.importers.shearwater_csv import read_shearwater_csv
from field.divecomputer.importers.subsurface import read_subsurface
from field.divecomputer.importers.uddf import read_uddf
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, dive_file_stem, read_dive_index, write_dive

log = logging.getLogger(__name__)

Reader = Callable[[Path], list[DiveProfile]]

IMPORTERS: dict[str, Reader] = {
    "subsurface": read_subsurface,
    "uddf": read_uddf,
    "shearwater-csv": read_shearwater_csv,
}


_HEAD_BYTES = 64 * 1024
# The first element's name, after the prolog (declaration, comments, DOCTYPE).
_FIRST_ELEMENT = re.compile(rb"<([A-Za-z_][\w.:-]*)")
_COMMENT_OR_PI = re.compile(rb"<!--.*?-->|<\?.*?\?>", re.DOTALL)
_DOCTYPE = re.compile(rb"<!DOCTYPE(?:[^\[>]*\[.*?\]\s*>|[^>]*>)", re.DOTALL | re.IGNORECASE)


def root_element(head: bytes) -> str | None:
    """The root element's local name in the first bytes of an XML file (None if not there)."""
    text = _COMMENT_OR_PI.sub(b"", head)
    text = _DOCTYPE.sub(b"", text)
    match = _FIRST_ELEMENT.search(text)
    if match is None:
        return None
    return match.group(1).decode("ascii", "replace").rsplit(":", 1)[-1]


def detect_format(path: Path) -> str:
    """The importer for `path`, from its suffix and, for .xml, its root element."""
    suffix = path.suffix.lower()
    if suffix == ".uddf":
        return "uddf"
    if suffix == ".ssrf":
        return "subsurface"
    if suffix == ".csv":
        return "shearwater-csv"
    if suffix == ".xml":
        try:
            with path.open("rb") as stream:
                head = stream.read(_HEAD_BYTES)
        except OSError as error:
            raise InputError(f"{path}: cannot read ({error.strerror})") from None
        root = root_element(head)
        if root is not None and root.lower() == "uddf":
            return "uddf"
        if root is not None and root.lower() in ("divelog", "dives", "dive"):
            return "subsurface"  # <dive>: libdivecomputer's dump, Subsurface's first input
        found = (
            f"root element <{root}>"
            if root is not None
            else f"no root element in the first {_HEAD_BYTES // 1024} kB"
        )
        raise InputError(
            f"{path}: XML that is neither Subsurface (<divelog>) nor UDDF (<uddf>) ({found}; "
            "not a dive log this importer reads)"
        )
    raise InputError(
        f"{path}: unknown logbook type {suffix or '(no suffix)'} "
        "(expected .xml/.ssrf Subsurface, .uddf/.xml UDDF or .csv Shearwater Cloud)"
    )


def read_logbook(path: Path | str, *, format_name: str | None = None) -> list[DiveProfile]:
    """Every dive (every dive computer of every dive) in a logbook file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such logbook file")
    name = format_name or detect_format(path)
    if name not in IMPORTERS:
        raise InputError(f"--format {name!r}: unknown (known: {', '.join(IMPORTERS)})")
    return IMPORTERS[name](path)


def import_logbook(
    path: Path | str, out_dir: Path | str, *, format_name: str | None = None
) -> list[Path]:
    """Write the logbook's dives into the dive folder `out_dir`; returns the new CSVs.

    The whole file is read and checked before anything is written: a file that cannot
    be imported leaves the dive folder exactly as it was (not even created). Dives
    already in the folder (same model, serial and fingerprint) are skipped, so an
    import can be repeated; a dive whose CSV name is taken by another dive is skipped
    with a warning rather than written over.
    """
    path = Path(path)
    out_dir = Path(out_dir)
    profiles = read_logbook(path, format_name=format_name)
    present = {
        (entry.get("model", ""), entry.get("serial", ""), entry.get("fingerprint", ""))
        for entry in read_dive_index(out_dir)
    }
    planned: list[DiveProfile] = []
    names: set[str] = set()
    for profile in profiles:
        key = (profile.model, profile.serial, profile.fingerprint)
        name = f"{dive_file_stem(profile)}.csv"
        if key in present:
            log.info("%s: dive %s already in %s", path, profile.fingerprint, out_dir)
            continue
        if name in names or (out_dir / name).exists():
            log.warning(
                "%s: dive %s (%s) skipped: %s is already taken by another dive",
                path,
                profile.fingerprint,
                profile.start_iso,
                out_dir / name,
            )
            continue
        planned.append(profile)
        present.add(key)
        names.add(name)
    return [write_dive(out_dir, profile) for profile in planned]
