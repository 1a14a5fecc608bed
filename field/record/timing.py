"""Clock math for live sources: device clock to epoch, and the fit of one clock to another.

Pure math, no I/O. Every time is int64 nanoseconds.

A camera such as the OAK stamps its samples on its own clock (nanoseconds since the
device booted). The archive keeps the sensor clock in `header.stamp` (conventions.md),
but as nanoseconds since the epoch, so the raw device reading is shifted by one constant
offset chosen at the first sample (`DeviceClockMapper`): rate, drift and jitter of the
device clock stay exactly as recorded. How that clock really relates to the host clock
(offset and drift, with the residual) is estimated on the side by `ClockFit` and stored
in session.yaml, never applied silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shared.clock import ClockModel, seconds_from_ns


class DeviceClockMapper:
    """Map raw device-clock readings (ns since device boot) to epoch ns by one fixed offset.

    The offset is `host_ns - device_ns` of the first sample seen (`observe`; pass the best
    host-clock estimate of the capture time, e.g. DepthAI's host-synced stamp, so the
    offset holds no transport latency), so the mapped stamps are on the device clock,
    merely moved to the epoch. `reset()` forgets it (a
    device that rebooted restarts its clock, so a reconnection picks a new offset; the new
    offset is kept in `offsets` so the change is visible in session.yaml).
    """

    def __init__(self) -> None:
        self.model: ClockModel | None = None
        self.offsets: list[ClockModel] = []

    def observe(self, device_ns: int, host_ns: int) -> ClockModel:
        """Fix the offset from this (device, host) pair if none is fixed yet; the model in use."""
        if self.model is None:
            self.model = ClockModel(offset_ns=int(host_ns) - int(device_ns), reference_ns=device_ns)
            self.offsets.append(self.model)
        return self.model

    def to_epoch(self, device_ns: int, host_ns: int) -> int:
        """The device reading `device_ns` as ns since the epoch on the device clock."""
        return self.observe(device_ns, host_ns).apply(int(device_ns))

    def reset(self) -> None:
        """Forget the offset (after a reconnection: the device clock may have restarted)."""
        self.model = None


@dataclass(frozen=True)
class ClockEstimate:
    """A fitted relation `target = source + offset + drift` with its quality.

    model: the affine map (source clock -> target clock); residual_rms_ns: RMS of the
    fit residuals; samples: pairs used; span_s: source-clock time covered by them.
    """

    model: ClockModel
    residual_rms_ns: float
    samples: int
    span_s: float

    def as_dict(self) -> dict[str, float | int]:
        return {
            "offset_ns": self.model.offset_ns,
            "drift_ppm": round(self.model.drift_ppm, 4),
            "reference_ns": self.model.reference_ns,
            "residual_rms_ns": round(self.residual_rms_ns, 1),
            "samples": self.samples,
            "span_s": round(self.span_s, 3),
        }


class ClockFit:
    """Online least-squares fit of `target_ns - source_ns = offset + drift * (source - ref)`.

    Constant memory: only running sums are kept (in float64 on values made small by
    subtracting the first pair), so it can run for a whole dive at IMU rate.
    """

    def __init__(self) -> None:
        self._ref_ns: int | None = None
        self._y0_ns = 0
        self._n = 0
        self._sx = self._sy = self._sxx = self._sxy = self._syy = 0.0
        self._x_max = 0.0

    def add(self, source_ns: int, target_ns: int) -> None:
        """One pair of readings of the two clocks for the same event."""
        if self._ref_ns is None:
            self._ref_ns = int(source_ns)
            self._y0_ns = int(target_ns) - int(source_ns)
        x = seconds_from_ns(int(source_ns) - self._ref_ns)
        y = float(int(target_ns) - int(source_ns) - self._y0_ns)  # ns
        self._n += 1
        self._sx += x
        self._sy += y
        self._sxx += x * x
        self._sxy += x * y
        self._syy += y * y
        self._x_max = max(self._x_max, abs(x))

    @property
    def samples(self) -> int:
        return self._n

    def estimate(self) -> ClockEstimate | None:
        """The fit so far (None before the first pair; drift 0 until the pairs span time)."""
        if self._ref_ns is None or self._n == 0:
            return None
        n = self._n
        var_x = self._sxx - self._sx * self._sx / n
        if n >= 3 and var_x > 1e-12:
            slope = (self._sxy - self._sx * self._sy / n) / var_x  # ns per s
            intercept = (self._sy - slope * self._sx) / n
        else:
            slope = 0.0
            intercept = self._sy / n
        # Residual sum of squares from the running sums.
        rss = (
            self._syy
            - 2 * intercept * self._sy
            - 2 * slope * self._sxy
            + n * intercept * intercept
            + 2 * intercept * slope * self._sx
            + slope * slope * self._sxx
        )
        rms = math.sqrt(max(rss, 0.0) / n)
        model = ClockModel(
            offset_ns=self._y0_ns + round(intercept),
            drift_ppm=slope * 1e-3,  # slope is ns of offset per s of source time
            reference_ns=self._ref_ns,
        )
        return ClockEstimate(model=model, residual_rms_ns=rms, samples=n, span_s=self._x_max)


def is_keyframe(data: bytes, video_format: str) -> bool:
    """True when an Annex B access unit holds an IDR (H.264) or IRAP (H.265) picture.

    JPEG stills ("jpeg", "mjpeg") are all key frames. Unknown formats: False.
    """
    fmt = video_format.lower()
    if fmt in ("jpeg", "jpg", "mjpeg"):
        return True
    if fmt not in ("h264", "h265", "hevc"):
        return False
    view = memoryview(data)
    start = 0
    size = len(view)
    while True:
        i = data.find(b"\x00\x00\x01", start)
        if i < 0 or i + 3 >= size:
            return False
        header = view[i + 3]
        if fmt == "h264":
            if header & 0x1F == 5:
                return True
        elif 16 <= (header >> 1) & 0x3F <= 21:
            return True
        start = i + 3
