"""Nanosecond time stamps and clock models (offset + drift)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.clock import ClockModel, ns_from_seconds, seconds_from_ns

EPOCH_2023_NS = 1_700_000_000_000_000_000
HOURS_NS = 3600 * 1_000_000_000
# Derandomized: the same examples every run (fixed seeds).
SETTINGS = settings(max_examples=200, deadline=None, derandomize=True)


def test_ns_from_seconds_rounds_not_truncates() -> None:
    assert ns_from_seconds(1.9999999996) == 2_000_000_000
    assert ns_from_seconds(0.0000000014) == 1
    assert ns_from_seconds(-0.0000000016) == -2
    assert ns_from_seconds(-1.5) == -1_500_000_000
    # 1e-9 s * 0.7 is not a whole nanosecond: the nearest is taken.
    assert ns_from_seconds(0.7e-9) == 1
    out = ns_from_seconds(np.array([1.9999999996, -0.0000000016, 0.25]))
    assert out.dtype == np.int64
    np.testing.assert_array_equal(out, [2_000_000_000, -2, 250_000_000])


def test_ns_from_seconds_epoch_precision() -> None:
    # The float nearest to this epoch time is within ~0.12 µs; so must the result be.
    t_s = 1_700_000_000.123456789
    assert abs(ns_from_seconds(t_s) - 1_700_000_000_123_456_789) <= 120
    assert ns_from_seconds(t_s) == int(ns_from_seconds(np.array([t_s]))[0])


def test_ns_from_seconds_rejects_non_finite() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        ns_from_seconds(float("nan"))
    with pytest.raises(ValueError, match="non-finite"):
        ns_from_seconds(np.array([0.0, np.inf]))


@SETTINGS
@given(st.integers(-(2**62), 2**62))
def test_seconds_from_ns_is_nearest_float(t_ns: int) -> None:
    t_s = seconds_from_ns(t_ns)
    assert isinstance(t_s, float)
    assert t_s == t_ns / 1e9 or abs(t_s - t_ns / 1e9) <= abs(t_s) * 2.3e-16
    arr = seconds_from_ns(np.array([t_ns], dtype=np.int64))
    assert arr.dtype == np.float64
    assert abs(arr[0] - t_s) <= abs(t_s) * 4.5e-16 + 1e-18


@SETTINGS
@given(st.integers(0, 4_000_000_000 * 10**9))
def test_seconds_ns_round_trip_within_float_precision(t_ns: int) -> None:
    # A float64 resolves ~2.4e-7 s at 2^31 s: the round trip is exact to that.
    back = ns_from_seconds(seconds_from_ns(t_ns))
    assert abs(back - t_ns) <= max(1, t_ns * 2.3e-16)


def test_seconds_from_ns_rejects_floats() -> None:
    with pytest.raises(ValueError, match="integer nanoseconds"):
        seconds_from_ns(np.array([1.5]))


def test_apply_known_values() -> None:
    model = ClockModel(offset_ns=5_000, drift_ppm=10.0, reference_ns=EPOCH_2023_NS)
    assert model.apply(EPOCH_2023_NS) == EPOCH_2023_NS + 5_000
    # One hour later: 10 ppm of an hour is 36 ms.
    assert model.apply(EPOCH_2023_NS + HOURS_NS) == EPOCH_2023_NS + HOURS_NS + 5_000 + 36_000_000
    out = model.apply(np.array([EPOCH_2023_NS, EPOCH_2023_NS + HOURS_NS], dtype=np.int64))
    assert out.dtype == np.int64
    np.testing.assert_array_equal(
        out, [EPOCH_2023_NS + 5_000, EPOCH_2023_NS + HOURS_NS + 36_005_000]
    )
    assert isinstance(model.apply(np.int64(7)), int)
    assert ClockModel(offset_ns=-3).apply(10) == 7


@SETTINGS
@given(
    offset_ns=st.integers(-12 * HOURS_NS, 12 * HOURS_NS),
    drift_ppm=st.floats(-50.0, 50.0),
    reference_ns=st.integers(0, 2 * EPOCH_2023_NS),
    delta_ns=st.integers(-6 * HOURS_NS, 6 * HOURS_NS),
)
def test_apply_inverse_round_trip(
    offset_ns: int, drift_ppm: float, reference_ns: int, delta_ns: int
) -> None:
    model = ClockModel(offset_ns=offset_ns, drift_ppm=drift_ppm, reference_ns=reference_ns)
    t = reference_ns + delta_ns
    assert abs(model.inverse(model.apply(t)) - t) <= 1
    assert abs(model.apply(model.inverse(t)) - t) <= 1
    # The inverted model maps like inverse() does, to rounding.
    assert abs(model.inverted().apply(t) - model.inverse(t)) <= 1
    inv_twice = model.inverted().inverted()
    assert inv_twice.offset_ns == offset_ns
    assert inv_twice.reference_ns == reference_ns
    assert inv_twice.drift_ppm == pytest.approx(drift_ppm, abs=1e-12)
    arr = np.array([t, t + HOURS_NS], dtype=np.int64)
    assert np.all(np.abs(model.inverse(model.apply(arr)) - arr) <= 1)
    assert model.apply(arr)[0] == model.apply(t)
    assert model.inverse(arr)[1] == model.inverse(t + HOURS_NS)


def test_exact_inverse_with_far_reference() -> None:
    # Reference at 0 with epoch-sized stamps: the drift term is ~1e14 ns; still exact.
    model = ClockModel(offset_ns=123_456_789, drift_ppm=-49.9, reference_ns=0)
    t = EPOCH_2023_NS + 987_654_321
    assert abs(model.inverse(model.apply(t)) - t) <= 1


def test_clock_model_errors() -> None:
    with pytest.raises(ValueError, match="drift_ppm"):
        ClockModel(offset_ns=0, drift_ppm=float("nan"))
    with pytest.raises(ValueError, match="drift_ppm"):
        ClockModel(offset_ns=0, drift_ppm=-1e6)
    with pytest.raises(ValueError, match="integer nanoseconds"):
        ClockModel(offset_ns=0).apply(np.array([1.0]))
    with pytest.raises(ValueError, match="integer nanoseconds"):
        ClockModel(offset_ns=0).inverse(np.array([1.0]))


@SETTINGS
@given(st.integers(-(2**53) + 1, 2**53 - 1))
def test_seconds_from_ns_array_is_nearest_below_2_53(t_ns: int) -> None:
    # Durations and offsets: the array path agrees with the scalar one to the bit.
    arr = seconds_from_ns(np.array([t_ns, 1_700_000_000_123_456_789], dtype=np.int64))
    assert arr[0] == t_ns / 1e9 == seconds_from_ns(t_ns)


def test_ns_from_seconds_never_truncates() -> None:
    # 1.001 is stored just below 1.001 s: int(x * 1e9) would give 1_000_999_999.
    assert ns_from_seconds(1.001) == 1_001_000_000
    assert ns_from_seconds(np.array([1.001, 2.5e-9, 3.5e-9])).tolist() == [1_001_000_000, 2, 4]
