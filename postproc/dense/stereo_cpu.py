"""Depth maps without a GPU: semi-global matching on rectified neighbour pairs.

For a reference image and each chosen neighbour, both images are rotated onto a common
rectified frame whose x axis is the baseline (our own rectification, so vertical or
diagonal motion works as well as horizontal), OpenCV's SGBM matches them with its
left-right check, and each reference pixel reads its disparity back through the
rectifying homography. The per-pair depths are then combined with a multi-view
consistency vote: a pixel keeps a depth only when at least `min_consistent` pairs agree
within `consistency_rel` of their median. Normals come from the depth map itself.

Pure math on arrays (numpy, OpenCV); no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from postproc.dense.options import CpuStereoOptions as CpuStereoOptions

F32 = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]
Image = npt.NDArray[np.uint8]


@dataclass
class StereoView:
    """An undistorted (pinhole) image: RGB or gray uint8, K (3x3 px), `cam_from_world` 4x4."""

    image: Image
    K: FloatArray
    cam_from_world: FloatArray


def _gray(image: Image) -> Image:
    if image.ndim == 3:
        return cast(Image, cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    return image


def rectifying_rotations(
    ref_from_world: FloatArray, src_from_world: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """(rect_from_ref, rect_from_src, baseline_m): rotations onto a common frame whose x axis
    points from the reference's centre to the source's, z close to both optical axes."""
    src_from_ref = src_from_world @ np.linalg.inv(ref_from_world)
    R, t = src_from_ref[:3, :3], src_from_ref[:3, 3]
    centre_src_in_ref = -R.T @ t
    baseline = float(np.linalg.norm(centre_src_in_ref))
    if baseline <= 0:
        raise ValueError("the two cameras share their centre (no baseline)")
    x = centre_src_in_ref / baseline
    z = np.array([0.0, 0.0, 1.0]) + R.T @ np.array([0.0, 0.0, 1.0])
    z = z - np.dot(z, x) * x
    norm = np.linalg.norm(z)
    if norm < 1e-6:
        raise ValueError("the baseline is along the optical axes (cannot rectify)")
    z /= norm
    y = np.cross(z, x)
    rect_from_ref = np.stack((x, y, z))
    rect_from_src = rect_from_ref @ R.T
    return rect_from_ref, rect_from_src, baseline


def disparity_bounds(
    K: FloatArray,
    size: tuple[int, int],
    rect_from_ref: FloatArray,
    f_px: float,
    baseline_m: float,
    depth_range_m: tuple[float, float],
    points_ref_cam: FloatArray | None = None,
) -> tuple[int, int]:
    """(min, max) disparity (px) to search in the rectified pair.

    Disparity is f * B / z_rect, with z_rect the depth along the rectified axis, which
    differs from the reference's depth when the pair is rotated for rectification (a
    diver swimming along a wall while looking obliquely at it). With the reference's
    sparse points (camera frame, m) the bounds are their 1-99 % disparities widened by
    25 % of depth; otherwise the exact extremes over the viewing frustum between the near
    and far depth (z_rect is linear in the point, so its extremes are at the corners).
    """
    z_axis = rect_from_ref[2]
    if points_ref_cam is not None and len(points_ref_cam) >= 10:
        z_rect = np.asarray(points_ref_cam, float) @ z_axis
        z_rect = z_rect[z_rect > 1e-3]
    else:
        z_rect = np.zeros(0)
    if len(z_rect) >= 10:
        lo, hi = np.percentile(z_rect, [1.0, 99.0])
        lo, hi = 0.75 * lo, 1.25 * hi
    else:
        width, height = size
        corners = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1],
                            [width - 1, height - 1, 1]], float).T  # fmt: skip
        rays = np.linalg.solve(K, corners)
        z_unit = z_axis @ rays  # z_rect of each corner ray at reference depth 1
        candidates = np.concatenate([z_unit * depth_range_m[0], z_unit * depth_range_m[1]])
        candidates = candidates[candidates > 1e-3]
        if len(candidates) == 0:
            return 0, 16
        lo, hi = float(candidates.min()), float(candidates.max())
    return int(np.floor(f_px * baseline_m / hi)), int(np.ceil(f_px * baseline_m / lo))


def pair_depth(
    ref: StereoView,
    src: StereoView,
    depth_range_m: tuple[float, float],
    options: CpuStereoOptions | None = None,
    *,
    points_ref_cam: FloatArray | None = None,
) -> F32:
    """Depth (camera z, metres; 0 where unknown) of each reference pixel from one pair.

    depth_range_m: (near, far) reference depths accepted; points_ref_cam: the sparse
    points the reference sees, in its camera frame (m), to narrow the disparity search."""
    options = options or CpuStereoOptions()
    height, width = ref.image.shape[:2]
    rect_from_ref, rect_from_src, baseline = rectifying_rotations(
        ref.cam_from_world, src.cam_from_world
    )
    f = float(ref.K[0, 0] + ref.K[1, 1]) / 2.0
    # Rectified intrinsics: the reference's focal length, principal point placing the rotated
    # reference image inside the rectified image. A strongly rotated pair stretches the far
    # side of the image without bound: the rectified image is then capped at
    # `max_rect_scale` times the reference, centred on where the reference's centre lands.
    w1, h1 = width - 1, height - 1
    corners = np.array([[0, 0, 1], [w1, 0, 1], [0, h1, 1], [w1, h1, 1], [w1 / 2, h1 / 2, 1]])
    rays = rect_from_ref @ np.linalg.solve(ref.K, corners.T.astype(float))
    if rays[2, 4] <= 1e-3:
        return np.zeros((height, width), np.float32)
    front = rays[2] > 1e-3
    xy = f * rays[:2, front] / rays[2, front]
    centre_xy = f * rays[:2, 4] / rays[2, 4]
    limit = options.max_rect_scale * np.array([width, height]) / 2.0
    lo = np.maximum(xy.min(axis=1), centre_xy - limit) if front[:4].all() else centre_xy - limit
    hi = np.minimum(xy.max(axis=1), centre_xy + limit) if front[:4].all() else centre_xy + limit
    z_min, z_max = depth_range_m
    d_min, d_max = disparity_bounds(
        ref.K, (width, height), rect_from_ref, f, baseline, depth_range_m, points_ref_cam
    )
    d_min = max(d_min, 0)
    # Too wide a search keeps the far end (the bulk of a survey view).
    num = min(int(np.ceil(max(d_max - d_min, 16) / 16.0) * 16), options.max_disparities)
    # The matcher cannot match the first `num` columns of the left image: pad them.
    lo = lo - np.array([num, 0.0])
    rect_w, rect_h = int(np.ceil(hi[0] - lo[0])) + 1, int(np.ceil(hi[1] - lo[1])) + 1
    K_rect = np.array([[f, 0.0, -lo[0]], [0.0, f, -lo[1]], [0.0, 0.0, 1.0]])
    # The source is shifted right by d_min so the search starts at 0.
    K_rect_src = K_rect + np.array([[0.0, 0.0, d_min], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    H_ref = K_rect @ rect_from_ref @ np.linalg.inv(ref.K)
    H_src = K_rect_src @ rect_from_src @ np.linalg.inv(src.K)
    left = cv2.warpPerspective(_gray(ref.image), H_ref, (rect_w, rect_h), flags=cv2.INTER_LINEAR)
    right = cv2.warpPerspective(_gray(src.image), H_src, (rect_w, rect_h), flags=cv2.INTER_LINEAR)
    block = options.block_size_px
    matcher = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=num,
        blockSize=block,
        P1=int(options.p1 * block * block),
        P2=int(options.p2 * block * block),
        disp12MaxDiff=options.lr_max_diff_px,
        uniquenessRatio=options.uniqueness_pct,
        speckleWindowSize=options.speckle_window_px,
        speckleRange=options.speckle_range,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disparity = matcher.compute(left, right).astype(np.float32) / 16.0
    # Where the source image has no pixels the matcher still answers: mask those out.
    coverage = cv2.warpPerspective(
        np.full(src.image.shape[:2], 255, np.uint8), H_src, (rect_w, rect_h),
        flags=cv2.INTER_NEAREST,
    )  # fmt: skip
    disparity[disparity < 0] = np.nan  # SGBM's "no match" is minDisparity - 1
    # Read each reference pixel's disparity at its rectified position.
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float32)
    pix = np.stack((uu.ravel(), vv.ravel(), np.ones(uu.size, np.float32)))
    mapped = H_ref @ pix
    map_x = (mapped[0] / mapped[2]).reshape(height, width).astype(np.float32)
    map_y = (mapped[1] / mapped[2]).reshape(height, width).astype(np.float32)
    disp_ref = cv2.remap(
        disparity, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )  # fmt: skip
    # The matched source pixel must lie on real source pixels.
    src_x = map_x - np.nan_to_num(disp_ref, nan=0.0)
    covered = cv2.remap(coverage, src_x, map_y, cv2.INTER_NEAREST, borderValue=0) > 0
    true_disp = disp_ref + d_min
    valid = np.isfinite(disp_ref) & (true_disp > 0) & covered
    z_rect = np.where(valid, f * baseline / np.where(valid, true_disp, 1.0), 0.0)
    # Back to the reference camera: p_ref = rect_from_ref^T p_rect; depth is its z.
    x_rect = (map_x - K_rect[0, 2]) / f * z_rect
    y_rect = (map_y - K_rect[1, 2]) / f * z_rect
    r = rect_from_ref
    depth = r[0, 2] * x_rect + r[1, 2] * y_rect + r[2, 2] * z_rect
    depth[~valid | (depth < z_min) | (depth > z_max)] = 0.0
    depth32: npt.NDArray[np.float32] = depth.astype(np.float32)
    return depth32


def consistent_depth(pair_depths: list[F32], options: CpuStereoOptions | None = None) -> F32:
    """Combine per-pair depth maps: the mean of the depths within `consistency_rel` of the
    per-pixel median, where at least `min_consistent` of them agree (else 0)."""
    return consistent_depth_support(pair_depths, options)[0]


def consistent_depth_support(
    pair_depths: list[F32], options: CpuStereoOptions | None = None
) -> tuple[F32, npt.NDArray[np.uint8]]:
    """`consistent_depth` and, per pixel, its support: how many pairs agree on the depth
    kept within `support_tolerance_m` (and `consistency_rel`), 0 where none is kept. A
    pixel two pairs support was matched in three images to that tolerance; far pixels,
    whose pairs agree only to a fraction of a large depth, get less support."""
    options = options or CpuStereoOptions()
    if not pair_depths:
        raise ValueError("no depth maps to combine")
    stack = np.stack(pair_depths).astype(np.float32)
    stack[stack <= 0] = np.nan
    need = min(options.min_consistent, len(pair_depths))
    with np.errstate(all="ignore"):
        median = nan_median_first_axis(stack)
        agree = np.abs(stack - median) <= options.consistency_rel * median
        count = agree.sum(axis=0)
        total = np.where(agree, stack, 0.0).sum(axis=0)
        kept = count >= need
        depth = np.where(kept, total / np.maximum(count, 1), 0.0)
        close = agree & (np.abs(stack - depth) <= options.support_tolerance_m)
        support_count = close.sum(axis=0)
    depth = np.nan_to_num(depth, nan=0.0).astype(np.float32)
    support = np.where(kept & (depth > 0), np.minimum(support_count, 255), 0).astype(np.uint8)
    return depth, support


def nan_median_first_axis(stack: F32) -> F32:
    """`np.nanmedian(stack, axis=0)` for a few layers without its slow masked path: sort
    (NaN sorts last), then average the middle one or two of each pixel's finite values
    (NaN where there are none)."""
    ordered = np.sort(stack, axis=0)
    count = np.isfinite(ordered).sum(axis=0)
    last = len(stack) - 1
    low = np.take_along_axis(ordered, np.clip((count - 1) // 2, 0, last)[None], axis=0)[0]
    high = np.take_along_axis(ordered, np.clip(count // 2, 0, last)[None], axis=0)[0]
    median: npt.NDArray[np.float32] = ((low + high) / 2).astype(stack.dtype)
    return median


def normals_from_depth(depth_m: F32, K: FloatArray, *, step_px: int = 2) -> F32:
    """Unit normals (H, W, 3) in the camera frame, facing the camera, from a depth map by
    central differences `step_px` apart (0 where a neighbour has no depth)."""
    height, width = depth_m.shape
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    z = depth_m.astype(np.float64)
    X = (uu - K[0, 2]) / K[0, 0] * z
    Y = (vv - K[1, 2]) / K[1, 1] * z
    P = np.stack((X, Y, z), axis=2)
    s = step_px
    du = np.zeros_like(P)
    dv = np.zeros_like(P)
    du[:, s:-s] = P[:, 2 * s :] - P[:, : -2 * s]
    dv[s:-s] = P[2 * s :] - P[: -2 * s]
    valid = z > 0
    ok = np.zeros_like(valid)
    ok[s:-s, s:-s] = (
        valid[s:-s, 2 * s :] & valid[s:-s, : -2 * s] & valid[2 * s :, s:-s] & valid[: -2 * s, s:-s]
    ) & valid[s:-s, s:-s]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=2)
    ok &= norm > 0
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    # Face the camera: the normal opposes the viewing ray.
    flip = np.sum(n * P, axis=2) > 0
    n[flip] *= -1.0
    n[~ok] = 0.0
    return n.astype(np.float32)


def depth_map(
    ref: StereoView,
    sources: list[StereoView],
    depth_range_m: tuple[float, float],
    options: CpuStereoOptions | None = None,
    *,
    points_ref_cam: FloatArray | None = None,
) -> tuple[F32, F32]:
    """(depth (H, W) m, normals (H, W, 3)) of the reference image from its neighbours
    (`points_ref_cam`: its sparse points in its camera frame, see `pair_depth`).

    Pixels with no consistent depth are 0 in both; where a normal cannot be formed the
    depth is dropped too (COLMAP's fusion needs both)."""
    depth, normals, _ = depth_support_map(
        ref, sources, depth_range_m, options, points_ref_cam=points_ref_cam
    )
    return depth, normals


def depth_support_map(
    ref: StereoView,
    sources: list[StereoView],
    depth_range_m: tuple[float, float],
    options: CpuStereoOptions | None = None,
    *,
    points_ref_cam: FloatArray | None = None,
) -> tuple[F32, F32, npt.NDArray[np.uint8]]:
    """`depth_map` and its support (H, W): the stereo pairs that agreed on each pixel's
    depth (0 where the depth is 0)."""
    options = options or CpuStereoOptions()
    height, width = ref.image.shape[:2]
    if not sources:
        return (
            np.zeros((height, width), np.float32),
            np.zeros((height, width, 3), np.float32),
            np.zeros((height, width), np.uint8),
        )
    pairs = [
        pair_depth(ref, src, depth_range_m, options, points_ref_cam=points_ref_cam)
        for src in sources
    ]
    depth, support = consistent_depth_support(pairs, options)
    normals = normals_from_depth(depth, ref.K, step_px=options.normal_step_px)
    no_normal = ~np.any(normals != 0, axis=2)
    depth[no_normal] = 0.0
    support[no_normal] = 0
    return depth, normals, support
