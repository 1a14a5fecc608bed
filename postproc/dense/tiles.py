"""Space cut into boxes of bounded work: pure geometry, no I/O.

COLMAP's fusion holds every fused point of a call in memory (about 450 bytes a point
through pycolmap), so a long dive is fused box by box: the depth maps' points are
sampled, and space is cut like a k-d tree until no box holds more depth pixels than a
budget. The boxes are half-open slabs of the cuts and together cover all of space, so
every depth pixel falls in exactly one box (COLMAP's bounding box is closed: a pixel
exactly on a cut plane, at float32, goes to both, a measure-zero case).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Box:
    """An axis-aligned box, `lo < x <= hi` per axis (m; half-open, so that boxes sharing
    a cut share no point); infinite sides allowed."""

    lo: FloatArray
    hi: FloatArray

    def contains(self, points_m: npt.ArrayLike, *, margin_m: float = 0.0) -> npt.NDArray[np.bool_]:
        """Which of the (N, 3) points lie in the box grown by `margin_m` on every side."""
        p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        inside: npt.NDArray[np.bool_] = np.all(
            (p > self.lo - margin_m) & (p <= self.hi + margin_m), axis=1
        )
        return inside


def split_boxes(points_m: npt.ArrayLike, weights: npt.ArrayLike, max_weight: float) -> list[Box]:
    """Boxes covering all of space, none holding more than `max_weight` of the weighted
    (N, 3) points unless it cannot be cut (one point, or all its points equal along
    every axis): a box over the budget is cut at the weighted median of its points along
    the axis where they spread most, and each half is cut again as needed.

    Returns the boxes in a depth-first order of the cuts (neighbouring boxes close in
    the list); one unbounded box when everything fits."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if len(w) != len(p):
        raise ValueError(f"{len(p)} points but {len(w)} weights")
    if max_weight <= 0:
        raise ValueError(f"max_weight must be positive, got {max_weight}")
    boxes: list[Box] = []
    everything = Box(np.full(3, -np.inf), np.full(3, np.inf))
    stack: list[tuple[Box, npt.NDArray[np.int64]]] = [(everything, np.arange(len(p)))]
    while stack:
        box, members = stack.pop()
        if w[members].sum() <= max_weight or len(members) < 2:
            boxes.append(box)
            continue
        q = p[members]
        spread = q.max(axis=0) - q.min(axis=0)
        axis = int(np.argmax(spread))
        if spread[axis] <= 0:
            boxes.append(box)
            continue
        order = np.argsort(q[:, axis], kind="stable")
        cumulative = np.cumsum(w[members][order])
        median = int(np.searchsorted(cumulative, 0.5 * cumulative[-1]))
        # A cut strictly inside the spread: both halves non-empty.
        cut = float(q[order[median], axis])
        if cut >= q[order[-1], axis]:
            cut = float(q[order[-2], axis])
        lower = q[:, axis] <= cut
        if lower.all() or not lower.any():
            # Many points at the cut value: cut midway between the extremes instead.
            cut = float(0.5 * (q[:, axis].min() + q[:, axis].max()))
            lower = q[:, axis] <= cut
        low_hi, high_lo = box.hi.copy(), box.lo.copy()
        low_hi[axis] = cut
        high_lo[axis] = cut
        # Pushed high first so that the low half is cut (and listed) first.
        stack.append((Box(high_lo, box.hi), members[~lower]))
        stack.append((Box(box.lo, low_hi), members[lower]))
    return boxes
