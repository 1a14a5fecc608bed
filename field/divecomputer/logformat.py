"""Petrel Native Format (PNF) dive logs: parse what a Shearwater sends, and build one.

Pure code (no I/O). A dive, after decompression, is a run of 32-byte records
(../shared/docs/shearwater-protocol.md §9). `parse_pnf` turns it into samples in SI
units with the logged sample interval; `build_pnf` makes a valid log from samples (for
the simulated unit). Times are the computer's local wall clock as seconds since 1970,
read as UTC (the log stores no zone).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from shared.errors import InputError

FEET_TO_M = 0.3048
DEFAULT_INTERVAL_MS = 10_000  # assumed when the log has no opening record 5 (§9.2)
RECORD = 32

SAMPLE = 0x01
FREEDIVE = 0x02
AVELO = 0x03
OPENING = range(0x10, 0x1A)
CLOSING = range(0x20, 0x2A)
INFO_EVENT = 0x30
EXTENDED_SAMPLE = 0xE1
FINAL = 0xFF

UNITS_METRIC = 0
UNITS_IMPERIAL = 1
STATUS_OPEN_CIRCUIT = 0x10
TANK_AI_OFF = 0xFFFF


@dataclass
class ParsedDive:
    """What a PNF log says. Depth metres positive down, temperature °C, times seconds.

    `stamps_s[k]` is `start_s + (k + 1) * sample_interval_s`: the first sample is logged
    one interval after the start (§9.5).
    """

    start_s: int  # local wall clock as if UTC, also the fingerprint
    fingerprint: bytes  # dive bytes 12..15
    imperial: bool
    sample_interval_s: float
    log_version: int
    stamps_s: list[float]
    depth_m: list[float]
    temperature_c: list[float]
    max_depth_m: float  # closing record 0
    duration_s: int  # closing record 0
    surface_pressure_mbar: int
    water_density_kg_m3: int
    serial: int | None = None  # final record, when present
    firmware: int | None = None
    model_number: int | None = None
    records: dict[int, bytes] = field(default_factory=dict)


def _u16(data: bytes, offset: int) -> int:
    return int.from_bytes(data[offset : offset + 2], "big")


def _depth_m(raw: int, imperial: bool) -> float:
    # raw / 10 first, as the reference client does, so metric depths print short (10.1).
    return raw / 10 * FEET_TO_M if imperial else raw / 10


def _temperature_c(raw: int, imperial: bool) -> float:
    # Reference-client quirk (§9.5): negative raw values t become min(t + 102, 0).
    # Reproduced so our samples match what dctool and Subsurface report for the same log.
    value = raw - 256 if raw >= 128 else raw
    if value < 0:
        value = min(value + 102, 0)
    if imperial:
        return (value - 32) * 5.0 / 9.0
    return float(value)


def parse_pnf(data: bytes, *, where: str = "dive") -> ParsedDive:
    """Parse one decompressed PNF dive; `where` names it in error messages.

    Raises `InputError` for a legacy ("Predator-like") log, a length that is not whole
    records, or missing opening/closing records 0-4.
    """
    if data[:2] == b"\xff\xff":
        raise InputError(
            f"{where}: legacy Predator-like log layout (FF FF at byte 0); only the Petrel "
            "Native Format is supported"
        )
    usable = len(data) - len(data) % RECORD
    if usable == 0:
        raise InputError(f"{where}: {len(data)} bytes, no 32-byte record")
    records: dict[int, bytes] = {}
    sample_records: list[bytes] = []
    for offset in range(0, usable, RECORD):
        record = data[offset : offset + RECORD]
        kind = record[0]
        if not any(record):
            continue
        if kind in (SAMPLE, AVELO, FREEDIVE):
            sample_records.append(record)
        elif kind in OPENING or kind in CLOSING or kind == FINAL:
            records.setdefault(kind, record)
    for number in range(5):
        for base, name in ((0x10, "opening"), (0x20, "closing")):
            if base + number not in records:
                raise InputError(f"{where}: {name} record {number} not found (damaged log)")
    open0, open1, open3, open4 = records[0x10], records[0x11], records[0x13], records[0x14]
    imperial = open0[8] == UNITS_IMPERIAL
    log_version = open4[16]
    interval_ms = DEFAULT_INTERVAL_MS
    if log_version >= 9 and 0x15 in records:
        interval_ms = _u16(records[0x15], 23)
        if interval_ms == 0:
            raise InputError(f"{where}: sample interval of 0 ms in opening record 5")
    interval_s = interval_ms / 1000.0
    start_s = int.from_bytes(open0[12:16], "big")
    surface_mbar = _u16(open1, 16)
    density = _u16(open3, 3)

    depths: list[float] = []
    temps: list[float] = []
    for record in sample_records:
        if record[0] == FREEDIVE:
            for sub in range(4):
                chunk = record[8 * sub : 8 * sub + 8]
                if not any(chunk):
                    break
                pressure_mbar = _u16(chunk, 1)
                depths.append(
                    (pressure_mbar - surface_mbar) * 100.0 / ((density or 1025) * 9.80665)
                )
                temps.append(int.from_bytes(chunk[3:5], "big", signed=True) / 10.0)
            continue
        depths.append(_depth_m(_u16(record, 1), imperial))
        temps.append(_temperature_c(record[14], imperial))
    close0 = records[0x20]
    final = records.get(FINAL)
    return ParsedDive(
        start_s=start_s,
        fingerprint=bytes(data[12:16]),
        imperial=imperial,
        sample_interval_s=interval_s,
        log_version=log_version,
        stamps_s=[start_s + (k + 1) * interval_s for k in range(len(depths))],
        depth_m=depths,
        temperature_c=temps,
        max_depth_m=_depth_m(_u16(close0, 4), imperial),
        duration_s=int.from_bytes(close0[6:9], "big"),
        surface_pressure_mbar=surface_mbar,
        water_density_kg_m3=density,
        serial=None if final is None else int.from_bytes(final[2:6], "big"),
        firmware=None if final is None else _from_bcd(final[10]),
        model_number=None if final is None else final[13],
        records=records,
    )


def _from_bcd(value: int) -> int:
    return (value >> 4) * 10 + (value & 0x0F)


def _to_bcd(value: int) -> int:
    value = max(0, min(99, value))
    return ((value // 10) << 4) | (value % 10)


@dataclass(kw_only=True)
class PnfSettings:
    """How the simulated unit logs a dive.

    start_s: local wall clock as seconds since 1970 read as UTC (whole seconds).
    sample_interval_ms: logged interval, milliseconds (opening record 5).
    """

    start_s: int
    sample_interval_ms: int = 10_000
    imperial: bool = False
    serial: int = 0x1234ABCD
    firmware: int = 92
    model_number: int = 6
    surface_pressure_mbar: int = 1013
    water_density_kg_m3: int = 1025
    log_version: int = 10
    o2_percent: int = 21


def quantize_depth(depth_m: float, imperial: bool) -> int:
    """Depth in metres -> the logged 0.1 m (or 0.1 ft) count, clipped to 0..65535."""
    unit = 0.1 * (FEET_TO_M if imperial else 1.0)
    if not math.isfinite(depth_m):
        return 0
    return max(0, min(0xFFFF, round(depth_m / unit)))


def quantize_temperature(temperature_c: float, imperial: bool) -> int:
    """°C -> the logged whole °C (or °F) byte, 0..127 (negatives decode ambiguously, §9.5)."""
    if not math.isfinite(temperature_c):
        return 0
    value = temperature_c * 9.0 / 5.0 + 32.0 if imperial else temperature_c
    return max(0, min(127, round(value)))


def build_pnf(
    settings: PnfSettings, depth_m: Sequence[float], temperature_c: Sequence[float]
) -> bytes:
    """A valid open-circuit PNF dive holding these samples (one per interval).

    Depth and temperature are quantized as the unit would log them (0.1 m or 0.1 ft,
    whole °C or °F, temperatures at or above 0).
    """
    if len(depth_m) != len(temperature_c):
        raise ValueError("depth_m and temperature_c must have one length")
    imperial = settings.imperial
    raw_depths = [quantize_depth(d, imperial) for d in depth_m]
    raw_temps = [quantize_temperature(t, imperial) for t in temperature_c]

    def record(kind: int, fields: dict[int, bytes]) -> bytes:
        out = bytearray(RECORD)
        out[0] = kind
        for offset, value in fields.items():
            out[offset : offset + len(value)] = value
        return bytes(out)

    def u16(value: int) -> bytes:
        return value.to_bytes(2, "big")

    gases = bytes((settings.o2_percent, 32))
    records = [
        record(
            0x10,
            {
                4: bytes((30, 70)),
                8: bytes((UNITS_IMPERIAL if imperial else UNITS_METRIC,)),
                12: settings.start_s.to_bytes(4, "big"),
                20: gases,
            },
        ),
        record(0x11, {16: u16(settings.surface_pressure_mbar)}),
        record(0x12, {}),
        record(0x13, {3: u16(settings.water_density_kg_m3)}),
        record(0x14, {1: b"\x01", 16: bytes((settings.log_version,)), 17: u16(0x0003)}),
        record(0x15, {23: u16(settings.sample_interval_ms)}),
    ]
    for raw_depth, raw_temp in zip(raw_depths, raw_temps, strict=True):
        records.append(
            record(
                SAMPLE,
                {
                    1: u16(raw_depth),
                    8: bytes((settings.o2_percent,)),
                    12: bytes((STATUS_OPEN_CIRCUIT,)),
                    14: bytes((raw_temp,)),
                    20: u16(TANK_AI_OFF),
                    22: b"\xff",
                    28: u16(TANK_AI_OFF),
                },
            )
        )
    duration_s = len(raw_depths) * settings.sample_interval_ms // 1000
    records.append(
        record(
            0x20,
            {4: u16(max(raw_depths, default=0)), 6: duration_s.to_bytes(3, "big")},
        )
    )
    records += [record(kind, {}) for kind in (0x21, 0x22, 0x23, 0x24)]
    records.append(
        record(
            FINAL,
            {
                1: b"\xff",
                2: settings.serial.to_bytes(4, "big"),
                10: bytes((_to_bcd(settings.firmware),)),
                13: bytes((settings.model_number,)),
            },
        )
    )
    return b"".join(records)


def check_dive(dive: ParsedDive, *, fingerprint: bytes, serial: int | None, where: str) -> None:
    """Consistency checks that catch corrupted bytes the link itself cannot detect.

    The protocol has no checksum, so a downloaded dive is checked against what the
    manifest and its own closing record say: the fingerprint, the serial number, the
    closing record's maximum depth and duration. Raises `InputError` when one differs.
    """
    problems = []
    if dive.fingerprint != fingerprint:
        problems.append(f"fingerprint {dive.fingerprint.hex()} (manifest {fingerprint.hex()})")
    if serial is not None and dive.serial is not None and dive.serial != serial:
        problems.append(f"serial {dive.serial:08X} (unit {serial:08X})")
    # The unit tracks its maximum between samples, so only a deeper sample is an error.
    if dive.depth_m and max(dive.depth_m) > dive.max_depth_m + 1e-6:
        problems.append(
            f"deepest sample {max(dive.depth_m):.2f} m (closing record {dive.max_depth_m:.2f} m)"
        )
    if problems:
        raise InputError(f"{where}: inconsistent log: " + "; ".join(problems))
