"""Keyframe selection in the manner of OKVIS / SVIn2.

Pure math, no I/O. A frame becomes a keyframe when the features it still
shares with the last keyframe cover too little of the image or are too few
a share of its features:

- overlap = area of the convex hull of the shared features / area of the
  convex hull of all the frame's features (OKVIS compares hull areas the same
  way);
- match ratio = shared features / all the frame's features.

SVIn2's thresholds are overlap <= 0.6 or match ratio <= 0.2. A minimum
interval keeps a nervous frontend from flooding the backend, and a maximum
interval bounds the IMU preintegration time (and gives a diver who hovers
still a keyframe now and then).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from postproc.slam.options import KeyframeOptions as KeyframeOptions
from postproc.slam.types import FloatArray, FrameTracks, IntArray
from shared.clock import seconds_from_ns


def _hull_area(points: FloatArray) -> float:
    if len(points) < 3:
        return 0.0
    hull = cv2.convexHull(points.astype(np.float32))
    return float(cv2.contourArea(hull))


@dataclass
class KeyframeDecision:
    """Why a frame was or was not taken: the two ratios and the verdict."""

    is_keyframe: bool
    overlap: float
    match_ratio: float
    reason: str


class KeyframeSelector:
    """Stateful keyframe rule: call `decide` on every frame in time order."""

    def __init__(self, options: KeyframeOptions) -> None:
        self.options = options
        self._last_ids: IntArray | None = None
        self._last_stamp_ns: int | None = None

    def decide(self, frame: FrameTracks) -> KeyframeDecision:
        """Whether `frame` is a keyframe; a keyframe becomes the new reference."""
        if self._last_ids is None or self._last_stamp_ns is None:
            decision = KeyframeDecision(True, 0.0, 0.0, "first frame")
        else:
            dt_s = seconds_from_ns(frame.stamp_ns - self._last_stamp_ns)
            shared = np.isin(frame.track_ids, self._last_ids)
            n = len(frame.track_ids)
            match_ratio = float(shared.sum()) / n if n else 0.0
            all_area = _hull_area(frame.pixels)
            overlap = _hull_area(frame.pixels[shared]) / all_area if all_area > 0 else 0.0
            o = self.options
            if dt_s < o.min_interval_s:
                decision = KeyframeDecision(False, overlap, match_ratio, "too soon")
            elif dt_s >= o.max_interval_s:
                decision = KeyframeDecision(True, overlap, match_ratio, "max interval")
            elif n < o.min_tracks:
                decision = KeyframeDecision(True, overlap, match_ratio, "few tracks")
            elif overlap <= o.overlap_threshold:
                decision = KeyframeDecision(True, overlap, match_ratio, "overlap")
            elif match_ratio <= o.match_ratio_threshold:
                decision = KeyframeDecision(True, overlap, match_ratio, "match ratio")
            else:
                decision = KeyframeDecision(False, overlap, match_ratio, "enough overlap")
        if decision.is_keyframe:
            self._last_ids = frame.track_ids.copy()
            self._last_stamp_ns = frame.stamp_ns
        return decision
