"""Structure-aware mutations: each takes a seeded `random.Random` and a valid input and
returns a damaged copy that is still close enough to the format to reach deep code.

Byte formats mutate the length, type and count fields they know about (MP4 box sizes
and table counts, GPMF KLV headers, MCAP record lengths, PNF records); text formats
mutate their structure (XML elements and attributes, CSV rows and cells, YAML/JSON
values) and then, sometimes, their bytes.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import random
import struct
import xml.etree.ElementTree as ET
from collections.abc import Callable
from typing import Any

import yaml

# Values that break length and count arithmetic (0, off-by-one, sign bits, 4 GB...).
INTERESTING_U32 = (
    0, 1, 2, 3, 4, 7, 8, 9, 15, 16, 255, 256, 0x7FFF, 0x8000, 0xFFFF, 0x10000,
    0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF,
)  # fmt: skip
INTERESTING_U64 = (*INTERESTING_U32, 0x100000000, 0x7FFFFFFFFFFFFFFF, 0xFFFFFFFFFFFFFFFF)
# Text that number parsers meet in damaged files.
WEIRD_NUMBERS = (
    "", " ", "nan", "NaN", "inf", "-inf", "Infinity", "1e999", "-1e999", "1e308", "1e-400",
    "0", "-0", "-1", "0x10", "1_000", "١٢", "²", "9" * 40, "9" * 400, "1e18", "1e20",
    "-9223372036854775809", "18446744073709551616", "12:34", "1:2:3:4", "12:xx min",
    "3 m", "3 ft", "3 furlong", "300 K", "1e999 K", "-40 F", "1.2.3", "--1", "+", ".",
    "\x00", "\u202e12", "9999-99-99T99:99:99", "2024-02-30T10:00:00", "0001-01-01T00:00:00",
    "9999-12-31T23:59:59", "10/31/2025 11:51:49 PM", "99/99/9999 99:99:99 AM",
)  # fmt: skip


def pick(rng: random.Random, values: tuple[Any, ...] | list[Any]) -> Any:
    return values[rng.randrange(len(values))]


# ------------------------------------------------------------------------------- raw bytes


def mutate_bytes(rng: random.Random, data: bytes, *, rounds: int = 1) -> bytes:
    """Classic havoc mutations: flips, interesting integers, truncation, splices."""
    out = bytearray(data)
    for _ in range(rounds):
        op = rng.randrange(8)
        if not out:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 16)))
            continue
        pos = rng.randrange(len(out))
        if op == 0:
            out[pos] ^= 1 << rng.randrange(8)
        elif op == 1:
            out[pos] = pick(rng, (0, 1, 0x7F, 0x80, 0xFF, 0xC0, 0xDB, 0x3C, 0x22))
        elif op == 2:
            width, fmt = pick(rng, ((2, ">H"), (4, ">I"), (4, "<I"), (8, "<Q"), (8, ">Q")))
            value = pick(rng, INTERESTING_U64) & ((1 << (8 * width)) - 1)
            out[pos : pos + width] = struct.pack(fmt, value)
        elif op == 3:
            del out[rng.randrange(len(out)) :]
        elif op == 4:
            end = min(len(out), pos + rng.randrange(1, 64))
            del out[pos:end]
        elif op == 5:
            end = min(len(out), pos + rng.randrange(1, 64))
            out[pos:pos] = out[pos:end] * rng.randrange(1, 4)
        elif op == 6:
            out[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 9)))
        else:
            for _ in range(rng.randrange(1, 9)):
                out[rng.randrange(len(out))] = rng.randrange(256)
    return bytes(out)


def mutate_overwrite(rng: random.Random, data: bytes) -> bytes:
    """Overwrites and one cut only (no shifts), so a big file's mutation is a small patch."""
    out = bytearray(data)
    for _ in range(rng.randrange(1, 8)):
        pos = rng.randrange(len(out))
        op = rng.randrange(5)
        if op == 0:
            out[pos] ^= 1 << rng.randrange(8)
        elif op == 1:
            out[pos] = pick(rng, (0, 1, 0x7F, 0x80, 0xFF))
        elif op == 2:
            value = pick(rng, INTERESTING_U32)
            out[pos : pos + 4] = struct.pack(">I", value)[: len(out) - pos]
        elif op == 3:
            # A GPMF-looking or start-code-looking marker where the scanner looks for them.
            marker = pick(rng, (b"DEVC", b"\x00\x00\x00\x01", b"\x00\x00\x01", b"\x00\x00\x00\x09"))
            out[pos : pos + len(marker)] = marker[: len(out) - pos]
        else:
            del out[rng.randrange(len(out) // 2, len(out)) :]
        if not out:
            break
    return bytes(out)


def _set_uint(out: bytearray, pos: int, width: int, rng: random.Random, old: int) -> None:
    fmt = {1: ">B", 2: ">H", 4: ">I", 8: ">Q"}[width]
    choices = [v for v in INTERESTING_U64 if v < 1 << (8 * width)]
    choices += [max(old - 1, 0), min(old + 1, (1 << (8 * width)) - 1), old * 2 % (1 << (8 * width))]
    struct.pack_into(fmt, out, pos, pick(rng, choices))


# ------------------------------------------------------------------------------------ GPMF


def gpmf_headers(data: bytes, base: int = 0, depth: int = 0) -> list[tuple[int, int, int]]:
    """(offset, struct_size, repeat) of every KLV header of a valid payload, nests included."""
    found: list[tuple[int, int, int]] = []
    pos = 0
    while pos + 8 <= len(data) and depth < 8:
        key, type_char, size, repeat = struct.unpack_from(">4scBH", data, pos)
        if key == b"\x00\x00\x00\x00":
            break
        length = size * repeat
        found.append((base + pos, size, repeat))
        if type_char == b"\x00":
            found += gpmf_headers(data[pos + 8 : pos + 8 + length], base + pos + 8, depth + 1)
        pos += 8 + ((length + 3) & ~3)
    return found


GPMF_TYPES = b"bBcdfFGjJlLqQsSuU?#\x00xZ"
_KEY_TEXT = "DEVC STRM SCAL TYPE TSMP STMP SIUN ORIN ORIO MTRX TMPC ACCL GYRO CORI DVID STNM"
GPMF_KEYS = (*(key.encode() for key in _KEY_TEXT.split(" ")), b"\x00\x00\x00\x00")


def mutate_gpmf(rng: random.Random, data: bytes) -> bytes:
    """Mutate KLV headers (key, type, structure size, repeat) or value bytes of a payload."""
    headers = gpmf_headers(data)
    out = bytearray(data)
    for _ in range(rng.randrange(1, 4)):
        if not headers or rng.random() < 0.2:
            return mutate_bytes(rng, bytes(out), rounds=rng.randrange(1, 4))
        offset, size, repeat = pick(rng, headers)
        field = rng.randrange(6)
        if field == 0:
            out[offset : offset + 4] = pick(rng, GPMF_KEYS)
        elif field == 1:
            out[offset + 4] = pick(rng, tuple(GPMF_TYPES))
        elif field == 2:
            out[offset + 5] = pick(rng, (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 255, size + 1))
        elif field == 3:
            _set_uint(out, offset + 6, 2, rng, repeat)
        elif field == 4 and size * repeat:
            value_pos = offset + 8 + rng.randrange(size * repeat)
            if value_pos < len(out):
                out[value_pos] = rng.randrange(256)
        else:
            del out[offset + rng.randrange(1, 12) :]
            headers = [h for h in headers if h[0] + 8 <= len(out)]
    return bytes(out)


# ------------------------------------------------------------------------------------- MP4

MP4_CONTAINERS = {b"moov", b"trak", b"mdia", b"minf", b"stbl", b"edts", b"dinf", b"udta"}
# Full boxes whose body is version/flags then a run of u32 fields (counts, sizes, deltas).
MP4_TABLES = {b"stsz", b"stz2", b"stts", b"ctts", b"stsc", b"stco", b"co64", b"stss", b"elst",
              b"mdhd", b"mvhd", b"tkhd", b"hdlr", b"stsd"}  # fmt: skip
MP4_TYPES = (b"moov", b"mdat", b"trak", b"stbl", b"stco", b"co64", b"stsz", b"stts", b"free",
             b"udta", b"mdhd", b"\x00\x00\x00\x00", b"ftyp")  # fmt: skip


def mp4_boxes(data: bytes, start: int = 0, end: int | None = None) -> list[tuple[int, int, bytes]]:
    """(offset, size, type) of every box of a valid file, containers walked."""
    end = len(data) if end is None else end
    found: list[tuple[int, int, bytes]] = []
    pos = start
    while pos + 8 <= end:
        size, box_type = struct.unpack_from(">I4s", data, pos)
        header = 8
        if size == 1:
            size = struct.unpack_from(">Q", data, pos + 8)[0]
            header = 16
        elif size == 0:
            size = end - pos
        if size < header or pos + size > end:
            break
        found.append((pos, size, box_type))
        if box_type in MP4_CONTAINERS:
            found += mp4_boxes(data, pos + header, pos + size)
        pos += size
    return found


def mutate_mp4(rng: random.Random, data: bytes, boxes: list[tuple[int, int, bytes]]) -> bytes:
    """Mutate box sizes/types, table fields of the sample tables, or truncate at a box."""
    out = bytearray(data)
    inner = [b for b in boxes if b[2] != b"mdat"]
    for _ in range(rng.randrange(1, 3)):
        offset, size, _ = pick(rng, inner)
        op = rng.randrange(10)
        if op in (0, 1):
            _set_uint(out, offset, 4, rng, size)
        elif op == 2:
            out[offset + 4 : offset + 8] = pick(rng, MP4_TYPES)
        elif op == 3:
            struct.pack_into(">I", out, offset, 1)  # 64-bit size follows (overwrites payload)
            struct.pack_into(">Q", out, offset + 8, pick(rng, INTERESTING_U64))
        elif op == 4:
            cut = offset + rng.randrange(0, max(size, 1))
            return bytes(out[:cut])
        elif op in (5, 6, 7, 8):
            tables = [b for b in boxes if b[2] in MP4_TABLES] or inner
            offset, size, _ = pick(rng, tables)
            fields = max((size - 8) // 4, 1)
            pos = offset + 8 + 4 * rng.randrange(min(fields, 12))
            if pos + 4 <= len(out):
                _set_uint(out, pos, 4, rng, struct.unpack_from(">I", out, pos)[0])
        else:
            pos = offset + rng.randrange(max(size, 1))
            if pos < len(out):
                out[pos] = rng.randrange(256)
    return bytes(out)


# ------------------------------------------------------------------------------------- XML


def _elements(root: ET.Element) -> list[tuple[ET.Element | None, ET.Element]]:
    pairs: list[tuple[ET.Element | None, ET.Element]] = [(None, root)]
    for parent in root.iter():
        pairs += [(parent, child) for child in parent]
    return pairs


def mutate_xml(rng: random.Random, data: bytes) -> bytes:
    """Delete, duplicate or rename elements; set attributes and text to weird values."""
    root = ET.fromstring(data)
    for _ in range(rng.randrange(1, 5)):
        pairs = _elements(root)
        parent, element = pick(rng, pairs)
        op = rng.randrange(7)
        if op == 0 and parent is not None:
            parent.remove(element)
        elif op == 1 and parent is not None:
            parent.insert(list(parent).index(element), copy.deepcopy(element))
        elif op == 2:
            element.tag = pick(rng, ("dive", "sample", "waypoint", "divetime", "x", root.tag))
        elif op == 3 and element.attrib:
            name = pick(rng, sorted(element.attrib))
            if rng.random() < 0.2:
                del element.attrib[name]
            else:
                element.set(name, pick(rng, WEIRD_NUMBERS))
        elif op == 4:
            element.text = pick(rng, WEIRD_NUMBERS)
        elif op == 5:
            # Numbers in the file (depths, times) are what parsers convert: hit those.
            leaves = [e for _, e in pairs if e.text and e.text.strip()[:1].isdigit()]
            leaves += [e for _, e in pairs if any(v[:1].isdigit() for v in e.attrib.values())]
            if leaves:
                target = pick(rng, leaves)
                if target.attrib and rng.random() < 0.5:
                    target.set(pick(rng, sorted(target.attrib)), pick(rng, WEIRD_NUMBERS))
                else:
                    target.text = pick(rng, WEIRD_NUMBERS)
        else:
            element.set(
                pick(rng, ("time", "depth", "temp", "date", "id")), pick(rng, WEIRD_NUMBERS)
            )
    text: bytes = ET.tostring(root, encoding="utf-8")
    if rng.random() < 0.15:
        text = mutate_bytes(rng, text, rounds=rng.randrange(1, 3))
    return text


# ------------------------------------------------------------------------------ CSV / lines


def mutate_table(rng: random.Random, data: bytes, *, delimiter: str = ",") -> bytes:
    """Mutate rows and cells of a delimited text table (CSV, TUM)."""
    text = data.decode("utf-8", errors="replace")
    if delimiter == ",":
        rows = list(csv.reader(io.StringIO(text)))
    else:
        rows = [line.split(delimiter) for line in text.splitlines()]
    for _ in range(rng.randrange(1, 5)):
        if not rows:
            rows.append([pick(rng, WEIRD_NUMBERS)])
            continue
        r = rng.randrange(len(rows))
        op = rng.randrange(8)
        if op <= 3 and rows[r]:
            rows[r][rng.randrange(len(rows[r]))] = pick(rng, WEIRD_NUMBERS)
        elif op == 4:
            del rows[r]
        elif op == 5:
            rows.insert(r, list(rows[rng.randrange(len(rows))]))
        elif op == 6 and rows[r]:
            if rng.random() < 0.5:
                del rows[r][rng.randrange(len(rows[r]))]
            else:
                rows[r].append(pick(rng, WEIRD_NUMBERS))
        else:
            rows[r] = [
                cell.replace(".", ",", 1) if rng.random() < 0.3 else cell for cell in rows[r]
            ]
    if delimiter == ",":
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="\n").writerows(rows)
        out = buffer.getvalue().encode("utf-8")
    else:
        out = "\n".join(delimiter.join(row) for row in rows).encode("utf-8") + b"\n"
    if rng.random() < 0.15:
        out = mutate_bytes(rng, out, rounds=rng.randrange(1, 3))
    return out


# ---------------------------------------------------------------------------- YAML / JSON

WEIRD_VALUES: tuple[Any, ...] = (
    None, True, 0, -1, 10**400, -(10**30), 1e308, float("nan"), float("inf"), "", "x", "1e-05",
    "nan", [], [1, 2], [[1, 2, 3, 4]] * 4, {}, {"a": 1}, [[[[[[[[[[1]]]]]]]]]], 2**64, 1.5,
)  # fmt: skip


def _containers(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, Any]]:
    """(container, key) for every value of a YAML/JSON tree."""
    found: list[tuple[Any, Any]] = []
    if isinstance(node, dict):
        for key in list(node):
            found.append((node, key))
            found += _containers(node[key], (*path, key))
    elif isinstance(node, list):
        for index in range(len(node)):
            found.append((node, index))
            found += _containers(node[index], (*path, index))
    return found


def mutate_tree(rng: random.Random, tree: Any) -> Any:
    tree = copy.deepcopy(tree)
    for _ in range(rng.randrange(1, 4)):
        slots = _containers(tree)
        if not slots:
            return pick(rng, WEIRD_VALUES)
        container, key = pick(rng, slots)
        op = rng.randrange(5)
        if op == 0:
            del container[key]
        elif op == 1 and isinstance(container[key], (int, float)) and rng.random() < 0.7:
            container[key] = pick(rng, (10**400, 1e308, -1e308, float("nan"), float("inf"),
                                        -1, 0, 2**63, 10**19, 1e-320))  # fmt: skip
        else:
            container[key] = copy.deepcopy(pick(rng, WEIRD_VALUES))
    return tree


def _yaml_safe(value: Any) -> Any:
    return value


def mutate_yaml(rng: random.Random, data: bytes) -> bytes:
    """Replace, delete or retype values of a YAML document; sometimes damage the text."""
    text = data.decode("utf-8")
    if rng.random() < 0.2:
        return mutate_bytes(rng, data, rounds=rng.randrange(1, 4))
    if rng.random() < 0.1:
        return yaml_alias_bomb(text).encode("utf-8")
    tree = yaml.safe_load(text)
    out = yaml.safe_dump(mutate_tree(rng, tree), default_flow_style=None, width=10**6)
    return out.encode("utf-8")


def yaml_alias_bomb(text: str, levels: int = 9) -> str:
    """A YAML document whose values are an exponential alias tree (billion laughs)."""
    lines = ['l0: &l0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for level in range(1, levels):
        refs = ", ".join([f"*l{level - 1}"] * 9)
        lines.append(f"l{level}: &l{level} [{refs}]")
    first_key = text.split(":", 1)[0].strip() if ":" in text else "x"
    lines.append(f"{first_key}: *l{levels - 1}")
    return "\n".join(lines) + "\n"


def mutate_json(rng: random.Random, data: bytes) -> bytes:
    if rng.random() < 0.2:
        return mutate_bytes(rng, data, rounds=rng.randrange(1, 4))
    tree = json.loads(data)
    return json.dumps(mutate_tree(rng, tree), allow_nan=True).encode("utf-8")


# -------------------------------------------------------------------------------------- PNF


def mutate_pnf(rng: random.Random, data: bytes) -> bytes:
    """Mutate 32-byte PNF records: kind byte, fields, order, count, length."""
    records = [bytearray(data[i : i + 32]) for i in range(0, len(data) - len(data) % 32, 32)]
    for _ in range(rng.randrange(1, 4)):
        if not records:
            break
        r = rng.randrange(len(records))
        op = rng.randrange(6)
        if op == 0:
            records[r][0] = pick(
                rng, (0x01, 0x02, 0x03, 0x10, 0x14, 0x15, 0x20, 0x30, 0xE1, 0xFF, 0)
            )
        elif op == 1:
            pos = rng.randrange(32)
            records[r][pos] = pick(rng, (0, 1, 0x7F, 0x80, 0xFF, rng.randrange(256)))
        elif op == 2:
            pos = rng.randrange(31)
            records[r][pos : pos + 2] = pick(rng, (b"\x00\x00", b"\xff\xff", b"\x80\x00"))
        elif op == 3:
            del records[r]
        elif op == 4:
            records.insert(r, bytearray(records[rng.randrange(len(records))]))
        else:
            records[r] = bytearray(32)
    out = b"".join(bytes(r) for r in records)
    if rng.random() < 0.2:
        out = mutate_bytes(rng, out)
    return out


# ------------------------------------------------------------------------------------- MCAP


def mcap_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level records of a valid MCAP file."""
    found: list[tuple[int, int, int]] = []
    pos = 8
    while pos + 9 <= len(data) - 8:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        found.append((pos, opcode, length))
        if opcode == 0x02:  # footer
            break
        pos += 9 + length
    return found


def mutate_mcap(rng: random.Random, data: bytes) -> bytes:
    """Mutate record lengths, opcodes and chunk/index fields, or cut the file."""
    records = mcap_records(data)
    out = bytearray(data)
    for _ in range(rng.randrange(1, 3)):
        offset, _, length = pick(rng, records)
        if offset + 9 > len(out):  # an earlier havoc round shortened the file
            break
        op = rng.randrange(8)
        if op == 0:
            struct.pack_into("<Q", out, offset + 1, pick(rng, INTERESTING_U64))
        elif op == 1:
            out[offset] = pick(
                rng, (0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0C, 0x0F, 0xFF)
            )
        elif op == 2:
            return bytes(out[: offset + rng.randrange(0, 9 + length)])
        elif op in (3, 4) and length >= 8:
            # A u64/u32 field inside the record body (chunk sizes, index offsets, lengths).
            pos = offset + 9 + 4 * rng.randrange(max(1, min(length, 64) // 4))
            width = 8 if rng.random() < 0.5 else 4
            if pos + width <= len(out):
                value = pick(rng, INTERESTING_U64) & ((1 << (8 * width)) - 1)
                struct.pack_into("<Q" if width == 8 else "<I", out, pos, value)
        elif op == 5 and length:
            pos = offset + 9 + rng.randrange(length)
            if pos < len(out):
                out[pos] ^= 1 << rng.randrange(8)
        else:
            out = bytearray(mutate_bytes(rng, bytes(out)))
    return bytes(out)


Mutator = Callable[[random.Random, bytes], bytes]
