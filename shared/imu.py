"""IMU samples, and IMU rows as real recorders write them made into one such stream.

Pure computation, no I/O. `ImuSamples` is the one IMU type of the tree: stamps on
the IMU clock (int64 ns since the UNIX epoch), gyro in rad/s, specific force in
m/s^2, in the IMU (body) frame. `clean_imu_rows` makes one from raw rows; what real
streams hold, and what becomes of it:

- rows that repeat a stamp: a recorder that writes a message twice, or a stream
  merged from separate gyro and accelerometer sensors that writes each sensor's
  sample as its own row at a shared stamp. Rows with one stamp become one row, each
  channel the mean of the rows that carry it (NaN where a row lacks a channel);
- rows whose stamp goes back in time (out of order): dropped (a clock jump or a
  re-sent message; reordering them could fold two clock bases into one stream);
- a channel missing (NaN) in a row: the gyro and accelerometer of a merged stream
  tick at different instants, so a row carries one of them; the other is
  interpolated linearly in time from its neighbours. A row with neither is dropped,
  and so are rows before one sensor's first sample or after its last.

Irregular stamps and sub-millisecond gaps need nothing: preintegration cuts its
intervals at every sample (`postproc.slam.backend.imu_intervals`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
LOG = logging.getLogger(__name__)


@dataclass
class ImuSamples:
    """IMU measurements in the body frame, on the IMU clock.

    stamps_ns: (M,) int64 ns, strictly increasing.
    gyro_rad_s: (M, 3) angular rate (rad/s).
    accel_m_s2: (M, 3) specific force (m/s^2; reads +9.81 upwards at rest).
    """

    stamps_ns: IntArray
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray

    def __post_init__(self) -> None:
        m = len(self.stamps_ns)
        if self.gyro_rad_s.shape != (m, 3) or self.accel_m_s2.shape != (m, 3):
            raise ValueError(
                f"ImuSamples: expected ({m}, 3) gyro and accel, got {self.gyro_rad_s.shape} "
                f"and {self.accel_m_s2.shape}"
            )
        if m > 1 and np.any(np.diff(self.stamps_ns) <= 0):
            raise ValueError("ImuSamples: stamps_ns must be strictly increasing")

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass
class ImuCleaning:
    """What `clean_imu_rows` changed (counts of rows)."""

    rows_in: int = 0
    duplicate_rows: int = 0
    out_of_order_rows: int = 0
    empty_rows: int = 0
    edge_rows: int = 0
    interpolated_values: int = 0

    @property
    def changed(self) -> bool:
        """Whether anything was dropped, merged or filled in."""
        return bool(
            self.duplicate_rows
            or self.out_of_order_rows
            or self.empty_rows
            or self.edge_rows
            or self.interpolated_values
        )

    def as_stats(self) -> dict[str, int]:
        """The stats.json entries."""
        return {
            "imu_rows": self.rows_in,
            "imu_duplicate_rows_merged": self.duplicate_rows,
            "imu_out_of_order_rows_dropped": self.out_of_order_rows,
            "imu_empty_rows_dropped": self.empty_rows,
            "imu_edge_rows_dropped": self.edge_rows,
            "imu_values_interpolated": self.interpolated_values,
        }

    def describe(self) -> str:
        """One line for a warning."""
        return (
            f"{self.duplicate_rows} rows repeating a stamp merged, {self.out_of_order_rows} "
            f"out-of-order rows dropped, {self.empty_rows} empty rows and {self.edge_rows} rows "
            "beyond the other sensor's span dropped, "
            f"{self.interpolated_values} missing gyro/accel values interpolated "
            f"(of {self.rows_in} rows)"
        )


def clean_imu_rows(
    stamps_ns: IntArray, gyro_rad_s: FloatArray, accel_m_s2: FloatArray, *, name: str = "IMU"
) -> tuple[ImuSamples, ImuCleaning]:
    """A strictly increasing `ImuSamples` from raw rows in file order (see module doc).

    stamps_ns (M,) int64; gyro_rad_s, accel_m_s2 (M, 3), NaN where a row lacks the
    channel. Logs one warning naming `name` when anything was changed. Raises
    ValueError when a channel has no value at all.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    gyro = np.asarray(gyro_rad_s, dtype=np.float64).reshape(-1, 3)
    accel = np.asarray(accel_m_s2, dtype=np.float64).reshape(-1, 3)
    report = ImuCleaning(rows_in=len(stamps))
    if not len(stamps):
        return ImuSamples(stamps, gyro, accel), report
    # Out of order: behind the latest stamp seen so far (equal stamps are merged below).
    running_max = np.maximum.accumulate(stamps)
    in_order = stamps >= running_max
    report.out_of_order_rows = int((~in_order).sum())
    stamps, gyro, accel = stamps[in_order], gyro[in_order], accel[in_order]
    # Rows sharing a stamp (adjacent now: the kept stamps never decrease): one row, each
    # channel the mean of the rows that carry it.
    unique, counts = np.unique(stamps, return_counts=True)
    report.duplicate_rows = int(len(stamps) - len(unique))
    if report.duplicate_rows:
        group = np.repeat(np.arange(len(unique)), counts)
        gyro = _group_nanmean(gyro, group, len(unique))
        accel = _group_nanmean(accel, group, len(unique))
        stamps = unique
    else:
        gyro, accel = gyro.copy(), accel.copy()
    # Rows with neither sensor: nothing to keep.
    has_gyro = np.all(np.isfinite(gyro), axis=1)
    has_accel = np.all(np.isfinite(accel), axis=1)
    keep = has_gyro | has_accel
    report.empty_rows = int((~keep).sum())
    stamps, gyro, accel = stamps[keep], gyro[keep], accel[keep]
    has_gyro, has_accel = has_gyro[keep], has_accel[keep]
    for has, what in ((has_gyro, "gyro"), (has_accel, "accelerometer")):
        if not has.any():
            raise ValueError(f"{name}: no {what} value in any row")
    for values, has in ((gyro, has_gyro), (accel, has_accel)):
        missing = ~has
        if missing.any():
            t = (stamps - stamps[0]).astype(np.float64)
            for axis in range(3):
                values[missing, axis] = np.interp(t[missing], t[has], values[has, axis])
    # Rows before one sensor's first sample or after its last cannot be interpolated.
    lo = max(stamps[has_gyro][0], stamps[has_accel][0])
    hi = min(stamps[has_gyro][-1], stamps[has_accel][-1])
    inside = (stamps >= lo) & (stamps <= hi)
    report.edge_rows = int((~inside).sum())
    report.interpolated_values = int((~(has_gyro & has_accel) & inside).sum())
    stamps, gyro, accel = stamps[inside], gyro[inside], accel[inside]
    if report.changed:
        LOG.warning("%s: %s", name, report.describe())
    return ImuSamples(stamps, gyro, accel), report


def _group_nanmean(values: FloatArray, group: IntArray, groups: int) -> FloatArray:
    """Per-group mean of (N, 3) values ignoring NaN (NaN where a group has none)."""
    finite = np.isfinite(values)
    sums = np.zeros((groups, 3))
    counts = np.zeros((groups, 3))
    np.add.at(sums, group, np.where(finite, values, 0.0))
    np.add.at(counts, group, finite)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean: FloatArray = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return mean
