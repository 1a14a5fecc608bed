"""Free-space carving: mesh surface where the cameras saw through it is removed.

A depth map says more than where surfaces are: along each pixel's ray, the space in front
of the measured depth is empty, since the camera saw past it. Poisson closes holes with
surface and grows blobs around stray points; where that surface lies in front of what
several depth maps measured, it cannot be there. A mesh vertex is removed when at least
`min_views` depth maps saw past it and more saw past it than agree with it (a depth map
with an outlier too far away must not cut a surface the others confirm).

"Saw past": the vertex projects inside the map, in front of the camera, and nearer than
the nearest depth of the 3x3 pixels around its projection by more than `tolerance_rel`
of that depth (the nearest of nine, so that a vertex on a silhouette, whose pixel may
show the background, is not counted). "Agrees": within `tolerance_rel` of the depth at
its pixel. Pure math on arrays; the dense stage reads the maps.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class DepthView:
    """One depth map (H, W) metres, 0 where unknown, with its 3x3 K (pixels, the centre
    of the top-left pixel at 0.5, as COLMAP's) and 4x4 `T_C_W` (m)."""

    depth_m: npt.NDArray[np.float32]
    K: FloatArray
    cam_from_world: FloatArray


def free_space_votes(
    vertices_m: FloatArray, view: DepthView, *, tolerance_rel: float
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """(seen_past, agrees), one flag per vertex (world, m), for one depth map (see the
    module docstring)."""
    import cv2

    count = len(vertices_m)
    seen_past = np.zeros(count, bool)
    agrees = np.zeros(count, bool)
    depth = np.asarray(view.depth_m, dtype=np.float32)
    height, width = depth.shape
    cam = vertices_m @ view.cam_from_world[:3, :3].T + view.cam_from_world[:3, 3]
    z = cam[:, 2]
    front = np.flatnonzero(z > 1e-6)
    if len(front) == 0:
        return seen_past, agrees
    zf = z[front]
    u = np.floor(view.K[0, 0] * cam[front, 0] / zf + view.K[0, 2])
    v = np.floor(view.K[1, 1] * cam[front, 1] / zf + view.K[1, 2])
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    index = front[inside]
    col, row, zi = u[inside].astype(np.int64), v[inside].astype(np.int64), zf[inside]
    # The nearest known depth of the 3x3 pixels (unknown: infinitely far, never nearer).
    known = np.where(depth > 0, depth, np.inf).astype(np.float32)
    nearest = cv2.erode(known, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    near = nearest[row, col]
    here = depth[row, col]
    seen_past[index] = np.isfinite(near) & (zi < near * (1.0 - tolerance_rel))
    agrees[index] = (here > 0) & (np.abs(zi - here) <= tolerance_rel * here)
    return seen_past, agrees


def carved_vertices(
    vertices_m: FloatArray,
    views: Iterable[DepthView],
    *,
    tolerance_rel: float,
    min_views: int,
) -> npt.NDArray[np.bool_]:
    """The vertices to remove: seen past by at least `min_views` depth maps, and by more
    maps than agree with them."""
    vertices_m = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
    past = np.zeros(len(vertices_m), np.int32)
    agree = np.zeros(len(vertices_m), np.int32)
    for view in views:
        seen_past, agrees = free_space_votes(vertices_m, view, tolerance_rel=tolerance_rel)
        past += seen_past
        agree += agrees
    carved: npt.NDArray[np.bool_] = (past >= max(min_views, 1)) & (past > agree)
    return carved
