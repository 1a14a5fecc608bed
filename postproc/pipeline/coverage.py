"""How well the dives saw each part of the wreck, and where the gaps are.

Pure math, no I/O. The surface (face centres of the mesh, or fused points) is tested
against every keyframe: a sample is seen by a keyframe when it projects into the image,
lies within `max_range_m` in front of the camera, faces it at no more than
`max_incidence_deg`, and (with an occluding mesh) nothing nearer covers it (a coarse
z-buffer, `postproc.dense.zbuffer`). Per sample that gives the number of views, the
angular spread of the rays (what triangulation needs) and the nearest range (what the
resolution needs); the score multiplies three factors that each reach 1 at "good":

    views: min(n / min_views, 1)
    angles: min(spread / min_spread_deg, 1)
    range: 1 up to good_range_m, falling linearly to 0 at max_range_m

Maps: a top view (samples facing up) and two side views along the wreck's long
horizontal axis (samples facing each side), a grid of cells holding the area-weighted
mean score. A gap is a connected set of cells scoring below `gap_score`, or cells with
no surface facing the view inside the filled silhouette of the whole surface (a hole in
the model, or a side nobody filmed: the dives did not see it well enough to
reconstruct it).

Frames: world W (z up, metres). The angular spread of a sample is twice the largest
angle between one of its rays and their mean direction (the exact angle for two rays).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

ViewName = Literal["top", "side_pos", "side_neg"]
VIEWS: tuple[ViewName, ...] = ("top", "side_pos", "side_neg")
# A sample belongs to a view when its normal points at the viewer by more than this
# (cos 78 deg): vertical walls are left to the side views, the deck to the top view.
_FACING_COS = 0.2


@dataclass(kw_only=True)
class CoverageOptions:
    """What counts as seen and as well seen.

    max_range_m: a keyframe farther than this from a sample does not count (m; about
        the visibility on a wreck and where the detail is lost).
    good_range_m: full marks for range up to here (m).
    max_incidence_deg: a surface seen more obliquely than this does not count.
    min_views: keyframes a sample needs for full marks.
    min_spread_deg: angular spread of the rays for full marks (deg).
    gap_score: cells scoring below this are gaps (0..1).
    cell_m: map cell (m); None: about a 60th of the surface's largest extent, rounded.
    min_gap_cells: smaller gaps are not listed (cells).
    occlusion_width_px: width of the z-buffer used for occlusion (0: no occlusion test).
    """

    max_range_m: float = 6.0
    good_range_m: float = 3.0
    max_incidence_deg: float = 80.0
    min_views: int = 3
    min_spread_deg: float = 15.0
    gap_score: float = 0.5
    cell_m: float | None = None
    min_gap_cells: int = 4
    occlusion_width_px: int = 96


@dataclass(kw_only=True)
class SurfaceSamples:
    """Points on the surface (N,3 m, world), unit normals (N,3) or None, areas (N,) m^2."""

    points_m: FloatArray
    normals: FloatArray | None
    areas_m2: FloatArray


@dataclass(kw_only=True)
class KeyframeViews:
    """The keyframes of one session: camera poses `T_W_C` (K,4,4) and the camera model
    (anything with `project((N,3)) -> (N,2)` pixels, `width`, `height`,
    `intrinsic_matrix`)."""

    name: str
    world_from_cam: FloatArray
    camera: Any


@dataclass(kw_only=True)
class Observations:
    """Per sample: keyframes that saw it, angular spread of their rays (deg), nearest
    range (m, inf when unseen) and the score (0..1)."""

    views: IntArray
    spread_deg: FloatArray
    nearest_range_m: FloatArray
    score: FloatArray


@dataclass(kw_only=True)
class Gap:
    """A connected region of a map seen too poorly (or not at all).

    centre_m: its centre in W (m); area_m2: its area in the map's plane; no_surface_m2:
    the part with no reconstructed surface; mean_score: over the cells with surface
    (0 when none); cells: (row, col) indices of its cells in the map grid; over its
    surface samples the median keyframe count, ray spread (deg) and nearest range (m,
    inf when none saw it); limited_by: the factor that fell shortest ("views", "angles",
    "range"), or "no surface" when most of its cells have none."""

    view: ViewName
    centre_m: FloatArray
    area_m2: float
    no_surface_m2: float
    mean_score: float
    cells: IntArray
    median_views: float = 0.0
    median_spread_deg: float = 0.0
    median_range_m: float = float("inf")
    limited_by: str = "no surface"


@dataclass(kw_only=True)
class CoverageMap:
    """One view's grid: `score` (rows, cols) mean score per cell (NaN: no surface),
    `views` mean keyframe count per cell, `surface` (cells holding samples), `holes`
    (no surface inside the filled outline), `gap_labels` (0 none, k: the k-th gap of
    `gaps`, largest first). Cell (r, c) covers u in origin_u + c*cell_m .. +cell_m, v in
    origin_v + r*cell_m .. +cell_m, in the view's plane: u and v are world coordinates
    along `axis_u` and `axis_v` (unit vectors in W); `axis_depth` points at the viewer."""

    view: ViewName
    cell_m: float
    origin_u_m: float
    origin_v_m: float
    axis_u: FloatArray
    axis_v: FloatArray
    axis_depth: FloatArray
    score: FloatArray
    views: FloatArray
    surface: BoolArray
    holes: BoolArray
    gap_labels: IntArray
    gaps: list[Gap] = field(default_factory=list)

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(u_min, u_max, v_min, v_max) for imshow's extent (m)."""
        rows, cols = self.score.shape
        return (
            self.origin_u_m,
            self.origin_u_m + cols * self.cell_m,
            self.origin_v_m,
            self.origin_v_m + rows * self.cell_m,
        )


