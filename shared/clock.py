"""Time stamps and the relation between two clocks.

Every time stamp inside wreckmap is an integer count of nanoseconds since the
UNIX epoch (int64). Seconds as floats appear only at file boundaries (TUM,
CSV), in options and in reports, and go through `ns_from_seconds` /
`seconds_from_ns`; this module is the one home of `NS_PER_S`. Durations,
offsets and periods use the same functions (a duration is a difference of
stamps); a period of a rate is `NS_PER_S / rate_hz`.

Rounding rules, exact:
- `ns_from_seconds` rounds to the nearest nanosecond, ties to even (Python's
  `round`, NumPy's `rint`). It never truncates: `int(x * 1e9)` would turn
  1.001 s (a float just below it) into 1 000 999 999 ns. It splits whole seconds
  from the fraction, so the result is the input float's exact value rounded
  once; `round(x * 1e9)` rounds the product first (to 256 ns at an epoch time)
  and can differ from it by that much.
- `seconds_from_ns` returns the nearest float (correctly rounded `t / 1e9`)
  for a scalar, and for an array when |t| < 2**53 ns (104 days: every duration
  and offset); epoch stamps in an array are within one ulp of it (about 0.24 µs
  at a present-day time, the float's own resolution).
- Arithmetic on stamps stays in integers; only a final result is converted.

Pure math: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import overload

import numpy as np
import numpy.typing as npt

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

NS_PER_S = 1_000_000_000
"""Nanoseconds per second (int, so integer arithmetic on stamps stays exact)."""

_EXACT_FLOAT_INT = 2**53


@overload
def ns_from_seconds(t_s: float) -> int: ...
@overload
def ns_from_seconds(t_s: npt.NDArray[np.floating] | list[float]) -> IntArray: ...
def ns_from_seconds(t_s: float | npt.NDArray[np.floating] | list[float]) -> int | IntArray:
    """Seconds (a time since the epoch or a duration; float or array) to int64 nanoseconds,
    rounded to nearest with ties to even, never truncated.

    Raises ValueError for non-finite input.
    """
    if isinstance(t_s, int | float | np.floating | np.integer):
        value = float(t_s)
        if not math.isfinite(value):
            raise ValueError(f"ns_from_seconds: non-finite time {value!r}")
        whole = math.floor(value)
        # value - whole is exact in float64 (Sterbenz), so only the fraction is rounded.
        return whole * NS_PER_S + round((value - whole) * NS_PER_S)
    arr = np.asarray(t_s, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("ns_from_seconds: non-finite time in array")
    whole_arr = np.floor(arr)
    frac_ns = np.rint((arr - whole_arr) * NS_PER_S).astype(np.int64)
    result: IntArray = whole_arr.astype(np.int64) * NS_PER_S + frac_ns
    return result


@overload
def seconds_from_ns(t_ns: int | np.integer) -> float: ...
@overload
def seconds_from_ns(t_ns: npt.NDArray[np.integer] | list[int]) -> FloatArray: ...
def seconds_from_ns(
    t_ns: int | np.integer | npt.NDArray[np.integer] | list[int],
) -> float | FloatArray:
    """Int64 nanoseconds (a stamp or a duration) to float seconds.

    The nearest float for a scalar and for array entries below 2**53 ns; within one ulp
    for larger array entries. Raises ValueError for a non-integer array.
    """
    if isinstance(t_ns, int | np.integer):
        # Python's int / int is correctly rounded.
        return int(t_ns) / NS_PER_S
    arr = np.asarray(t_ns)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"seconds_from_ns: expected integer nanoseconds, got {arr.dtype}")
    arr = arr.astype(np.int64)
    # Below 2**53 the integer is exact as a float and one division rounds correctly.
    small = np.abs(arr) < _EXACT_FLOAT_INT
    if np.all(small):
        quotient: FloatArray = arr.astype(np.float64) / NS_PER_S
        return quotient
    # Split toward zero so both parts share the sign (no cancellation near zero).
    magnitude = np.abs(arr)
    sign = np.sign(arr).astype(np.float64)
    whole, frac = np.divmod(magnitude, NS_PER_S)
    result: FloatArray = sign * (whole.astype(np.float64) + frac.astype(np.float64) / NS_PER_S)
    exact = arr.astype(np.float64) / NS_PER_S
    result[small] = exact[small]
    return result


@dataclass(frozen=True)
class ClockModel:
    """Affine map from a source clock to a target clock, in int64 nanoseconds.

    `t_target = t_source + offset_ns + drift_ppm * 1e-6 * (t_source - reference_ns)`.
    `reference_ns` is a time on the source clock near the data (so the drift
    term stays small); `drift_ppm` is the target's rate relative to the source
    minus one, in parts per million.
    """

    offset_ns: int
    drift_ppm: float = 0.0
    reference_ns: int = 0

    def __post_init__(self) -> None:
        if not math.isfinite(self.drift_ppm) or abs(self.drift_ppm) >= 1e6:
            raise ValueError(
                f"ClockModel: drift_ppm must be finite and above -1e6, got {self.drift_ppm}"
            )

    @property
    def _rate_minus_one(self) -> float:
        return self.drift_ppm * 1e-6

    @overload
    def apply(self, t_ns: int | np.integer) -> int: ...
    @overload
    def apply(self, t_ns: npt.NDArray[np.integer]) -> IntArray: ...
    def apply(self, t_ns: int | np.integer | npt.NDArray[np.integer]) -> int | IntArray:
        """Map source-clock stamps (int64 ns) to the target clock (int64 ns, rounded)."""
        d = self._rate_minus_one
        if isinstance(t_ns, int | np.integer):
            x = int(t_ns) - self.reference_ns
            # Integer part exact; only the (small) drift correction is a float.
            return int(t_ns) + self.offset_ns + round(x * d)
        arr = _int64_array(t_ns)
        x_arr = (arr - np.int64(self.reference_ns)).astype(np.float64)
        result: IntArray = arr + np.int64(self.offset_ns) + np.rint(x_arr * d).astype(np.int64)
        return result

    @overload
    def inverse(self, t_target_ns: int | np.integer) -> int: ...
    @overload
    def inverse(self, t_target_ns: npt.NDArray[np.integer]) -> IntArray: ...
    def inverse(self, t_target_ns: int | np.integer | npt.NDArray[np.integer]) -> int | IntArray:
        """Map target-clock stamps back to the source clock (int64 ns, rounded).

        Exact algebraic inverse: with x = t_target - offset - reference,
        t_source = reference + x / (1 + d) = t_target - offset - x * d / (1 + d).
        """
        d = self._rate_minus_one
        k = d / (1.0 + d)
        if isinstance(t_target_ns, int | np.integer):
            x = int(t_target_ns) - self.offset_ns - self.reference_ns
            return int(t_target_ns) - self.offset_ns - round(x * k)
        arr = _int64_array(t_target_ns)
        x_arr = (arr - np.int64(self.offset_ns) - np.int64(self.reference_ns)).astype(np.float64)
        result: IntArray = arr - np.int64(self.offset_ns) - np.rint(x_arr * k).astype(np.int64)
        return result

    def inverted(self) -> ClockModel:
        """The model of the inverse map (target clock to source clock).

        Its reference is the image of `reference_ns` on the target clock, so
        `inverted().apply(t)` equals `inverse(t)` up to rounding.
        """
        d = self._rate_minus_one
        return ClockModel(
            offset_ns=-self.offset_ns,
            drift_ppm=-self.drift_ppm / (1.0 + d),
            reference_ns=self.reference_ns + self.offset_ns,
        )


def _int64_array(t: npt.ArrayLike) -> IntArray:
    arr = np.asarray(t)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"expected integer nanoseconds, got dtype {arr.dtype}")
    return arr.astype(np.int64)
