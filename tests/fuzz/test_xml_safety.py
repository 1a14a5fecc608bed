"""Every XML entry point refuses entity expansion and external references (issue 14).

The logbook importers are the only XML readers of the project (parse_xml in
field/divecomputer/importers/common.py, used by the UDDF and Subsurface readers and
reached through read_logbook / import_logbook); each is tried with each payload.
"""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import pytest

from field.divecomputer.importers import import_logbook, read_logbook
from field.divecomputer.importers.common import parse_xml
from field.divecomputer.importers.subsurface import read_subsurface
from field.divecomputer.importers.uddf import read_uddf
from shared.errors import InputError

pytestmark = pytest.mark.timeout(60)

_LAUGHS = "".join(f'<!ENTITY lol{i} "{("&lol" + str(i - 1) + ";") * 10}">' for i in range(1, 10))
PAYLOADS = {
    "billion laughs": (
        f'<!DOCTYPE {{root}} [<!ENTITY lol0 "lol">{_LAUGHS}]>'
        "<{root}><dive><notes>&lol9;</notes></dive></{root}>"
    ),
    "quadratic blowup": (
        '<!DOCTYPE {root} [<!ENTITY a "' + "x" * 50_000 + '">]>'
        "<{root}>" + "&a;" * 2000 + "</{root}>"
    ),
    "external entity": (
        '<!DOCTYPE {root} [<!ENTITY secret SYSTEM "file:///etc/passwd">]>'
        "<{root}><dive>&secret;</dive></{root}>"
    ),
    "external parameter entity": (
        '<!DOCTYPE {root} [<!ENTITY % remote SYSTEM "http://127.0.0.1:9/x.dtd"> %remote;]><{root}/>'
    ),
    "internal entity": '<!DOCTYPE {root} [<!ENTITY e "3">]><{root}><dive>&e;</dive></{root}>',
}

ENTRY_POINTS: dict[str, tuple[str, str, Callable[[Path], object]]] = {
    "parse_xml": ("divelog", ".xml", parse_xml),
    "read_uddf": ("uddf", ".uddf", read_uddf),
    "read_subsurface": ("divelog", ".xml", read_subsurface),
    "read_logbook uddf": ("uddf", ".uddf", read_logbook),
    "read_logbook subsurface": ("divelog", ".ssrf", read_logbook),
    "read_logbook detected .xml": ("uddf", ".xml", read_logbook),
    "import_logbook": ("divelog", ".xml", lambda p: import_logbook(p, p.parent / "out")),
}


@pytest.mark.parametrize("payload", sorted(PAYLOADS))
@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_entities_are_refused(tmp_path: Path, entry: str, payload: str) -> None:
    root, suffix, call = ENTRY_POINTS[entry]
    path = tmp_path / f"hostile{suffix}"
    path.write_text(PAYLOADS[payload].replace("{root}", root), encoding="utf-8")
    tracemalloc.start()
    start = time.perf_counter()
    try:
        # (A root element beyond the first 4 kB is refused earlier, by format detection.)
        refusal = r"hostile\.\w+: (refused unsafe XML|XML that is neither)"
        with pytest.raises(InputError, match=refusal) as caught:
            call(path)
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    # A hang guard (an expanded entity bomb runs for minutes), not a speed check: a refusal
    # takes a fraction of a second even on a loaded machine; the memory limit is the real test.
    assert time.perf_counter() - start < 30.0
    assert peak < 8 << 20, f"peak {peak} bytes: the entity was expanded"
    assert "root:" not in str(caught.value)  # nothing of /etc/passwd leaked into the message
    assert not (tmp_path / "out").exists()


def test_plain_dtd_without_entities_is_still_read(tmp_path: Path, shared_data: Path) -> None:
    """Refusing entities must not refuse a logbook that merely has a DOCTYPE line."""
    text = (shared_data / "divelogs" / "ostc.xml").read_text(encoding="utf-8")
    declaration, body = text.split("\n", 1) if text.startswith("<?xml") else ("", text)
    path = tmp_path / "with-doctype.xml"
    path.write_text(f"{declaration}\n<!DOCTYPE divelog>\n{body}", encoding="utf-8")
    assert len(read_logbook(path)) == len(read_logbook(shared_data / "divelogs" / "ostc.xml"))