def surface_from_mesh(vertices_m: FloatArray, faces: IntArray) -> SurfaceSamples:
    """Face centres, unit face normals (right-hand winding) and face areas of a mesh."""
    v = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
    tri = v[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    keep = norm > 0
    return SurfaceSamples(
        points_m=tri[keep].mean(axis=1),
        normals=cross[keep] / norm[keep, None],
        areas_m2=0.5 * norm[keep],
    )


def surface_from_points(
    points_m: FloatArray, normals: FloatArray | None, *, spacing_m: float | None = None
) -> SurfaceSamples:
    """Points standing for `spacing_m`^2 of surface each (a fused point cloud, a sparse
    map); None: each an equal share of a surface about (largest extent)^2 / 2."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if spacing_m is None:
        extent = float(np.max(np.ptp(p, axis=0))) if len(p) else 1.0
        spacing_m = extent / np.sqrt(max(2 * len(p), 1))
    n = None
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return SurfaceSamples(points_m=p, normals=n, areas_m2=np.full(len(p), spacing_m**2))


@dataclass(kw_only=True)
class Sightings:
    """Every (sample, keyframe) pair that passed the tests: sample index, unit direction
    from the sample to the camera (W) and range (m)."""

    samples: IntArray
    directions: FloatArray
    ranges_m: FloatArray


def sightings(
    surface: SurfaceSamples,
    session: KeyframeViews,
    options: CoverageOptions,
    *,
    occluder: tuple[FloatArray, IntArray] | None = None,
) -> Sightings:
    """What each keyframe of `session` saw of the surface (see the module docstring);
    `occluder` (vertices m, faces) hides what is behind it."""
    from postproc.dense.zbuffer import MeshRasteriser, scaled_intrinsics

    p = surface.points_m
    rasteriser = None
    if occluder is not None and options.occlusion_width_px > 0 and len(occluder[1]):
        rasteriser = MeshRasteriser(occluder[0], occluder[1])
    cos_max = np.cos(np.deg2rad(options.max_incidence_deg))
    sample_idx: list[IntArray] = [np.zeros(0, dtype=np.int64)]
    directions: list[FloatArray] = [np.zeros((0, 3))]
    ranges: list[FloatArray] = [np.zeros(0)]
    camera = session.camera
    width, height = int(camera.width), int(camera.height)
    factor = min(1.0, options.occlusion_width_px / max(width, 1))
    small_w, small_h = max(1, round(width * factor)), max(1, round(height * factor))
    K_small = scaled_intrinsics(np.asarray(camera.intrinsic_matrix, float), factor)
    for world_from_cam in np.asarray(session.world_from_cam, dtype=np.float64):
        R, c = world_from_cam[:3, :3], world_from_cam[:3, 3]
        offset = p - c
        distance = np.linalg.norm(offset, axis=1)
        near = np.flatnonzero(distance <= options.max_range_m)
        if len(near) == 0:
            continue
        p_cam = offset[near] @ R  # R^T (p - c), row-wise
        ahead = p_cam[:, 2] > 0.05
        near, p_cam = near[ahead], p_cam[ahead]
        if len(near) == 0:
            continue
        pixels = camera.project(p_cam)
        inside = (
            np.isfinite(pixels).all(axis=1)
            & (pixels[:, 0] >= -0.5)
            & (pixels[:, 0] < width - 0.5)
            & (pixels[:, 1] >= -0.5)
            & (pixels[:, 1] < height - 0.5)
        )
        near, p_cam, pixels = near[inside], p_cam[inside], pixels[inside]
        to_camera = -offset[near] / distance[near, None]
        if surface.normals is not None:
            facing = np.abs(np.sum(surface.normals[near] * to_camera, axis=1)) >= cos_max
            near, p_cam, pixels, to_camera = (
                near[facing],
                p_cam[facing],
                pixels[facing],
                to_camera[facing],
            )
        if rasteriser is not None and len(near):
            cam_from_world = np.eye(4)
            cam_from_world[:3, :3] = R.T
            cam_from_world[:3, 3] = -R.T @ c
            depth = rasteriser.depth_map(
                cam_from_world, K_small, small_w, small_h,
                max_range_m=options.max_range_m + 1.0,
            )  # fmt: skip
            # Pinhole pixel of the sample in the small map (occlusion is coarse: the
            # lens distortion moves a sample by a fraction of a small pixel).
            uv = p_cam[:, :2] / p_cam[:, 2:3] @ K_small[:2, :2].T + K_small[:2, 2]
            u = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, small_w - 1)
            v = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, small_h - 1)
            z = p_cam[:, 2]
            # A pixel's depth is taken at its centre, not at the sample: allow for a
            # slanted surface across one coarse pixel.
            tolerance = 0.1 + 0.05 * z
            visible = z <= depth[v, u] + tolerance
            near, to_camera, p_cam = near[visible], to_camera[visible], p_cam[visible]
        sample_idx.append(near)
        directions.append(to_camera)
        ranges.append(np.linalg.norm(p_cam, axis=1))
    return Sightings(
        samples=np.concatenate(sample_idx),
        directions=np.concatenate(directions),
        ranges_m=np.concatenate(ranges),
    )


def aggregate(n_samples: int, seen: Sequence[Sightings], options: CoverageOptions) -> Observations:
    """Views, spread, nearest range and score per sample from the sightings of one or
    more sessions together."""
    views = np.zeros(n_samples, dtype=np.int64)
    spread = np.zeros(n_samples)
    nearest = np.full(n_samples, np.inf)
    idx = np.concatenate([s.samples for s in seen]) if seen else np.zeros(0, np.int64)
    if len(idx):
        d = np.concatenate([s.directions for s in seen])
        r = np.concatenate([s.ranges_m for s in seen])
        views = np.bincount(idx, minlength=n_samples).astype(np.int64)
        mean = np.zeros((n_samples, 3))
        np.add.at(mean, idx, d)
        mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
        angle = np.degrees(np.arccos(np.clip(np.sum(d * mean[idx], axis=1), -1.0, 1.0)))
        np.maximum.at(spread, idx, 2.0 * angle)
        np.minimum.at(nearest, idx, r)
    return Observations(
        views=views,
        spread_deg=spread,
        nearest_range_m=nearest,
        score=score_samples(views, spread, nearest, options),
    )


def observe(
    surface: SurfaceSamples,
    sessions: Sequence[KeyframeViews],
    options: CoverageOptions,
    *,
    occluder: tuple[FloatArray, IntArray] | None = None,
) -> Observations:
    """Views, spread, nearest range and score of every sample, from all keyframes of
    `sessions` together; `occluder` (vertices m, faces) hides what is behind it."""
    seen = [sightings(surface, s, options, occluder=occluder) for s in sessions]
    return aggregate(len(surface.points_m), seen, options)


def score_factors(
    views: IntArray | FloatArray,
    spread_deg: FloatArray,
    nearest_range_m: FloatArray,
    options: CoverageOptions,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The views, angles and range factors (each 0..1; see the module docstring)."""
    f_views = np.minimum(np.asarray(views, float) / max(options.min_views, 1), 1.0)
    f_angles = np.minimum(np.asarray(spread_deg, float) / max(options.min_spread_deg, 1e-9), 1.0)
    span = max(options.max_range_m - options.good_range_m, 1e-9)
    nearest = np.asarray(nearest_range_m, float)
    finite = np.isfinite(nearest)
    f_range = np.where(
        finite, np.clip((options.max_range_m - np.where(finite, nearest, 0.0)) / span, 0, 1), 0.0
    )
    return f_views, f_angles, f_range


def score_samples(
    views: IntArray, spread_deg: FloatArray, nearest_range_m: FloatArray, options: CoverageOptions
) -> FloatArray:
    """The product of the views, angles and range factors (see the module docstring)."""
    f_views, f_angles, f_range = score_factors(views, spread_deg, nearest_range_m, options)
    return np.asarray(f_views * f_angles * f_range, dtype=np.float64)


def view_axes(surface: SurfaceSamples, view: ViewName) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(axis_u, axis_v, axis_depth) of a view in W: the top view is x right, y up, seen
    from +z; the side views run along the surface's long horizontal axis (u, its
    direction fixed so that it has a non-negative x), z up, seen from +b or -b where
    b = z x u."""
    z = np.array([0.0, 0.0, 1.0])
    if view == "top":
        return np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), z
    xy = surface.points_m[:, :2]
    weights = surface.areas_m2 / max(float(surface.areas_m2.sum()), 1e-12)
    centred = xy - weights @ xy
    covariance = (centred * weights[:, None]).T @ centred
    _, vectors = np.linalg.eigh(covariance)
    long_axis = vectors[:, -1]
    if long_axis[0] < 0 or (long_axis[0] == 0 and long_axis[1] < 0):
        long_axis = -long_axis
    u = np.array([long_axis[0], long_axis[1], 0.0])
    b = np.cross(z, u)
    return u, z, b if view == "side_pos" else -b


def auto_cell_m(surface: SurfaceSamples) -> float:
    """About a 60th of the largest extent, rounded down to 1, 2 or 5 times a power of 10."""
    extent = float(np.max(np.ptp(surface.points_m, axis=0))) if len(surface.points_m) else 1.0
    raw = max(extent / 60.0, 1e-3)
    power = 10.0 ** np.floor(np.log10(raw))
    for step in (5.0, 2.0, 1.0):
        if step * power <= raw:
            return float(step * power)
    return float(power)


def coverage_map(
    surface: SurfaceSamples,
    observations: Observations,
    view: ViewName,
    options: CoverageOptions,
    *,
    cell_m: float | None = None,
) -> CoverageMap:
    """The grid of one view with its gaps (largest first)."""
    from scipy import ndimage

    score, views = observations.score, observations.views

    cell = cell_m or options.cell_m or auto_cell_m(surface)
    axis_u, axis_v, axis_depth = view_axes(surface, view)
    p = surface.points_m
    if surface.normals is not None:
        facing = surface.normals @ axis_depth
        # Normals of a mesh may be wound either way; a side view keeps what faces it,
        # the top view what faces up or down (seen from above through a cut hull).
        chosen = facing > _FACING_COS if view != "top" else np.abs(facing) > _FACING_COS
    else:
        chosen = np.ones(len(p), dtype=bool)
    u_all, v_all = p @ axis_u, p @ axis_v
    margin = 2 * cell
    origin_u = float(np.floor((u_all.min() - margin) / cell) * cell)
    origin_v = float(np.floor((v_all.min() - margin) / cell) * cell)
    cols = int(np.ceil((u_all.max() + margin - origin_u) / cell))
    rows = int(np.ceil((v_all.max() + margin - origin_v) / cell))
    col = np.clip(((u_all - origin_u) / cell).astype(np.int64), 0, cols - 1)
    row = np.clip(((v_all - origin_v) / cell).astype(np.int64), 0, rows - 1)
    flat = (row * cols + col)[chosen]
    area = surface.areas_m2[chosen]
    weight = np.bincount(flat, weights=area, minlength=rows * cols)
    score_sum = np.bincount(flat, weights=area * score[chosen], minlength=rows * cols)
    views_sum = np.bincount(flat, weights=area * views[chosen], minlength=rows * cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        cell_score = np.where(weight > 0, score_sum / weight, np.nan).reshape(rows, cols)
        cell_views = np.where(weight > 0, views_sum / weight, np.nan).reshape(rows, cols)
    has_surface = (weight > 0).reshape(rows, cols)
    # The outline: the silhouette of the whole surface (not only of what faces this view:
    # a side nobody filmed is a gap, not a blank), closed over one-cell cracks, filled.
    silhouette: npt.NDArray[np.bool_] = np.zeros(rows * cols, dtype=bool)
    silhouette[row * cols + col] = True
    silhouette = silhouette.reshape(rows, cols)
    closed = ndimage.binary_closing(silhouette, structure=np.ones((3, 3)), iterations=1)
    outline = ndimage.binary_fill_holes(closed | silhouette)
    holes = outline & ~has_surface
    poor = has_surface & (np.nan_to_num(cell_score, nan=0.0) < options.gap_score)
    labels, count = ndimage.label(poor | holes, structure=np.ones((3, 3)))
    gaps: list[Gap] = []
    depth_all = p @ axis_depth
    cell_of_sample = row * cols + col
    for k in range(1, count + 1):
        cells = np.argwhere(labels == k)
        if len(cells) < options.min_gap_cells:
            continue
        centre_u = origin_u + (cells[:, 1].mean() + 0.5) * cell
        centre_v = origin_v + (cells[:, 0].mean() + 0.5) * cell
        # Along the viewing axis: the samples in and around the gap (a hole has none).
        around = ndimage.binary_dilation(labels == k, iterations=2).reshape(-1)
        near = around[cell_of_sample] & chosen
        depth = float(np.median(depth_all[near])) if near.any() else float(np.median(depth_all))
        centre = centre_u * axis_u + centre_v * axis_v + depth * axis_depth
        scored = cell_score[cells[:, 0], cells[:, 1]]
        inside = (labels == k).reshape(-1)[cell_of_sample] & chosen
        gaps.append(
            Gap(
                view=view,
                centre_m=centre,
                area_m2=float(len(cells) * cell * cell),
                no_surface_m2=float(holes[cells[:, 0], cells[:, 1]].sum() * cell * cell),
                mean_score=float(np.nanmean(scored)) if np.isfinite(scored).any() else 0.0,
                cells=cells.astype(np.int64),
                # Mostly without surface: that is what it lacks, whatever the rest shows.
                **_why(observations, inside, options, no_surface=holes[labels == k].mean() > 0.5),
            )
        )
    gaps.sort(key=lambda g: -g.area_m2)
    gap_labels = np.zeros((rows, cols), dtype=np.int64)
    for index, gap in enumerate(gaps, start=1):
        gap_labels[gap.cells[:, 0], gap.cells[:, 1]] = index
    return CoverageMap(
        view=view,
        cell_m=float(cell),
        origin_u_m=origin_u,
        origin_v_m=origin_v,
        axis_u=axis_u,
        axis_v=axis_v,
        axis_depth=axis_depth,
        score=cell_score,
        views=cell_views,
        surface=has_surface,
        holes=holes,
        gap_labels=gap_labels,
        gaps=gaps,
    )


def _why(
    observations: Observations, inside: BoolArray, options: CoverageOptions, *, no_surface: bool
) -> dict[str, Any]:
    """The medians of a gap's samples and the score factor that fell shortest."""
    if no_surface or not inside.any():
        return {"limited_by": "no surface"}
    views = float(np.median(observations.views[inside]))
    spread = float(np.median(observations.spread_deg[inside]))
    ranges = observations.nearest_range_m[inside]
    seen = np.isfinite(ranges)
    nearest = float(np.median(ranges[seen])) if seen.any() else float("inf")
    f_views, f_angles, f_range = score_factors(
        np.array([views]), np.array([spread]), np.array([nearest]), options
    )
    by = {"views": float(f_views[0]), "angles": float(f_angles[0]), "range": float(f_range[0])}
    return {
        "median_views": views,
        "median_spread_deg": spread,
        "median_range_m": nearest,
        "limited_by": min(by, key=lambda name: by[name]),
    }


@dataclass(kw_only=True)
class TargetOffset:
    """Where a point lies from the nearest target: its name, the offset in W (m) and the
    distance (m)."""

    target: str
    offset_m: FloatArray
    distance_m: float


def nearest_target(point_m: FloatArray, targets: dict[str, FloatArray]) -> TargetOffset | None:
    """The target (name -> `T_W_m`, 4x4) whose origin is nearest to `point_m`."""
    best: TargetOffset | None = None
    for name, pose in targets.items():
        offset = np.asarray(point_m, float) - np.asarray(pose, float)[:3, 3]
        distance = float(np.linalg.norm(offset))
        if best is None or distance < best.distance_m:
            best = TargetOffset(target=name, offset_m=offset, distance_m=distance)
    return best
