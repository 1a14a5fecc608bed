"""GPMF (GoPro Metadata Format) reading and writing: KLV tuples, nesting, scaled values.

Layout of one KLV (all big-endian, 32-bit aligned):

    key     4 bytes  FourCC, e.g. b"ACCL"
    type    1 byte   value type character ('s' int16, 'f' float32, '?' complex, 0 = nested)
    size    1 byte   bytes per structure (one sample: e.g. 6 for three int16 axes)
    repeat  2 bytes  number of structures (samples)
    value   size * repeat bytes, then zero padding to the next multiple of 4

A telemetry payload (one MP4 'gpmd' sample, about one second) is a list of
DEVC (device) nests, each holding DVID/DVNM and STRM (stream) nests; a STRM
holds "sticky" metadata (STNM name, SIUN/UNIT units, SCAL divisor, TYPE for
complex structures, TSMP total samples so far, STMP microsecond time stamp,
ORIN/ORIO/MTRX axis orientation, TMPC temperature) followed by the sensor
data KLV it describes (ACCL, GYRO, GPS5...). As in GoPro's reference parser,
each modifier applies to the data KLVs that follow it in the same nest: for a
data KLV we take the most recent preceding modifier of each kind.

Scaled values follow the reference parser (gpmf-parser GPMF_ScaledData):
`value = raw / SCAL`, with one SCAL for every element or one per element of
the structure; Q15.16 ('q') and Q31.32 ('Q') fixed point are divided by 2^16
and 2^32 first. Orientation (ORIN/ORIO or MTRX) is *not* applied by
`GPMFStream.scaled()`: values stay in the file's axis order; use
`GPMFStream.orientation_matrix()` when the camera's output frame is wanted.

Compressed KLVs (type '#') are parsed as opaque bytes; asking for their values
raises `GPMFError` (no GoPro camera writes them into MP4 telemetry).

Every length is checked against its enclosing nest before anything is read or
allocated: a corrupt length raises `GPMFError` naming the source and the byte
offset, never an out-of-bounds read or a huge allocation.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from shared.errors import InputError

# Type character -> (numpy big-endian dtype, size in bytes). Strings ('c', 'u', 'U'),
# FourCC ('F') and GUID ('G') are byte types here; `decode_value` turns them into str/bytes.
TYPE_DTYPES: dict[str, str] = {
    "b": ">i1",
    "B": ">u1",
    "c": "S1",
    "u": "S1",
    "d": ">f8",
    "f": ">f4",
    "F": "S4",
    "G": "V16",
    "j": ">i8",
    "J": ">u8",
    "l": ">i4",
    "L": ">u4",
    "q": ">i4",
    "Q": ">i8",
    "s": ">i2",
    "S": ">u2",
    "U": "S16",
}
TYPE_NEST = "\x00"
TYPE_COMPLEX = "?"
TYPE_COMPRESSED = "#"
NUMERIC_TYPES = frozenset("bBdfjJlLqQsS")
# Divisor that turns a fixed-point raw value into its real value.
FIXED_POINT_DIVISOR = {"q": float(1 << 16), "Q": float(1 << 32)}

# Keys that modify or describe the data KLVs after them (never sensor data themselves).
MODIFIER_KEYS = frozenset(
    {
        "DVID", "DVNM", "STNM", "RMRK", "SIUN", "UNIT", "SCAL", "TYPE", "TSMP", "TIMO",
        "TICK", "TOCK", "EMPT", "STMP", "STPS", "MTRX", "ORIN", "ORIO", "TMPC", "PFRM",
        "QUAN", "VERS", "FREE",
    }
)  # fmt: skip

_HEADER = struct.Struct(">4scBH")
MAX_NEST_DEPTH = 16


class GPMFError(InputError):
    """A GPMF buffer is malformed (the message names the source and the byte offset)."""


@dataclass(frozen=True, slots=True)
class KLV:
    """One GPMF key-length-value tuple.

    `offset` is the byte offset of the key in the source (file offset when the
    payload was read from an MP4, else offset in the buffer); `value` is the
    unpadded value bytes; `children` the parsed nest when `type` is 0.
    """

    key: str
    type: str
    struct_size: int
    repeat: int
    offset: int
    value: bytes
    children: tuple[KLV, ...] = ()

    @property
    def is_nest(self) -> bool:
        return self.type == TYPE_NEST


def _key_text(raw: bytes) -> str:
    return raw.decode("latin-1")


def parse_klv(
    buffer: bytes | memoryview,
    *,
    source: str = "<bytes>",
    base_offset: int = 0,
    _depth: int = 0,
) -> tuple[KLV, ...]:
    """Parse a GPMF buffer into KLV tuples (nests parsed recursively).

    `source` (a file name) and `base_offset` (where the buffer starts in that
    file) only serve the error messages and `KLV.offset`. Raises `GPMFError`
    when a length runs past its enclosing nest or nesting is deeper than 16.
    Trailing zero padding (a zero key) ends the list.
    """
    if _depth > MAX_NEST_DEPTH:
        raise GPMFError(
            f"{source}: GPMF nesting deeper than {MAX_NEST_DEPTH} at byte {base_offset}"
        )
    view = memoryview(buffer)
    end = len(view)
    pos = 0
    items: list[KLV] = []
    while pos < end:
        if end - pos < 8:
            if any(view[pos:end]):
                raise GPMFError(
                    f"{source}: truncated GPMF header at byte {base_offset + pos} "
                    f"(expected 8 bytes, {end - pos} left)"
                )
            break
        key_raw, type_raw, struct_size, repeat = _HEADER.unpack_from(view, pos)
        if key_raw == b"\x00\x00\x00\x00":
            break  # padding after the last KLV
        type_char = type_raw.decode("latin-1")
        length = struct_size * repeat
        padded = (length + 3) & ~3
        # Checked before slicing: a corrupt length never reads or allocates past the nest.
        # (The last KLV of a buffer may omit its padding.)
        if pos + 8 + length > end:
            raise GPMFError(
                f"{source}: GPMF {_key_text(key_raw)!r} at byte {base_offset + pos} declares "
                f"{length} bytes but only {end - pos - 8} remain in its nest"
            )
        value = bytes(view[pos + 8 : pos + 8 + length])
        children: tuple[KLV, ...] = ()
        if type_char == TYPE_NEST and length:
            children = parse_klv(
                value, source=source, base_offset=base_offset + pos + 8, _depth=_depth + 1
            )
        items.append(
            KLV(
                key=_key_text(key_raw),
                type=type_char,
                struct_size=struct_size,
                repeat=repeat,
                offset=base_offset + pos,
                value=value,
                children=children,
            )
        )
        pos += 8 + padded
    return tuple(items)


_TYPE_TOKEN = re.compile(r"([a-zA-Z])(?:\[(\d+)\])?")


def expand_type_string(type_string: str, *, source: str = "<bytes>", offset: int = 0) -> str:
    """Expand a complex TYPE like "f[8]L" to one character per element ("ffffffffL")."""
    out: list[str] = []
    pos = 0
    text = type_string.rstrip("\x00")
    while pos < len(text):
        match = _TYPE_TOKEN.match(text, pos)
        if match is None or match.group(1) not in TYPE_DTYPES:
            raise GPMFError(f"{source}: unsupported GPMF TYPE {type_string!r} at byte {offset}")
        out.append(match.group(1) * int(match.group(2) or 1))
        pos = match.end()
    return "".join(out)


def _element_types(klv: KLV, type_string: str | None, source: str) -> str:
    """One type character per element of a structure of `klv`."""
    if klv.type == TYPE_COMPLEX:
        if type_string is None:
            raise GPMFError(
                f"{source}: complex GPMF {klv.key!r} at byte {klv.offset} has no preceding TYPE"
            )
        elements = expand_type_string(type_string, source=source, offset=klv.offset)
        size = sum(np.dtype(TYPE_DTYPES[t]).itemsize for t in elements)
        if size != klv.struct_size:
            raise GPMFError(
                f"{source}: GPMF {klv.key!r} at byte {klv.offset}: TYPE {type_string!r} is "
                f"{size} bytes but the structure size is {klv.struct_size}"
            )
        return elements
    if klv.type not in TYPE_DTYPES:
        raise GPMFError(
            f"{source}: GPMF {klv.key!r} at byte {klv.offset} has unsupported type {klv.type!r}"
        )
    item = np.dtype(TYPE_DTYPES[klv.type]).itemsize
    if klv.struct_size % item:
        raise GPMFError(
            f"{source}: GPMF {klv.key!r} at byte {klv.offset}: structure size {klv.struct_size} "
            f"is not a multiple of the {item}-byte type {klv.type!r}"
        )
    return klv.type * (klv.struct_size // item)


def structure_dtype(
    klv: KLV, type_string: str | None = None, *, source: str = "<bytes>"
) -> np.dtype:
    """The numpy dtype of one structure (sample) of `klv` (a record dtype for TYPE '?')."""
    elements = _element_types(klv, type_string, source)
    dtype = np.dtype([(f"f{i}", TYPE_DTYPES[t]) for i, t in enumerate(elements)])
    if dtype.itemsize != klv.struct_size:
        raise GPMFError(
            f"{source}: GPMF {klv.key!r} at byte {klv.offset}: TYPE {type_string or klv.type!r} "
            f"is {dtype.itemsize} bytes but the structure size is {klv.struct_size}"
        )
    return dtype


def raw_array(klv: KLV, type_string: str | None = None, *, source: str = "<bytes>") -> np.ndarray:
    """Raw values as a (repeat, elements) array in native byte order (numeric types only).

    For mixed complex structures the result is int64/float64 as the reference
    parser would promote them (call `structured_array` to keep the exact types).
    """
    elements = _element_types(klv, type_string, source)
    if not set(elements) <= NUMERIC_TYPES:
        raise GPMFError(
            f"{source}: GPMF {klv.key!r} at byte {klv.offset} holds non-numeric type {elements!r}"
        )
    if len(set(elements)) == 1:
        dtype = np.dtype(TYPE_DTYPES[elements[0]])
        flat = np.frombuffer(klv.value, dtype=dtype, count=klv.repeat * len(elements))
        return flat.astype(dtype.newbyteorder("="), copy=True).reshape(klv.repeat, len(elements))
    records = structured_array(klv, type_string, source=source)
    out = np.empty((klv.repeat, len(elements)), dtype=np.float64)
    for i in range(len(elements)):
        out[:, i] = records[f"f{i}"]
    return out


def structured_array(
    klv: KLV, type_string: str | None = None, *, source: str = "<bytes>"
) -> np.ndarray:
    """All structures of `klv` as a record array (fields f0, f1, ... one per element)."""
    dtype = structure_dtype(klv, type_string, source=source)
    return np.frombuffer(klv.value, dtype=dtype, count=klv.repeat)


def decode_value(klv: KLV, type_string: str | None = None, *, source: str = "<bytes>") -> object:
    """A Python value for metadata KLVs: str for 'c'/'u'/'U' text, list of str for
    several strings or FourCCs, a float/int for one number, else a raw numeric array.
    """
    if klv.type in ("c", "u"):
        if klv.struct_size > 1 and klv.repeat > 1:
            width = klv.struct_size
            return [
                # One unit per element; blanks pad the short ones ("uT mm  ").
                _text(klv.value[i * width : (i + 1) * width], klv.type).strip()
                for i in range(klv.repeat)
            ]
        return _text(klv.value, klv.type)
    if klv.type == "U":
        return [_text(klv.value[i * 16 : (i + 1) * 16], "c") for i in range(klv.repeat)]
    if klv.type == "F":
        return [klv.value[i : i + 4].decode("latin-1") for i in range(0, len(klv.value), 4)]
    if klv.type == "G":
        return klv.value
    if klv.type == TYPE_COMPRESSED:
        raise GPMFError(
            f"{source}: compressed GPMF {klv.key!r} at byte {klv.offset} is not supported"
        )
    array = raw_array(klv, type_string, source=source)
    if array.size == 1:
        return array.item()
    return array


def _text(raw: bytes, type_char: str) -> str:
    # SIUN uses single-byte 0xB2 for '²' and 0xB5 for 'µ': Latin-1, not UTF-8 ('u' is UTF-8).
    raw = raw.split(b"\x00", 1)[0]
    return raw.decode("utf-8", errors="replace") if type_char == "u" else raw.decode("latin-1")


@dataclass(frozen=True, slots=True)
class GPMFStream:
    """One sensor data KLV of one payload with the metadata that applies to it.

    `total_samples` is TSMP (samples of this stream since the recording started,
    including this payload) and `timestamp_us` STMP (microseconds since the
    recording started, of the first sample here), each None when absent.
    `scale` is the SCAL divisor (one value or one per element); `units` SIUN
    (or UNIT when no SIUN) as given: one string or one per element.
    """

    key: str
    data: KLV
    source: str = "<bytes>"
    device_id: int | None = None
    device_name: str | None = None
    name: str | None = None
    units: str | list[str] | None = None
    si_units: bool = True
    scale: tuple[float, ...] = (1.0,)
    type_string: str | None = None
    total_samples: int | None = None
    timestamp_us: int | None = None
    temperature_c: float | None = None
    orientation_in: str | None = None
    orientation_out: str | None = None
    matrix: tuple[float, ...] | None = None
    metadata: dict[str, KLV] = field(default_factory=dict)

    @property
    def samples(self) -> int:
        """Number of samples (structures) in this payload."""
        return self.data.repeat

    @property
    def elements(self) -> int:
        """Values per sample (3 for ACCL/GYRO)."""
        return len(_element_types(self.data, self.type_string, self.source))

    def raw(self) -> np.ndarray:
        """Raw integer/float values, shape (samples, elements), file axis order."""
        return raw_array(self.data, self.type_string, source=self.source)

    def scaled(self) -> np.ndarray:
        """Values in the stream's units: raw / SCAL (as gpmf-parser), shape (samples, elements),
        float64, file axis order (no ORIN/MTRX applied).
        """
        elements = _element_types(self.data, self.type_string, self.source)
        raw = self.raw().astype(np.float64)
        fixed = np.array([FIXED_POINT_DIVISOR.get(t, 1.0) for t in elements])
        if len(self.scale) not in (1, len(elements)):
            raise GPMFError(
                f"{self.source}: GPMF {self.key!r} at byte {self.data.offset}: "
                f"{len(self.scale)} SCAL values for {len(elements)} elements"
            )
        scale = np.asarray(self.scale, dtype=np.float64)
        if np.any(scale == 0):
            raise GPMFError(f"{self.source}: GPMF {self.key!r} at byte {self.data.offset}: SCAL 0")
        values: np.ndarray = raw / fixed / scale
        return values

    def orientation_matrix(self) -> np.ndarray | None:
        """The (elements x elements) matrix mapping file-order values to the output
        (camera) axes, `out = M @ in`: MTRX when given, else built from ORIN/ORIO
        (ORIN letters in lower case mean a negated axis), else None.
        """
        n = self.elements
        if self.matrix is not None and len(self.matrix) == n * n:
            return np.asarray(self.matrix, dtype=np.float64).reshape(n, n)
        orin, orio = self.orientation_in, self.orientation_out
        if orin is None or orio is None or len(orin) != len(orio) or len(orin) != n:
            return None
        out = np.zeros((n, n))
        for row, out_axis in enumerate(orio):
            for col, in_axis in enumerate(orin):
                if in_axis == out_axis:
                    out[row, col] = 1.0
                elif in_axis.upper() == out_axis and in_axis.islower():
                    out[row, col] = -1.0
        return out


@dataclass(frozen=True, slots=True)
class GPMFPayload:
    """One parsed telemetry payload (one 'gpmd' sample)."""

    klvs: tuple[KLV, ...]
    streams: tuple[GPMFStream, ...]

    def find(self, key: str) -> list[GPMFStream]:
        """All streams with data key `key` (e.g. "ACCL"), in file order."""
        return [s for s in self.streams if s.key == key]


_DATA_TYPES = frozenset(TYPE_DTYPES) | {TYPE_COMPLEX, TYPE_COMPRESSED}


def _as_int(klv: KLV, source: str) -> int:
    value = decode_value(klv, source=source)
    if isinstance(value, np.ndarray):
        value = value.reshape(-1)[0].item()
    if not isinstance(value, (int, float)):
        raise GPMFError(f"{source}: GPMF {klv.key!r} at byte {klv.offset} is not a number")
    return int(value)


def _streams_in_nest(
    nest: KLV,
    *,
    source: str,
    device_id: int | None,
    device_name: str | None,
) -> Iterator[GPMFStream]:
    """Data KLVs of a STRM with the modifiers that precede them (gpmf-parser FindPrev)."""
    current: dict[str, KLV] = {}
    found: list[tuple[KLV, dict[str, KLV]]] = []
    for klv in nest.children:
        if klv.is_nest:
            continue  # nested sub-structures (TICK/TOCK groups) are kept in `klvs` only
        if klv.key in MODIFIER_KEYS:
            current[klv.key] = klv
            continue
        if klv.type not in _DATA_TYPES:
            continue  # unknown value type: skip safely
        found.append((klv, dict(current)))
    for i, (klv, meta) in enumerate(found):
        if i < len(found) - 1:
            # TSMP counts the samples of the stream's main (last) data KLV, not of the
            # one-per-payload companions before it (GPSF/GPSU/GPSP beside GPS5).
            meta.pop("TSMP", None)
        yield _make_stream(klv, meta, source, device_id, device_name)


def _make_stream(
    data: KLV,
    meta: dict[str, KLV],
    source: str,
    device_id: int | None,
    device_name: str | None,
) -> GPMFStream:
    scale: tuple[float, ...] = (1.0,)
    if "SCAL" in meta:
        scale_array = raw_array(meta["SCAL"], source=source).reshape(-1)
        scale = tuple(
            float(x) / FIXED_POINT_DIVISOR.get(meta["SCAL"].type, 1.0) for x in scale_array
        )
    units: str | list[str] | None = None
    si_units = "SIUN" in meta
    unit_klv = meta.get("SIUN") or meta.get("UNIT")
    if unit_klv is not None:
        value = decode_value(unit_klv, source=source)
        units = value if isinstance(value, (str, list)) else None
    type_string = None
    if "TYPE" in meta:
        type_value = decode_value(meta["TYPE"], source=source)
        if isinstance(type_value, str):
            type_string = type_value
        elif isinstance(type_value, list):
            type_string = "".join(str(part) for part in type_value)
    matrix = None
    if "MTRX" in meta:
        matrix = tuple(float(x) for x in raw_array(meta["MTRX"], source=source).reshape(-1))
    temperature = None
    if "TMPC" in meta:
        temperature = float(raw_array(meta["TMPC"], source=source).reshape(-1)[0])
    orin = decode_value(meta["ORIN"], source=source) if "ORIN" in meta else None
    orio = decode_value(meta["ORIO"], source=source) if "ORIO" in meta else None
    name = decode_value(meta["STNM"], source=source) if "STNM" in meta else None
    return GPMFStream(
        key=data.key,
        data=data,
        source=source,
        device_id=device_id,
        device_name=device_name,
        name=name if isinstance(name, str) else None,
        units=units,
        si_units=si_units,
        scale=scale,
        type_string=type_string,
        total_samples=_as_int(meta["TSMP"], source) if "TSMP" in meta else None,
        timestamp_us=_as_int(meta["STMP"], source) if "STMP" in meta else None,
        temperature_c=temperature,
        orientation_in="".join(orin) if isinstance(orin, (str, list)) else None,
        orientation_out="".join(orio) if isinstance(orio, (str, list)) else None,
        matrix=matrix,
        metadata=meta,
    )


def parse_payload(
    buffer: bytes | memoryview, *, source: str = "<bytes>", base_offset: int = 0
) -> GPMFPayload:
    """Parse one telemetry payload: every DEVC/STRM data KLV with its metadata.

    Data KLVs found directly in a DEVC (outside a STRM) are streams too. Keys
    this module does not know are kept as streams (their values decode by
    type) and never stop the parse.
    """
    klvs = parse_klv(buffer, source=source, base_offset=base_offset)
    streams: list[GPMFStream] = []
    for device in klvs:
        if device.key != "DEVC" or not device.is_nest:
            continue
        device_id: int | None = None
        device_name: str | None = None
        for klv in device.children:
            if klv.key == "DVID" and klv.type in NUMERIC_TYPES:
                device_id = _as_int(klv, source)
            elif klv.key == "DVNM" and klv.type in ("c", "u"):
                name = decode_value(klv, source=source)
                device_name = name if isinstance(name, str) else None
        streams.extend(
            _streams_in_nest(device, source=source, device_id=device_id, device_name=device_name)
        )
        for klv in device.children:
            if klv.key == "STRM" and klv.is_nest:
                streams.extend(
                    _streams_in_nest(
                        klv, source=source, device_id=device_id, device_name=device_name
                    )
                )
    return GPMFPayload(klvs=klvs, streams=tuple(streams))


# ---------------------------------------------------------------- writing


def encode_klv(key: str, type_char: str, struct_size: int, repeat: int, value: bytes) -> bytes:
    """One KLV with its 8-byte header and zero padding to 4 bytes."""
    if len(key) != 4:
        raise ValueError(f"GPMF key must be 4 characters, got {key!r}")
    if struct_size > 255 or repeat > 65535:
        raise ValueError(f"GPMF {key}: structure size {struct_size} or repeat {repeat} too large")
    if len(value) != struct_size * repeat:
        raise ValueError(f"GPMF {key}: {len(value)} bytes for {struct_size} x {repeat}")
    pad = (-len(value)) % 4
    header = _HEADER.pack(key.encode("latin-1"), type_char.encode("latin-1"), struct_size, repeat)
    return header + value + b"\x00" * pad


def encode_nest(key: str, children: Sequence[bytes]) -> bytes:
    """A nest (DEVC, STRM) of already-encoded KLVs (each a multiple of 4 bytes)."""
    body = b"".join(children)
    # Nests count 4-byte words so that large nests fit the 16-bit repeat.
    return encode_klv(key, TYPE_NEST, 4, len(body) // 4, body)


def encode_string(key: str, text: str) -> bytes:
    """A 'c' string KLV (Latin-1, so '²' and 'µ' are one byte as GoPro writes them)."""
    raw = text.encode("latin-1")
    return encode_klv(key, "c", len(raw), 1, raw)


def encode_array(key: str, type_char: str, values: np.ndarray) -> bytes:
    """A numeric KLV: `values` shape (repeat,) or (repeat, elements), cast to `type_char`."""
    array = np.asarray(values)
    if array.ndim == 1:
        array = array.reshape(-1, 1)
    dtype = np.dtype(TYPE_DTYPES[type_char])
    raw = np.ascontiguousarray(array.astype(dtype)).tobytes()
    return encode_klv(key, type_char, dtype.itemsize * array.shape[1], array.shape[0], raw)
