"""Underwater colour correction of fused points: undo attenuation and backscatter.

Image model per channel c (linear intensity, after undoing the display gamma):
    I_c = A_c * J_c * exp(-beta_c * r) + B_c * (1 - exp(-beta_c * r))
with r the camera-to-point range (m), J the albedo, A the illumination, beta the
attenuation coefficient (1/m) and B the veiling light (backscatter at infinite range).
Estimating (A*mean J, B, beta) per channel from the fused points is a robust fit of
intensity against range: the scene's albedo does not depend on how far the diver was, so
the trend with range is the water's. Inversion then gives A*J, white-balanced (grey world:
each channel divided by its A*mean J) when asked.

`estimate_water` and `correct_colours` are pure; `correct_fused` reads and writes PLY.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from postproc.dense.options import ColourOptions as ColourOptions
from shared.errors import StageError

if TYPE_CHECKING:
    from postproc.dense.colmap_io import FusionVisibility, PinholeView

FloatArray = npt.NDArray[np.float64]

# Range bins (equal counts) of the attenuation fit.
_RANGE_BINS = 24


@dataclass
class WaterEstimate:
    """Per-channel (R, G, B) attenuation (1/m), backscatter and mean illuminated albedo
    (linear 0..1; nan when the attenuation was given), and whether they were estimated."""

    attenuation_per_m: tuple[float, float, float]
    backscatter: tuple[float, float, float]
    albedo: tuple[float, float, float]
    estimated: bool


def _linear(colors_u8: npt.ArrayLike, gamma: float) -> FloatArray:
    return (np.asarray(colors_u8, dtype=np.float64) / 255.0) ** gamma


def _fit_channel(intensity: FloatArray, ranges: FloatArray) -> tuple[float, float, float]:
    """(A, B, beta) of I = A e^{-beta r} + B (1 - e^{-beta r}), A the median albedo.

    The fit is to the median intensity in range bins of equal counts: at a fixed range the
    model is monotonic in the albedo, so the median intensity is the model at the median
    albedo, whatever the albedo's spread (and outliers do not move it)."""
    from scipy.optimize import least_squares

    edges = np.quantile(ranges, np.linspace(0.0, 1.0, _RANGE_BINS + 1))
    which = np.clip(np.searchsorted(edges, ranges, side="right") - 1, 0, _RANGE_BINS - 1)
    r_bin, i_bin = [], []
    for k in range(_RANGE_BINS):
        members = which == k
        if members.sum() >= 5:
            r_bin.append(float(np.median(ranges[members])))
            i_bin.append(float(np.median(intensity[members])))
    r, i = np.array(r_bin), np.array(i_bin)

    def residual(p: FloatArray) -> FloatArray:
        a, b, beta = p
        t = np.exp(-beta * r)
        value: FloatArray = a * t + b * (1.0 - t) - i
        return value

    start = np.array([float(i.max()), float(i.min()) / 2.0, 0.2])
    fit = least_squares(residual, start, bounds=([0.0, 0.0, 0.0], [2.0, 1.0, 5.0]))
    a, b, beta = fit.x
    return float(a), float(b), float(beta)


def estimate_water(
    colors_u8: npt.ArrayLike, ranges_m: npt.ArrayLike, *, gamma: float = 2.2,
    min_range_span_m: float = 0.5,
) -> WaterEstimate:  # fmt: skip
    """Fit the water model to point colours (N, 3) uint8 seen at ranges (N,) m."""
    ranges = np.asarray(ranges_m, dtype=np.float64)
    lin = _linear(colors_u8, gamma)
    ok = np.isfinite(ranges) & (ranges > 0)
    if ok.sum() < 50:
        raise StageError(f"colour correction: {int(ok.sum())} points (need at least 50)")
    lo, hi = np.percentile(ranges[ok], [5.0, 95.0])
    if hi - lo < min_range_span_m:
        raise StageError(
            f"colour correction: point ranges span {hi - lo:.2f} m (5-95 %), too little to "
            f"separate attenuation from colour (need {min_range_span_m} m); give the "
            "attenuation instead"
        )
    params = [_fit_channel(lin[ok, c], ranges[ok]) for c in range(3)]
    return WaterEstimate(
        attenuation_per_m=tuple(p[2] for p in params),  # type: ignore[arg-type]
        backscatter=tuple(p[1] for p in params),  # type: ignore[arg-type]
        albedo=tuple(p[0] for p in params),  # type: ignore[arg-type]
        estimated=True,
    )


