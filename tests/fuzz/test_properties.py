"""Hypothesis properties of the byte-level codecs: round trips of what our writers make, and
arbitrary bytes that end in our own error type (never another exception)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from field.divecomputer import logformat
from field.divecomputer import protocol as p
from field.gopro import gpmf
from shared.archive import Imu, cdr
from shared.errors import InputError, WreckmapError

pytestmark = pytest.mark.timeout(120)

FAST = settings(max_examples=100, derandomize=True, deadline=None, database=None)
FIXTURE = settings(
    max_examples=60,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@FAST
@given(st.binary(max_size=300))
def test_slip_round_trip(payload: bytes) -> None:
    decoder = p.SlipDecoder()
    frames = decoder.feed(p.slip_encode(payload))
    assert frames == ([payload] if payload else [])
    assert decoder.pending == 0


@FAST
@given(st.binary(max_size=400))
def test_slip_decoder_on_any_bytes(data: bytes) -> None:
    decoder = p.SlipDecoder()
    for frame in decoder.feed(data):
        if isinstance(frame, p.ProtocolError):
            assert str(frame)
            continue
        assert frame and isinstance(frame, bytes)
        try:
            p.decode_response(frame)
        except p.ProtocolError as error:
            assert "frame" in str(error) or "header" in str(error)
    assert decoder.pending <= len(data)


@FAST
@given(st.binary(max_size=2000))
def test_lre_xor_round_trip(plain: bytes) -> None:
    assert p.decompress_blocks(p.compress_dive(plain)) == plain


@FAST
@given(st.lists(st.binary(max_size=60), max_size=6))
def test_decompress_any_blocks(blocks: list[bytes]) -> None:
    try:
        out = p.decompress_blocks(blocks)
    except p.ProtocolError as error:
        assert "compress" in str(error)
        return
    # 9-bit tokens: one run token makes at most 255 bytes.
    assert len(out) <= 255 * sum(len(b) for b in blocks) * 8 // 9


@FAST
@given(st.binary(min_size=0x600, max_size=0x600))
def test_manifest_page_of_any_bytes(page: bytes) -> None:
    records, full = p.decode_manifest_page(page)
    assert len(records) <= p.MANIFEST_RECORDS and (not full or len(records) == 48)


@FAST
@given(
    st.lists(
        st.tuples(st.floats(-5, 300, allow_nan=False), st.floats(-5, 40, allow_nan=False)),
        max_size=50,
    ),
    st.booleans(),
)
def test_pnf_round_trip(samples: list[tuple[float, float]], imperial: bool) -> None:
    settings_ = logformat.PnfSettings(start_s=1_600_000_000, imperial=imperial)
    depths = [d for d, _ in samples]
    temps = [t for _, t in samples]
    dive = logformat.parse_pnf(logformat.build_pnf(settings_, depths, temps), where="d")
    unit = 0.1 * (logformat.FEET_TO_M if imperial else 1.0)
    assert len(dive.depth_m) == len(samples)
    for got, want in zip(dive.depth_m, depths, strict=True):
        assert abs(got - min(max(want, 0.0), 0xFFFF * unit)) <= unit / 2 + 1e-9
    logformat.check_dive(dive, fingerprint=dive.fingerprint, serial=dive.serial, where="d")


@FAST
@given(st.binary(max_size=700))
def test_pnf_of_any_bytes(data: bytes) -> None:
    try:
        logformat.parse_pnf(data, where="any.pnf")
    except InputError as error:
        assert str(error).startswith("any.pnf: ")


_KEYS = st.text(alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZ", min_size=4, max_size=4)


@FAST
@given(
    st.lists(
        st.tuples(_KEYS, st.sampled_from("bBsSlLfdjJ"), st.integers(1, 4), st.integers(0, 20)),
        max_size=8,
    ),
    st.randoms(use_true_random=False),
)
def test_gpmf_klv_round_trip(specs: list[tuple[str, str, int, int]], rng: object) -> None:
    import random

    assert isinstance(rng, random.Random)
    encoded = []
    arrays = []
    for key, type_char, elements, repeat in specs:
        dtype = np.dtype(gpmf.TYPE_DTYPES[type_char])
        raw = bytes(rng.randrange(256) for _ in range(dtype.itemsize * elements * repeat))
        values = np.frombuffer(raw, dtype=dtype).reshape(repeat, elements)
        encoded.append(gpmf.encode_array(key, type_char, values))
        arrays.append(values)
    klvs = gpmf.parse_klv(b"".join(encoded), source="r.bin")
    assert len(klvs) == len(specs)
    for klv, values in zip(klvs, arrays, strict=True):
        got = gpmf.raw_array(klv, source="r.bin")
        np.testing.assert_array_equal(got.view(np.uint8), values.astype(got.dtype).view(np.uint8))


@FAST
@given(st.binary(max_size=300))
def test_gpmf_any_bytes(data: bytes) -> None:
    try:
        payload = gpmf.parse_payload(data, source="any.bin")
    except gpmf.GPMFError as error:
        assert "any.bin" in str(error) and "byte" in str(error)
        return
    for stream in payload.streams:
        try:
            stream.scaled()
        except gpmf.GPMFError as error:
            assert "any.bin" in str(error) and "at byte" in str(error)


@FAST
@given(
    st.integers(-(2**31) * 10**9, (2**31 - 1) * 10**9),
    st.text(max_size=20),
    st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=6, max_size=6),
)
def test_cdr_imu_round_trip(stamp_ns: int, frame_id: str, values: list[float]) -> None:
    message = Imu(stamp_ns=stamp_ns, frame_id=frame_id,
                  angular_velocity_rad_s=np.array(values[:3]),
                  linear_acceleration_m_s2=np.array(values[3:]))  # fmt: skip
    back = cdr.decode_imu(cdr.encode_imu(message))
    assert back.stamp_ns == stamp_ns and back.frame_id == frame_id
    np.testing.assert_array_equal(back.angular_velocity_rad_s, values[:3])
    batch = cdr.decode_imu_batch([cdr.encode_imu(message)] * 3)
    assert batch.stamps_ns.tolist() == [stamp_ns] * 3


@FAST
@given(st.sampled_from(sorted(cdr.DECODERS)), st.binary(max_size=200))
def test_cdr_any_bytes(schema: str, data: bytes) -> None:
    try:
        cdr.decode(schema, data, where="x.mcap /t")
    except InputError as error:
        assert str(error).startswith("x.mcap /t: ")


@FIXTURE
@given(
    st.lists(st.integers(-(2**62), 2**62), min_size=1, max_size=20, unique=True),
    st.randoms(use_true_random=False),
)
def test_tum_round_trip_of_any_int64_stamps(tmp_path: Path, stamps: list[int], rng: object) -> None:
    import random

    from shared.formats.tum import format_tum, read_tum
    from shared.geometry import make_pose, so3_exp
    from shared.trajectory import Trajectory

    assert isinstance(rng, random.Random)
    stamps = sorted(stamps)
    generator = np.random.default_rng(rng.randrange(2**32))
    poses = make_pose(
        so3_exp(generator.normal(size=(len(stamps), 3))), generator.normal(size=(len(stamps), 3))
    )
    path = tmp_path / "t.tum"
    path.write_text(format_tum(Trajectory(stamps_ns=np.array(stamps), poses=poses)), "utf-8")
    back = read_tum(path)
    assert back.stamps_ns.tolist() == stamps
    np.testing.assert_allclose(back.poses, poses, atol=1e-12)


@FIXTURE
@given(
    st.lists(
        st.tuples(
            st.floats(0, 1e6, allow_nan=False),
            st.floats(allow_nan=True, allow_infinity=False),
            st.floats(allow_nan=True, allow_infinity=False),
        ),
        max_size=30,
    )
)
def test_dive_csv_round_trip(tmp_path: Path, rows: list[tuple[float, float, float]]) -> None:
    from shared.formats.diveprofile import DiveProfile, dive_csv_text, read_dive_csv_arrays

    stamps = sorted(1.6e9 + r[0] for r in rows)
    profile = DiveProfile(
        stamps_s=np.array(stamps),
        depth_m=np.array([r[1] for r in rows]),
        temperature_c=np.array([r[2] for r in rows]),
        start_iso="2020-09-13T12:26:40",
    )
    path = tmp_path / "d.csv"
    path.write_text(dive_csv_text(profile), "utf-8")
    got = read_dive_csv_arrays(path)
    np.testing.assert_array_equal(got[0], profile.stamps_s)
    for a, b in zip(got[1:], (profile.depth_m, profile.temperature_c), strict=True):
        assert [x if not math.isnan(x) else None for x in a.tolist()] == [
            x if not math.isnan(x) else None for x in b.tolist()
        ]


def test_every_error_is_a_wreckmap_error() -> None:
    """The errors the properties above accept all derive from WreckmapError."""
    for error_type in (p.ProtocolError, gpmf.GPMFError, InputError):
        assert issubclass(error_type, WreckmapError)
