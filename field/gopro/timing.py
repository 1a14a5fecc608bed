"""Per-sample times of GPMF streams on the video's clock (pure math, no I/O).

Time base: media time in seconds from the start of the video (the MP4 movie
timeline; GoPro's video and 'gpmd' tracks both start at 0 with no edit
offset). Payload p of the 'gpmd' track starts at `t_p` (stts decode time /
timescale) and declares a duration `d_p`; it holds `n_p` samples of a stream
whose running total after it is `TSMP_p`, so its first sample has the global
index

    K_p = TSMP_p - n_p - (TSMP_0 - n_0)        (0 for the first payload)

(without TSMP, K_p is the running sum of n_p). Sample k of payload p has the
global index K_p + k.

Method 1, STMP (HERO8+, MAX, Fusion): STMP_p is the time, in microseconds on
the camera's sensor clock, of the first sample of payload p. That clock starts
before the video, so we subtract an origin found from a stream locked to
video frames when there is one (CORI: one sample per frame, STMP = start of
the frame, per GoPro; the first CORI sample of payload q is the frame at the
payload's media time t_q), else 0:

    STMP_origin = STMP_CORI,q - t_q * 1e6      (q: first payload holding CORI)
    T_p = (STMP_p - STMP_origin) / 1e6
    t(K) = T_p + (K - K_p) * (T_{p+1} - T_p) / (K_{p+1} - K_p)   for K_p <= K < K_{p+1}

i.e. exact at every payload's first sample and linear in between; samples of
the last payload continue with the mean period of the complete payloads,
`(T_last - T_0) / (K_last - K_0)`.

Method 2, TSMP and the MP4 sample table (HERO5-7): the payload boundaries are
only roughly where the samples are (the camera flushes about once a second),
but the sample clock is steady, so we fit one line through the payload starts
by least squares, K_p ~ r * (t_p - t_0) over every payload p, and use

    t(K) = t_0 + K / r,     rate r in Hz.

Only payload *starts* enter the fit: the last payload is usually declared
longer than the samples it holds (the video stopped mid-payload), so its end
must not be used. With a single payload, r = n_0 / d_0 and the first sample
is at t_0 (or at its STMP time when it has one).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from shared.errors import InputError


@dataclass(frozen=True, kw_only=True)
class PayloadSamples:
    """What one payload says about one stream.

    `start_s`/`duration_s`: the payload's media time and declared duration
    (seconds, from the MP4 'gpmd' track); `samples`: n_p; `total_samples`:
    TSMP (None when absent); `timestamp_us`: STMP (None when absent).
    """

    start_s: float
    duration_s: float
    samples: int
    total_samples: int | None = None
    timestamp_us: int | None = None


@dataclass(frozen=True, kw_only=True)
class StreamTiming:
    """Sample times of one stream: `times_s` (media seconds, float64, one per
    sample), the mean sampling `rate_hz` and the `method` used ("stmp" or "tsmp").
    """

    times_s: np.ndarray
    rate_hz: float
    method: str


def first_sample_indices(payloads: Sequence[PayloadSamples]) -> np.ndarray:
    """K_p: the global index of each payload's first sample (int64), from TSMP when
    every payload has it, else the running sum of the sample counts."""
    counts = np.array([p.samples for p in payloads], dtype=np.int64)
    totals = [p.total_samples for p in payloads]
    if payloads and all(t is not None for t in totals):
        tsmp = np.array(totals, dtype=np.int64)
        firsts: np.ndarray = tsmp - counts
        shifted: np.ndarray = firsts - firsts[0]
        return shifted
    summed: np.ndarray = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    return summed


def stream_times(
    payloads: Sequence[PayloadSamples],
    *,
    stmp_origin_us: int | None = 0,
    use_stmp: bool = True,
    source: str = "<stream>",
) -> StreamTiming:
    """Times of every sample of a stream (see the module docstring for the formulas).

    Uses STMP when every payload with samples has one and `use_stmp` is true
    (origin `stmp_origin_us`, the STMP of video frame 0), else the TSMP fit.
    Raises `InputError` when the stream has no samples or its sample counter
    goes backwards.
    """
    payloads = [p for p in payloads if p.samples > 0]
    if not payloads:
        raise InputError(f"{source}: stream has no samples")
    counts = np.array([p.samples for p in payloads], dtype=np.int64)
    firsts = first_sample_indices(payloads)
    if np.any(np.diff(firsts) < 0):
        raise InputError(f"{source}: TSMP goes backwards (expected a growing sample count)")
    total = int(firsts[-1] + counts[-1])
    indices = np.concatenate([firsts[i] + np.arange(n) for i, n in enumerate(counts)])
    stamps = [p.timestamp_us for p in payloads]
    if use_stmp and len(payloads) >= 2 and all(s is not None for s in stamps):
        anchors_s = (np.array(stamps, dtype=np.float64) - float(stmp_origin_us or 0)) * 1e-6
        return _times_from_anchors(indices, firsts, anchors_s, counts, total, source)
    starts = np.array([p.start_s for p in payloads], dtype=np.float64)
    if len(payloads) == 1:
        duration = payloads[0].duration_s
        if duration <= 0:
            raise InputError(f"{source}: single payload with duration {duration} s")
        rate = counts[0] / duration
        t0 = starts[0]
        if use_stmp and stamps[0] is not None:
            t0 = (stamps[0] - (stmp_origin_us or 0)) * 1e-6
            return StreamTiming(times_s=t0 + indices / rate, rate_hz=float(rate), method="stmp")
    else:
        # Least-squares line K = r * (t - t_0) through the payload starts.
        t_mean = starts.mean()
        k_mean = firsts.mean()
        spread = float(np.sum((starts - t_mean) ** 2))
        slope = float(np.sum((starts - t_mean) * (firsts - k_mean))) / spread if spread else 0.0
        if slope <= 0:
            raise InputError(f"{source}: samples do not advance with the payload times")
        rate = slope
        t0 = float(t_mean - k_mean / rate)
    return StreamTiming(times_s=t0 + indices / rate, rate_hz=float(rate), method="tsmp")


def _times_from_anchors(
    indices: np.ndarray,
    firsts: np.ndarray,
    anchors_s: np.ndarray,
    counts: np.ndarray,
    total: int,
    source: str,
) -> StreamTiming:
    span_s = anchors_s[-1] - anchors_s[0]
    span_k = firsts[-1] - firsts[0]
    if span_s <= 0 or span_k <= 0:
        raise InputError(f"{source}: STMP does not increase between payloads")
    period = span_s / span_k
    # Anchor past the end so the last payload continues with the mean period.
    knots_k = np.append(firsts, total).astype(np.float64)
    knots_t = np.append(anchors_s, anchors_s[-1] + counts[-1] * period)
    times = np.interp(indices.astype(np.float64), knots_k, knots_t)
    return StreamTiming(times_s=times, rate_hz=float(1.0 / period), method="stmp")
