"""Clock mapping, clock fits and key-frame detection (pure math)."""

from __future__ import annotations

import numpy as np
import pytest

from field.record.timing import ClockFit, DeviceClockMapper, is_keyframe


def test_mapper_fixes_one_offset_and_keeps_device_rate() -> None:
    mapper = DeviceClockMapper()
    host0 = 1_700_000_000_000_000_000
    first = mapper.to_epoch(5_000_000_000, host0)
    assert first == host0
    # Later readings keep the device's own spacing exactly (no drift correction).
    assert mapper.to_epoch(5_000_000_000 + 123_456_789, host0 + 999) == host0 + 123_456_789
    mapper.reset()
    assert mapper.to_epoch(7, 100) == 100
    assert [m.offset_ns for m in mapper.offsets] == [host0 - 5_000_000_000, 93]


def test_clock_fit_recovers_offset_and_drift() -> None:
    rng = np.random.default_rng(4)
    fit = ClockFit()
    assert fit.estimate() is None
    source0 = 1_700_000_000_000_000_000
    offset_ns, drift_ppm = 12_345_678, -31.5
    for k in range(4000):  # 10 s at 400 Hz
        s = source0 + k * 2_500_000
        noise = rng.normal(0.0, 20_000.0)  # 20 us of jitter
        fit.add(s, s + offset_ns + round(drift_ppm * 1e-6 * (s - source0) + noise))
    est = fit.estimate()
    assert est is not None and est.samples == 4000
    assert est.model.reference_ns == source0
    assert abs(est.model.offset_ns - offset_ns) < 3_000
    assert est.model.drift_ppm == pytest.approx(drift_ppm, abs=1.0)
    assert est.residual_rms_ns == pytest.approx(20_000.0, rel=0.1)
    assert est.span_s == pytest.approx(9.9975)


def test_clock_fit_with_one_pair_is_an_offset() -> None:
    fit = ClockFit()
    fit.add(10, 25)
    est = fit.estimate()
    assert est is not None
    assert (est.model.offset_ns, est.model.drift_ppm, est.residual_rms_ns) == (15, 0.0, 0.0)


def test_keyframe_detection_h264_h265_jpeg() -> None:
    sps_pps_idr = (
        b"\x00\x00\x00\x01\x67\x42" + b"\x00\x00\x00\x01\x68\xce" + b"\x00\x00\x01\x65\x88"
    )
    p_slice = b"\x00\x00\x00\x01\x41\x9a\x00"
    assert is_keyframe(sps_pps_idr, "h264")
    assert not is_keyframe(p_slice, "h264")
    # H.265: NAL type in bits 1-6 of the first header byte; 19 = IDR_W_RADL, 1 = TRAIL_R.
    assert is_keyframe(b"\x00\x00\x01\x40\x01" + b"\x00\x00\x01" + bytes([19 << 1, 1]), "h265")
    assert not is_keyframe(b"\x00\x00\x01" + bytes([1 << 1, 1]), "h265")
    assert is_keyframe(b"\xff\xd8anything", "jpeg")
    assert not is_keyframe(b"\x00\x00\x01\x65", "vp9")
    assert not is_keyframe(b"", "h264")
