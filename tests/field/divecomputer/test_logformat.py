"""PNF parsing and building, checked against the golden dives of the example-session doc."""

from __future__ import annotations

import re

import pytest

from field.divecomputer import logformat
from shared.errors import InputError

from .golden import load

GOLDEN = load()


def _search(pattern: str, text: str) -> re.Match[str]:
    match = re.search(pattern, text)
    assert match is not None, pattern
    return match


def doc_samples(xml: str, dive_number: int) -> list[tuple[int, float, float]]:
    """(time s, depth m, temperature °C) of one dive as dctool printed it in the doc."""
    dive = xml.split("<dive>")[dive_number]
    samples = []
    for block in re.findall(r"<sample>(.*?)</sample>", dive, re.S):
        minutes, seconds = _search(r"<time>(\d+):(\d+)</time>", block).groups()
        depth = float(_search(r"<depth>([-\d.]+)</depth>", block).group(1))
        temp = float(_search(r"<temperature>([-\d.]+)</temperature>", block).group(1))
        samples.append((int(minutes) * 60 + int(seconds), depth, temp))
    return samples


@pytest.mark.parametrize(("raw", "number"), [(GOLDEN.dive_a, 1), (GOLDEN.dive_b, 2)])
def test_golden_dives_parse_as_dctool_printed(raw: bytes, number: int) -> None:
    dive = logformat.parse_pnf(raw)
    expected = doc_samples(GOLDEN.xml, number)
    got = [
        (round(t - dive.start_s), d, c)
        for t, d, c in zip(dive.stamps_s, dive.depth_m, dive.temperature_c, strict=True)
    ]
    want: list[object] = [
        (t, pytest.approx(d, abs=0.005), pytest.approx(c)) for t, d, c in expected
    ]
    assert got == want
    header = GOLDEN.xml.split("<dive>")[number]
    assert f"<fingerprint>{dive.fingerprint.hex().upper()}</fingerprint>" in header
    minutes, seconds = _search(r"<divetime>(\d+):(\d+)</divetime>", header).groups()
    assert dive.duration_s == int(minutes) * 60 + int(seconds)
    assert f"<maxdepth>{dive.max_depth_m:.2f}</maxdepth>" in header
    assert (dive.serial, dive.firmware, dive.model_number) == (0x1234ABCD, 92, 6)
    assert dive.surface_pressure_mbar == 1013 and dive.water_density_kg_m3 == 1025
    assert not dive.imperial and dive.log_version == 10


def test_build_reproduces_golden_dive_b() -> None:
    parsed = logformat.parse_pnf(GOLDEN.dive_b)
    settings = logformat.PnfSettings(start_s=parsed.start_s, sample_interval_ms=10_000)
    assert logformat.build_pnf(settings, parsed.depth_m, parsed.temperature_c) == GOLDEN.dive_b


def test_imperial_round_trip() -> None:
    depths = [3.0, 12.19, 30.48, 18.0]
    temps = [20.0, 15.0, 10.0, 12.2]
    settings = logformat.PnfSettings(start_s=1_717_000_000, sample_interval_ms=5000, imperial=True)
    dive = logformat.parse_pnf(logformat.build_pnf(settings, depths, temps))
    assert dive.imperial and dive.sample_interval_s == 5.0
    # 0.1 ft and whole °F steps: within half a step of what was asked.
    assert dive.depth_m == pytest.approx(depths, abs=0.0153)
    assert dive.temperature_c == pytest.approx(temps, abs=0.28)
    assert dive.depth_m[2] == 100.0 * 0.3048
    assert dive.stamps_s == [1_717_000_005.0 + 5 * k for k in range(4)]


def test_refusals() -> None:
    with pytest.raises(InputError, match="d1: legacy Predator-like"):
        logformat.parse_pnf(b"\xff\xff" + bytes(126), where="d1")
    with pytest.raises(InputError, match="no 32-byte record"):
        logformat.parse_pnf(b"\x10" * 20)
    no_closing = GOLDEN.dive_a[:0x120] + GOLDEN.dive_a[0x140:]
    with pytest.raises(InputError, match="closing record 0 not found"):
        logformat.parse_pnf(no_closing)
    zero_interval = bytearray(GOLDEN.dive_a)
    zero_interval[0xA0 + 23 : 0xA0 + 25] = b"\x00\x00"
    with pytest.raises(InputError, match="sample interval of 0 ms"):
        logformat.parse_pnf(bytes(zero_interval))


def test_default_interval_without_record_5() -> None:
    without = GOLDEN.dive_a[:0xA0] + GOLDEN.dive_a[0xC0:]
    assert logformat.parse_pnf(without).sample_interval_s == 10.0


def test_check_dive() -> None:
    dive = logformat.parse_pnf(GOLDEN.dive_a)
    fingerprint = dive.fingerprint
    logformat.check_dive(dive, fingerprint=fingerprint, serial=0x1234ABCD, where="A")
    with pytest.raises(InputError, match="A: inconsistent log: fingerprint"):
        logformat.check_dive(dive, fingerprint=b"\0\0\0\0", serial=None, where="A")
    with pytest.raises(InputError, match="serial 1234ABCD"):
        logformat.check_dive(dive, fingerprint=fingerprint, serial=1, where="A")
    dive.depth_m[0] = 99.0
    with pytest.raises(InputError, match=r"deepest sample 99\.00 m"):
        logformat.check_dive(dive, fingerprint=fingerprint, serial=None, where="A")


def test_freedive_records() -> None:
    base = bytearray(GOLDEN.dive_b)
    record = bytearray(32)
    record[0] = logformat.FREEDIVE
    record[1:3] = (1013 + 1005).to_bytes(2, "big")  # ~10 m of salt water above surface
    record[3:5] = (215).to_bytes(2, "big")
    base[0xC0:0xE0] = record
    dive = logformat.parse_pnf(bytes(base))
    assert dive.depth_m[0] == pytest.approx(1005 * 100 / (1025 * 9.80665))
    assert dive.temperature_c[0] == 21.5
    assert len(dive.depth_m) == 6
