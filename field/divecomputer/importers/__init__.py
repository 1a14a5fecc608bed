"""Logbook importers: a registry from format name to a reader `Path -> list[DiveProfile]`."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from field.divecomputer.importers.shearwater_csv import read_shearwater_csv
from field.divecomputer.importers.subsurface import read_subsurface
from field.divecomputer.importers.uddf import read_uddf
from shared.errors import InputError
from shared.formats.diveprofile import DiveProfile, read_dive_index, write_dive

log = logging.getLogger(__name__)

Reader = Callable[[Path], list[DiveProfile]]

IMPORTERS: dict[str, Reader] = {
    "subsurface": read_subsurface,
    "uddf": read_uddf,
    "shearwater-csv": read_shearwater_csv,
}


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
                head = stream.read(4096).lower()
        except OSError as error:
            raise InputError(f"{path}: cannot read ({error.strerror})") from None
        if b"<uddf" in head:
            return "uddf"
        if b"<divelog" in head:
            return "subsurface"
        raise InputError(f"{path}: XML that is neither Subsurface (<divelog>) nor UDDF (<uddf>)")
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

    Dives already in the folder (same model, serial and fingerprint) are skipped, so an
    import can be repeated.
    """
    out_dir = Path(out_dir)
    profiles = read_logbook(path, format_name=format_name)
    present = {
        (entry.get("model", ""), entry.get("serial", ""), entry.get("fingerprint", ""))
        for entry in read_dive_index(out_dir)
    }
    written = []
    for profile in profiles:
        key = (profile.model, profile.serial, profile.fingerprint)
        if key in present:
            log.info("%s: dive %s already in %s", path, profile.fingerprint, out_dir)
            continue
        written.append(write_dive(out_dir, profile))
        present.add(key)
    return written
