"""Which neighbours each image is matched with: pure geometry, no I/O.

A good stereo partner for reference image i sees what i sees (overlap), from a baseline
that gives a useful triangulation angle (too small: depth is noise; too large: the
appearance changes and occlusions grow), and, for rectified two-view stereo, moves
sideways rather than along the viewing direction (forward motion puts the epipole inside
the image, where rectification degenerates).
"""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt

from postproc.dense.options import NeighbourOptions as NeighbourOptions
from postproc.dense.options import ViewSelectionOptions as ViewSelectionOptions

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def select_reference_views(
    cams_from_world: list[FloatArray],
    scene_depths_m: npt.ArrayLike,
    options: ViewSelectionOptions | None = None,
    *,
    order: list[int] | None = None,
) -> list[int]:
    """Indices (ascending) of the reference views among keyframes with poses `T_C_W`
    (4x4, metres) and scene depths (m): greedily, in `order` (default: index order, the
    keyframes' time order), a keyframe is kept unless a reference already kept is both
    near and looking the same way (see `ViewSelectionOptions`). A keyframe without a
    valid depth (0, negative, NaN) is always kept."""
    options = options or ViewSelectionOptions()
    n = len(cams_from_world)
    if not options.enabled or n == 0:
        return list(range(n))
    depths = np.asarray(scene_depths_m, dtype=np.float64).reshape(n)
    worlds_from_cam = [np.linalg.inv(np.asarray(T, dtype=np.float64)) for T in cams_from_world]
    centres = np.array([T[:3, 3] for T in worlds_from_cam]).reshape(n, 3)
    axes = np.array([T[:3, 2] for T in worlds_from_cam]).reshape(n, 3)
    axes /= np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    cos_limit = np.cos(np.radians(options.min_rotation_deg))
    chosen: list[int] = []
    for i in order if order is not None else range(n):
        depth = depths[i]
        if chosen and np.isfinite(depth) and depth > 0:
            kept = np.asarray(chosen)
            near = np.linalg.norm(centres[kept] - centres[i], axis=1) < (
                options.min_baseline_rel * depth
            )
            same_way = axes[kept] @ axes[i] > cos_limit
            if np.any(near & same_way):
                continue
        chosen.append(int(i))
    return sorted(chosen)


def view_overlap(
    K_ref: FloatArray,
    size_ref: tuple[int, int],
    world_from_ref: FloatArray,
    depth_ref_m: float,
    K_src: FloatArray,
    size_src: tuple[int, int],
    src_from_world: FloatArray,
    *,
    grid: int = 7,
) -> float:
    """Fraction of a `grid` x `grid` set of reference pixels, put at `depth_ref_m`, that
    project inside the source image (in front of it). Sizes are (width, height) px."""
    w, h = size_ref
    # Cell centres of a grid over the image.
    u, v = np.meshgrid((np.arange(grid) + 0.5) * w / grid, (np.arange(grid) + 0.5) * h / grid)
    pixels = np.stack((u.ravel(), v.ravel(), np.ones(grid * grid)))
    rays = np.linalg.solve(K_ref, pixels)
    points_ref = rays / rays[2] * depth_ref_m
    points_world = world_from_ref[:3, :3] @ points_ref + world_from_ref[:3, 3:4]
    points_src = src_from_world[:3, :3] @ points_world + src_from_world[:3, 3:4]
    in_front = points_src[2] > 1e-6
    proj = K_src @ points_src
    with np.errstate(divide="ignore", invalid="ignore"):
        us, vs = proj[0] / proj[2], proj[1] / proj[2]
    inside = in_front & (us >= 0) & (us < size_src[0]) & (vs >= 0) & (vs < size_src[1])
    return float(np.mean(inside))


