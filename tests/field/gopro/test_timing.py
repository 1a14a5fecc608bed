"""Per-sample times: STMP anchors and the TSMP fit, with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from field.gopro.timing import PayloadSamples, first_sample_indices, stream_times
from shared.errors import InputError


def jittered_payloads(
    *, rate_hz: float, t0_s: float, n_payloads: int, last_samples: int, seed: int, stmp: bool
) -> tuple[list[PayloadSamples], np.ndarray]:
    """Payloads every 1.001 s, flushed with jitter; the last one is cut short but declares
    a full 1.001 s (as when the video stops mid-payload). Returns them and the true times."""
    rng = np.random.default_rng(seed)
    starts = np.arange(n_payloads) * 1.001
    # The camera flushes whatever arrived before (payload end + jitter).
    flush = starts + 1.001 + rng.uniform(-0.01, 0.01, n_payloads)
    k_end = np.floor((flush - t0_s) * rate_hz).astype(int)
    firsts = np.concatenate([[0], k_end[:-1]])
    counts = np.diff(np.concatenate([firsts, [firsts[-1] + last_samples]]))
    payloads = []
    for p in range(n_payloads):
        payloads.append(
            PayloadSamples(
                start_s=float(starts[p]),
                duration_s=1.001,
                samples=int(counts[p]),
                total_samples=int(firsts[p] + counts[p]),
                timestamp_us=round((t0_s + firsts[p] / rate_hz) * 1e6) if stmp else None,
            )
        )
    truth = t0_s + np.arange(int(firsts[-1] + last_samples)) / rate_hz
    return payloads, truth


def test_tsmp_fit_recovers_rate_and_times_despite_short_last_payload() -> None:
    payloads, truth = jittered_payloads(
        rate_hz=198.6, t0_s=0.004, n_payloads=13, last_samples=14, seed=1, stmp=False
    )
    timing = stream_times(payloads)
    assert timing.method == "tsmp"
    assert timing.rate_hz == pytest.approx(198.6, rel=1.5e-3)  # +-10 ms jitter over 12 s
    # Within a few ms everywhere (flush jitter is +-10 ms, averaged by the fit).
    assert np.max(np.abs(timing.times_s - truth)) < 0.008
    # Using the last payload's declared end would have given a rate off by ~7 %:
    naive = sum(p.samples for p in payloads) / (13 * 1.001)
    assert abs(naive - 198.6) > 10


def test_stmp_anchors_are_exact_and_last_payload_continues() -> None:
    payloads, truth = jittered_payloads(
        rate_hz=197.46, t0_s=0.0806, n_payloads=11, last_samples=105, seed=2, stmp=True
    )
    timing = stream_times(payloads, stmp_origin_us=85608)
    assert timing.method == "stmp"
    np.testing.assert_allclose(timing.times_s, truth - 0.085608, atol=2e-6)
    firsts = first_sample_indices(payloads)
    for p, k in zip(payloads, firsts, strict=True):
        assert p.timestamp_us is not None
        assert timing.times_s[k] == pytest.approx(p.timestamp_us * 1e-6 - 0.085608, abs=1e-12)
    assert timing.rate_hz == pytest.approx(197.46, rel=1e-5)


def test_stmp_can_be_ignored() -> None:
    payloads, _ = jittered_payloads(
        rate_hz=200, t0_s=0.0, n_payloads=5, last_samples=50, seed=3, stmp=True
    )
    assert stream_times(payloads, use_stmp=False).method == "tsmp"


def test_tsmp_offset_of_first_payload_is_removed() -> None:
    """HERO11 files start TSMP above the first payload's count (samples before the video)."""
    payloads = [
        PayloadSamples(start_s=0.0, duration_s=1.0, samples=200, total_samples=410),
        PayloadSamples(start_s=1.0, duration_s=1.0, samples=200, total_samples=610),
    ]
    assert first_sample_indices(payloads).tolist() == [0, 200]
    timing = stream_times(payloads)
    np.testing.assert_allclose(timing.times_s[[0, 200, 399]], [0.0, 1.0, 399 / 200])


def test_without_tsmp_counts_are_summed_and_single_payload_uses_its_duration() -> None:
    payloads = [PayloadSamples(start_s=0.5, duration_s=1.0, samples=4)]
    timing = stream_times(payloads)
    np.testing.assert_allclose(timing.times_s, [0.5, 0.75, 1.0, 1.25])
    with_stmp = [PayloadSamples(start_s=0.0, duration_s=1.0, samples=2, timestamp_us=2_000_000)]
    np.testing.assert_allclose(
        stream_times(with_stmp, stmp_origin_us=1_000_000).times_s, [1.0, 1.5]
    )


def test_bad_streams_raise() -> None:
    with pytest.raises(InputError, match="no samples"):
        stream_times([PayloadSamples(start_s=0, duration_s=1, samples=0)], source="x.mp4: ACCL")
    backwards = [
        PayloadSamples(start_s=0, duration_s=1, samples=10, total_samples=100),
        PayloadSamples(start_s=1, duration_s=1, samples=10, total_samples=50),
    ]
    with pytest.raises(InputError, match="TSMP goes backwards"):
        stream_times(backwards)
    stuck = [
        PayloadSamples(start_s=0, duration_s=1, samples=10, timestamp_us=5),
        PayloadSamples(start_s=1, duration_s=1, samples=10, timestamp_us=5),
    ]
    with pytest.raises(InputError, match="STMP does not increase"):
        stream_times(stuck)
    with pytest.raises(InputError, match="single payload with duration 0"):
        stream_times([PayloadSamples(start_s=0, duration_s=0, samples=3)])
    same_time = [
        PayloadSamples(start_s=1, duration_s=1, samples=10),
        PayloadSamples(start_s=1, duration_s=1, samples=10),
        PayloadSamples(start_s=1, duration_s=1, samples=10),
    ]
    with pytest.raises(InputError, match="do not advance"):
        stream_times(same_time)
