"""Underwater colour correction: the water model is recovered and undone."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from postproc.dense.colmap_io import FusionVisibility, PinholeView
from postproc.dense.colour import (
    ColourOptions,
    WaterEstimate,
    correct_colours,
    correct_fused,
    estimate_water,
    point_ranges_m,
)
from shared.errors import StageError
from shared.formats.ply import PlyData, read_ply, write_ply

BETA = (0.40, 0.13, 0.11)
B = (0.02, 0.13, 0.16)


def seen_through_water(
    rng: np.random.Generator, n: int, spread: tuple[float, float] = (0.1, 0.7)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo linear (n,3), ranges (n,), observed uint8 colours) under the water model."""
    albedo = rng.uniform(*spread, (n, 3)) * rng.uniform(0.6, 1.0, (n, 1))
    ranges = rng.uniform(0.8, 6.0, n)
    t = np.exp(-np.array(BETA)[None] * ranges[:, None])
    lin = albedo * t + np.array(B)[None] * (1 - t)
    observed = np.round(255 * np.clip(lin, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    return albedo, ranges, observed


def test_estimate_recovers_the_water() -> None:
    # A scene of similar albedos: the water's parameters are identifiable.
    albedo, ranges, observed = seen_through_water(np.random.default_rng(0), 6000, (0.35, 0.45))
    water = estimate_water(observed, ranges)
    # Red fades fast and is identified; green and blue (0.13, 0.11 /m over 1-6 m) bend so
    # little that attenuation and backscatter trade off (their curves are checked below).
    assert water.attenuation_per_m[0] == pytest.approx(BETA[0], rel=0.1)
    assert water.backscatter[0] == pytest.approx(B[0], abs=0.02)
    assert water.albedo[0] == pytest.approx(np.median(albedo[:, 0]), rel=0.1)


def test_estimated_curve_fits_a_varied_scene() -> None:
    # Albedos from 0.06 to 0.7: (A, B, beta) trade off against each other, but the fitted
    # curve of median intensity against range must still be the true one.
    albedo, ranges, observed = seen_through_water(np.random.default_rng(0), 6000)
    water = estimate_water(observed, ranges)
    r = np.linspace(1.0, 6.0, 50)
    for c in range(3):
        true_t, fit_t = np.exp(-BETA[c] * r), np.exp(-water.attenuation_per_m[c] * r)
        median_albedo = np.median(albedo[:, c])
        truth = median_albedo * true_t + B[c] * (1 - true_t)
        fit = water.albedo[c] * fit_t + water.backscatter[c] * (1 - fit_t)
        np.testing.assert_allclose(fit, truth, atol=0.015)


def test_correction_removes_the_range_dependence() -> None:
    albedo, ranges, observed = seen_through_water(np.random.default_rng(1), 5000)
    water = WaterEstimate(attenuation_per_m=BETA, backscatter=B, albedo=(0.4,) * 3, estimated=False)
    corrected = correct_colours(observed, ranges, water, white_balance=False)
    lin = (corrected / 255.0) ** 2.2
    near = ranges < 4.0  # beyond, 8-bit quantisation of a dark red dominates
    np.testing.assert_allclose(lin[near], albedo[near], atol=0.05)
    # Before correction red fades with range; after, it does not.
    before = np.corrcoef(ranges, (observed[:, 0] / 255.0) ** 2.2 / albedo[:, 0])[0, 1]
    after = np.corrcoef(ranges[near], lin[near, 0] / albedo[near, 0])[0, 1]
    assert before < -0.8 and abs(after) < 0.2


def test_white_balance_equalises_channels() -> None:
    _, ranges, observed = seen_through_water(np.random.default_rng(2), 3000)
    water = estimate_water(observed, ranges)
    corrected = correct_colours(observed, ranges, water, white_balance=True)
    medians = np.median((corrected / 255.0) ** 2.2, axis=0)
    assert medians.max() / medians.min() < 1.1


def test_estimate_refuses_weak_data() -> None:
    rng = np.random.default_rng(3)
    _, ranges, observed = seen_through_water(rng, 30)
    with pytest.raises(StageError, match="at least 50"):
        estimate_water(observed, ranges)
    _, _, observed = seen_through_water(rng, 500)
    with pytest.raises(StageError, match="too little"):
        estimate_water(observed, np.full(500, 2.0))


def test_correct_fused_uses_the_visibility(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    albedo, _, _ = seen_through_water(rng, 400)
    centres = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    points = np.column_stack(
        (rng.uniform(0, 1, 400), rng.uniform(-1, 1, 400), rng.uniform(1, 5, 400))
    )
    vis = [np.array([0, 1], np.uint32) if k % 2 else np.array([0], np.uint32) for k in range(400)]
    ranges = point_ranges_m(points, FusionVisibility.from_lists(vis), centres)
    np.testing.assert_allclose(ranges[0], np.linalg.norm(points[0]))
    np.testing.assert_allclose(ranges[1], np.linalg.norm(points[1] - centres, axis=1).mean())
    assert np.isnan(point_ranges_m(points[:2], FusionVisibility.from_lists([[], [0]]), centres)[0])
    t = np.exp(-np.array(BETA)[None] * ranges[:, None])
    lin = albedo * t + np.array(B)[None] * (1 - t)
    colors = np.round(255 * lin ** (1 / 2.2)).astype(np.uint8)
    fused = write_ply(
        tmp_path / "fused.ply", PlyData(vertices=points, normals=points, colors=colors)
    )
    data = struct.pack("<Q", len(vis)) + b"".join(
        struct.pack(f"<I{len(v)}I", len(v), *v) for v in vis
    )
    (tmp_path / "fused.ply.vis").write_bytes(data)
    views = []
    for k, centre in enumerate(centres):
        cam_from_world = np.eye(4)
        cam_from_world[:3, 3] = -centre
        views.append(
            PinholeView(name=f"{k}.png", K=np.eye(3), width=10, height=10,
                        cam_from_world=cam_from_world, points_m=np.zeros((0, 3)))
        )  # fmt: skip
    options = ColourOptions(attenuation_per_m=BETA, backscatter=B, white_balance=False)
    water = correct_fused(options, fused, views, tmp_path / "out.ply")
    assert not water.estimated
    out = read_ply(tmp_path / "out.ply")
    assert out.colors is not None
    np.testing.assert_allclose((out.colors / 255.0) ** 2.2, albedo, atol=0.06)
    (tmp_path / "fused.ply.vis").write_bytes(struct.pack("<Q", 0))
    with pytest.raises(StageError, match="visibility entries"):
        correct_fused(options, fused, views, tmp_path / "out2.ply")
