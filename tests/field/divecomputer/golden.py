"""The golden session of ../shared/docs/shearwater-example-session.md, read from the doc."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

DOC = (
    Path(__file__).resolve().parents[3].parent / "shared" / "docs" / "shearwater-example-session.md"
)


@dataclass
class GoldenSession:
    dive_a: bytes
    dive_b: bytes
    manifest_prefix: bytes  # first 64 bytes of the page; the rest is FF
    trace: list[tuple[str, bytes, int | None]]  # (">>" or "<<", shown bytes, total if cut)
    block_a: bytes  # full wire frame of the compressed block of dive A
    block_b: bytes
    xml: str


def _hex(text: str) -> bytes:
    return bytes.fromhex(" ".join(re.findall(r"\b[0-9A-Fa-f]{2}\b", text)))


def _section(text: str, title: str) -> str:
    start = text.index(title)
    fence = text.index("```", start)
    end = text.index("```", fence + 3)
    return text[fence + 3 : end]


def _dump(block: str) -> bytes:
    out = bytearray()
    for line in block.strip().splitlines():
        body = line.split(";")[0]
        out += _hex(body.split(maxsplit=1)[1])  # drop the offset column
    return bytes(out)


def load() -> GoldenSession:
    if not DOC.is_file():
        raise FileNotFoundError(f"{DOC}: golden session doc missing")
    text = DOC.read_text(encoding="utf-8")
    manifest = _section(text, "## Manifest page")
    manifest_prefix = b"".join(_hex(line.split(";")[0]) for line in manifest.strip().splitlines())
    trace = []
    for line in _section(text, "### Packet trace").strip().splitlines():
        direction, rest = line[:2], line[3:]
        total = None
        if "..." in rest:
            rest, tail = rest.split("...", 1)
            wire = re.search(r"\((\d+) bytes on the wire\)", tail)
            assert wire is not None
            total = int(wire.group(1))
        trace.append((direction, _hex(rest), total))
    return GoldenSession(
        dive_a=_dump(_section(text, "### Dive A")),
        dive_b=_dump(_section(text, "### Dive B")),
        manifest_prefix=manifest_prefix,
        trace=trace,
        block_a=_hex(_section(text, "### Block 1 of the dive at 0x80020000")),
        block_b=_hex(_section(text, "### Block 1 of the dive at 0x80010000")),
        xml=_section(text, "## dctool XML output"),
    )