def correct_colours(
    colors_u8: npt.ArrayLike,
    ranges_m: npt.ArrayLike,
    water: WaterEstimate,
    *,
    gamma: float = 2.2,
    white_balance: bool = True,
) -> npt.NDArray[np.uint8]:
    """Colours (N, 3) uint8 as seen from zero range (and white-balanced when asked)."""
    ranges = np.nan_to_num(np.asarray(ranges_m, dtype=np.float64), nan=0.0)[:, None]
    lin = _linear(colors_u8, gamma)
    beta = np.asarray(water.attenuation_per_m)[None, :]
    b = np.asarray(water.backscatter)[None, :]
    t = np.exp(-beta * ranges)
    # Attenuation past a few e-foldings would amplify noise without bound: cap the gain.
    t = np.maximum(t, 0.05)
    restored = (lin - b * (1.0 - t)) / t
    if white_balance:
        # Grey world on the restored colours: equal channel medians.
        median = np.maximum(np.median(restored, axis=0), 1e-3)
        restored = restored * (median.mean() / median)[None, :]
    restored = np.clip(restored, 0.0, 1.0)
    return np.round(255.0 * restored ** (1.0 / gamma)).astype(np.uint8)


def point_ranges_m(
    points_m: FloatArray, visibility: FusionVisibility, centres_m: FloatArray
) -> FloatArray:
    """Mean distance (m) from each point to the cameras it was fused from (NaN for a
    point of none)."""
    owners = visibility.point_of_each_image()
    distances = np.linalg.norm(centres_m[visibility.images] - points_m[owners], axis=1)
    counts = visibility.counts
    sums = np.bincount(owners, weights=distances, minlength=len(counts))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def correct_fused(
    options: ColourOptions, fused_ply: Path, views: list[PinholeView], out_ply: Path
) -> WaterEstimate:
    """Correct the colours of `fused_ply` (using its `.vis` and the workspace's `views`, in
    registered-image order) into `out_ply`; returns the water model used."""
    from postproc.dense.colmap_io import read_fusion_visibility
    from shared.formats.ply import PlyData, read_ply, write_ply

    cloud = read_ply(fused_ply)
    if cloud.colors is None:
        raise StageError(f"{fused_ply}: no colours to correct")
    visibility = read_fusion_visibility(fused_ply.with_name(fused_ply.name + ".vis"))
    if len(visibility) != len(cloud.vertices):
        raise StageError(
            f"{fused_ply}: {len(cloud.vertices)} points but {len(visibility)} visibility entries"
        )
    centres = np.array([v.centre_m for v in views]).reshape(-1, 3)
    ranges = point_ranges_m(cloud.vertices, visibility, centres)
    if options.attenuation_per_m is not None:
        water = WaterEstimate(
            attenuation_per_m=options.attenuation_per_m,
            backscatter=options.backscatter or (0.0, 0.0, 0.0),
            albedo=(float("nan"),) * 3,
            estimated=False,
        )
    else:
        water = estimate_water(
            cloud.colors, ranges, gamma=options.gamma, min_range_span_m=options.min_range_span_m
        )
    colors = correct_colours(
        cloud.colors, ranges, water, gamma=options.gamma, white_balance=options.white_balance
    )
    write_ply(out_ply, PlyData(vertices=cloud.vertices, normals=cloud.normals, colors=colors))
    return water