def pair_score(
    *,
    centre_ref_m: FloatArray,
    axis_ref: FloatArray,
    centre_src_m: FloatArray,
    depth_ref_m: float,
    overlap: float,
    options: NeighbourOptions,
) -> float:
    """Score of a (reference, source) pair: 0 when rejected, else overlap times an angle
    weight that peaks at `best_angle_deg` (both in [0, 1])."""
    baseline = np.asarray(centre_src_m, float) - np.asarray(centre_ref_m, float)
    length = float(np.linalg.norm(baseline))
    if length <= 0 or depth_ref_m <= 0 or overlap < options.min_overlap:
        return 0.0
    angle_deg = float(np.degrees(2.0 * np.arctan2(0.5 * length, depth_ref_m)))
    if not options.min_angle_deg <= angle_deg <= options.max_angle_deg:
        return 0.0
    cos_axis = abs(float(np.dot(baseline / length, axis_ref))) / max(
        float(np.linalg.norm(axis_ref)), 1e-12
    )
    sideways = float(np.sqrt(max(0.0, 1.0 - cos_axis**2)))
    if sideways < options.min_sideways:
        return 0.0
    # Log-normal-like weight: a factor of two off the best angle halves the score.
    weight = float(np.exp(-0.5 * (np.log(angle_deg / options.best_angle_deg) / 0.85) ** 2))
    return overlap * weight * sideways


def select_neighbours(
    Ks: list[FloatArray],
    sizes: list[tuple[int, int]],
    cams_from_world: list[FloatArray],
    scene_depths_m: npt.ArrayLike,
    options: NeighbourOptions | None = None,
    *,
    far_depths_m: npt.ArrayLike | None = None,
    references: list[int] | None = None,
) -> list[list[int]]:
    """For each reference image, the indices of its partners among all images: the best
    for its typical depth (highest score first, at most `options.max_neighbours`, none
    scoring 0), then, when `far_depths_m` is given, up to `options.far_neighbours` more,
    the best scored at the far depth among those not already chosen.

    Ks: 3x3 intrinsics; sizes: (width, height) px; cams_from_world: 4x4 poses `T_C_W`;
    scene_depths_m: a typical depth of what each image sees (median sparse-point depth);
    far_depths_m: a far depth of what it sees (90th percentile sparse-point depth);
    references: the images that need partners, in the order of the result (None: all).
    """
    options = options or NeighbourOptions()
    refs = list(range(len(Ks))) if references is None else list(references)
    near = _ranked(Ks, sizes, cams_from_world, scene_depths_m, options, refs)
    result = [r[: options.max_neighbours] for r in near]
    if far_depths_m is None or options.far_neighbours <= 0:
        return result
    far = _ranked(Ks, sizes, cams_from_world, far_depths_m, options, refs)
    for chosen, candidates in zip(result, far, strict=True):
        extra = [j for j in candidates if j not in chosen][: options.far_neighbours]
        chosen.extend(extra)
    return result


def _ranked(
    Ks: list[FloatArray],
    sizes: list[tuple[int, int]],
    cams_from_world: list[FloatArray],
    scene_depths_m: npt.ArrayLike,
    options: NeighbourOptions,
    references: list[int],
) -> list[list[int]]:
    """Each reference image's partners scoring above 0 at the given depths, best first."""
    n = len(Ks)
    depths = np.asarray(scene_depths_m, dtype=np.float64)
    worlds_from_cam = [cast(FloatArray, np.linalg.inv(T)) for T in cams_from_world]
    centres = np.array([T[:3, 3] for T in worlds_from_cam]).reshape(n, 3)
    axes = np.array([T[:3, 2] for T in worlds_from_cam]).reshape(n, 3)
    result: list[list[int]] = []
    for i in references:
        # Cheap pre-filter: only cameras within the largest useful baseline.
        max_baseline = 2.0 * depths[i] * np.tan(np.radians(options.max_angle_deg) / 2.0)
        near = np.flatnonzero(np.linalg.norm(centres - centres[i], axis=1) <= max_baseline)
        scored: list[tuple[float, int]] = []
        for j in near:
            if j == i:
                continue
            overlap = view_overlap(
                Ks[i], sizes[i], worlds_from_cam[i], float(depths[i]),
                Ks[j], sizes[j], cams_from_world[j],
            )  # fmt: skip
            score = pair_score(
                centre_ref_m=centres[i],
                axis_ref=axes[i],
                centre_src_m=centres[j],
                depth_ref_m=float(depths[i]),
                overlap=overlap,
                options=options,
            )
            if score > 0:
                scored.append((score, int(j)))
        scored.sort(key=lambda s: (-s[0], s[1]))
        result.append([j for _, j in scored])
    return result
