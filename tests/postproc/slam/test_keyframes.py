"""The OKVIS/SVIn2-style keyframe rule."""

from __future__ import annotations

import numpy as np

from postproc.slam.keyframes import KeyframeOptions, KeyframeSelector
from postproc.slam.types import FrameTracks


def _frame(stamp_s: float, ids: np.ndarray, pixels: np.ndarray) -> FrameTracks:
    return FrameTracks(
        stamp_ns=round(stamp_s * 1e9),
        track_ids=ids.astype(np.int64),
        xy_normalised=pixels / 500.0,
        pixels=pixels.astype(np.float64),
        image_size=(960, 540),
    )


def _grid(n: int, x0: float, x1: float) -> np.ndarray:
    xs, ys = np.meshgrid(np.linspace(x0, x1, n), np.linspace(10, 530, n))
    return np.column_stack([xs.ravel(), ys.ravel()])


def test_overlap_drop_makes_a_keyframe() -> None:
    selector = KeyframeSelector(KeyframeOptions(min_interval_s=0.4, max_interval_s=5.0))
    pixels = _grid(10, 10, 950)
    ids = np.arange(100)
    assert selector.decide(_frame(0.0, ids, pixels)).reason == "first frame"
    # Too soon, whatever the content.
    assert selector.decide(_frame(0.2, ids + 1000, pixels)).reason == "too soon"
    # Same features: full overlap, no keyframe.
    same = selector.decide(_frame(0.5, ids, pixels))
    assert not same.is_keyframe and same.overlap > 0.99 and same.match_ratio == 1.0
    assert same.reason == "enough overlap"
    # Left half of the image still shared (overlap ~0.5), right half new.
    shared = pixels[:, 0] < 480
    new_ids = np.where(shared, ids, ids + 1000)
    decision = selector.decide(_frame(0.7, new_ids, pixels))
    assert decision.is_keyframe and decision.reason == "overlap"
    assert 0.4 < decision.overlap < 0.6


def test_match_ratio_and_intervals() -> None:
    options = KeyframeOptions(
        overlap_threshold=0.0, min_interval_s=0.1, max_interval_s=2.0, min_tracks=5
    )
    selector = KeyframeSelector(options)
    pixels = _grid(10, 10, 950)
    ids = np.arange(100)
    selector.decide(_frame(0.0, ids, pixels))
    # 15 % of the features shared, spread over the image: the overlap stays high.
    mixed = np.where(np.arange(100) % 7 == 0, ids, ids + 5000)
    decision = selector.decide(_frame(0.5, mixed, pixels))
    assert decision.reason == "match ratio"
    # Nothing changes for a long time: the maximum interval forces one.
    assert selector.decide(_frame(1.0, mixed, pixels)).is_keyframe is False
    assert selector.decide(_frame(2.6, mixed, pixels)).reason == "max interval"
    # Almost nothing tracked: keyframe as soon as allowed.
    assert selector.decide(_frame(2.8, mixed[:3], pixels[:3])).reason == "few tracks"
