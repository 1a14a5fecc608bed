"""Space cut into boxes of bounded weight (the tiles of a long dive's fusion)."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.dense.tiles import Box, split_boxes


def owners(boxes: list[Box], points: np.ndarray) -> np.ndarray:
    """For each point, how many boxes hold it."""
    counts: np.ndarray = np.sum([box.contains(points) for box in boxes], axis=0)
    return counts


def test_boxes_cover_space_once_and_keep_to_the_budget() -> None:
    rng = np.random.default_rng(4)
    # A long hull: 40 m by 6 m by 8 m, denser at one end.
    points = rng.uniform([0, 0, 0], [40, 6, 8], (20000, 3))
    points[:5000, 0] *= 0.1
    weights = rng.uniform(10, 20, len(points))
    boxes = split_boxes(points, weights, 0.2 * weights.sum())
    assert 5 <= len(boxes) <= 8
    assert np.all(owners(boxes, points) == 1)  # continuous coordinates: no point on a cut
    for box in boxes:
        assert weights[box.contains(points)].sum() <= 0.2 * weights.sum()
    # Points never seen (outside the samples' hull) fall in exactly one box too.
    far = rng.uniform(-1000, 1000, (2000, 3))
    assert np.all(owners(boxes, far) == 1)
    # The first cut is across the long axis, and the first box starts at its end.
    assert np.isfinite(boxes[0].hi[0]) and np.isinf(boxes[0].lo).all()


def test_everything_in_budget_is_one_unbounded_box() -> None:
    points = np.random.default_rng(1).normal(size=(100, 3))
    boxes = split_boxes(points, np.ones(100), 100)
    assert len(boxes) == 1 and np.all(np.isinf(boxes[0].lo)) and np.all(np.isinf(boxes[0].hi))
    assert len(split_boxes(np.zeros((0, 3)), np.zeros(0), 1)) == 1


def test_boxes_that_cannot_be_cut_are_kept_whole() -> None:
    # 50 copies of one point over the budget, and a heavy point beside a light one.
    points = np.vstack([np.ones((50, 3)), [[0.0, 0, 0], [5.0, 0, 0]]])
    weights = np.concatenate([np.ones(50), [100.0, 1.0]])
    boxes = split_boxes(points, weights, 10)
    assert np.all(owners(boxes, points) == 1)
    heavy = [b for b in boxes if b.contains(points[:1]).all()]
    assert len(heavy) == 1 and weights[heavy[0].contains(points)].sum() == 50


def test_margin_and_bad_arguments() -> None:
    box = Box(np.array([0.0, 0, 0]), np.array([1.0, 1, 1]))
    near = np.array([[1.05, 0.5, 0.5]])
    assert not box.contains(near)[0] and box.contains(near, margin_m=0.1)[0]
    with pytest.raises(ValueError, match="weights"):
        split_boxes(np.zeros((3, 3)), np.ones(2), 1)
    with pytest.raises(ValueError, match="positive"):
        split_boxes(np.zeros((3, 3)), np.ones(3), 0)
