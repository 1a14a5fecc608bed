"""Corrupt input never crashes the readers: only InputError, never another exception."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from field.gopro import gpmf
from field.gopro.mp4 import read_mp4
from shared.errors import InputError


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(st.binary(max_size=256))
def test_random_bytes_parse_or_raise_gpmf_error(data: bytes) -> None:
    try:
        payload = gpmf.parse_payload(data, source="fuzz")
    except gpmf.GPMFError:
        return
    for stream in payload.streams:
        with contextlib.suppress(gpmf.GPMFError):
            stream.scaled()


@settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(position=st.integers(0, 10**9), value=st.integers(0, 255))
def test_flipped_byte_in_real_payload(shared_data: Path, position: int, value: int) -> None:
    mp4 = read_mp4(shared_data / "gopro" / "max-heromode.mp4")
    payload = bytearray(mp4.read_sample(mp4.gpmf_track(), 0))
    payload[position % len(payload)] = value
    try:
        parsed = gpmf.parse_payload(bytes(payload), source="max-heromode.mp4")
        for stream in parsed.streams:
            stream.scaled()
    except gpmf.GPMFError:
        pass


@pytest.mark.parametrize("cut", [0, 8, 19, 20, 4_000_000, 4_115_990, 4_120_000, 4_134_000])
def test_truncated_real_file_raises_input_error(
    shared_data: Path, tmp_path: Path, cut: int
) -> None:
    source = (shared_data / "gopro" / "karma.mp4").read_bytes()
    path = tmp_path / "karma.mp4"
    path.write_bytes(source[:cut])
    with pytest.raises(InputError, match=r"karma\.mp4"):
        mp4 = read_mp4(path)
        mp4.gpmf_track()
