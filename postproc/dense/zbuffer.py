"""A triangle z-buffer in pure numpy: the depth map a pinhole camera sees of a mesh.

Pure math, no I/O. Used to tell which truth-surface samples a camera really saw (the
depth at a sample's pixel agrees with its own depth; see `postproc.dense.evaluate`),
where a ray caster would be exact but far slower. Meant for low resolutions (a quarter
of the image or so): every triangle is tested against the pixel centres of its screen
bounding box in one vectorised pass.

Conventions: camera frame as OpenCV (x right, y down, z forward, metres); pixel (u, v)
has its centre at (u, v) (OpenCV), so pixel `depth[v, u]` holds the camera z of the
nearest surface along the ray through K^-1 (u, v, 1), inf where the ray hits nothing.
Triangles crossing the near plane are clipped against it (a wall the diver is close to
still hides what is behind it); back faces are kept (a surface occludes from either side).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# Candidate pixels tested per vectorised pass (bounds the memory: ~100 bytes a pixel).
_CHUNK_PIXELS = 1 << 18
# Edge-function slack (in units of twice the triangle's screen area) so that pixels on an
# edge shared by two triangles are drawn by both: no cracks for a far surface to show
# through.
_EDGE_EPS = 1e-9


def scaled_intrinsics(K: FloatArray, factor: float) -> FloatArray:
    """K of the same camera with its image scaled by `factor` (0.25: a quarter of the
    width and height), pixel centres kept at integer coordinates."""
    S = np.array([[factor, 0.0, 0.5 * factor - 0.5], [0.0, factor, 0.5 * factor - 0.5]])
    out = np.array(K, dtype=np.float64)
    out[:2] = S @ out
    return out


def _clip_near(P: FloatArray, near_m: float) -> FloatArray:
    """Triangles (T,3,3) in the camera frame clipped against z = near_m: (T',3,3), those
    wholly behind dropped, those with one vertex behind split into two."""
    behind = P[:, :, 2] < near_m
    n_behind = behind.sum(axis=1)
    keep = [P[n_behind == 0]]
    rows = np.arange(len(P))

    def rolled(mask: npt.NDArray[np.bool_], odd: npt.NDArray[np.bool_]) -> FloatArray:
        """Triangles of `mask` with their odd vertex (`odd` per vertex) first, order kept."""
        first = np.argmax(odd[mask], axis=1)
        order = (first[:, None] + np.arange(3)[None, :]) % 3
        rolled_P: FloatArray = P[rows[mask][:, None], order]
        return rolled_P

    def cut(a: FloatArray, b: FloatArray) -> FloatArray:
        """Where segment a->b crosses z = near_m (a and b on opposite sides)."""
        t = (near_m - a[:, 2]) / (b[:, 2] - a[:, 2])
        return a + (b - a) * t[:, None]

    one = n_behind == 1
    if np.any(one):
        Q = rolled(one, behind)  # A behind, B and C in front: the quad B, C, ac, ab
        a, b, c = Q[:, 0], Q[:, 1], Q[:, 2]
        ab, ac = cut(a, b), cut(a, c)
        keep.append(np.stack([ab, b, c], axis=1))
        keep.append(np.stack([ab, c, ac], axis=1))
    two = n_behind == 2
    if np.any(two):
        Q = rolled(two, ~behind)  # A in front, B and C behind
        a, b, c = Q[:, 0], Q[:, 1], Q[:, 2]
        keep.append(np.stack([a, cut(a, b), cut(a, c)], axis=1))
    return np.concatenate(keep)


def rasterise_depth(
    vertices_cam_m: FloatArray,
    triangles: IntArray,
    K: FloatArray,
    width: int,
    height: int,
    *,
    near_m: float = 0.05,
    max_range_m: float = np.inf,
) -> npt.NDArray[np.float32]:
    """Depth map (height, width) float32 of the mesh seen by a pinhole camera: camera z
    (m) of the nearest surface at each pixel centre, inf where nothing is hit.

    vertices_cam_m: (N,3) vertices in the camera frame; triangles: (M,3) vertex indices;
    K: 3x3 pinhole intrinsics of this image size (see `scaled_intrinsics`); near_m: the
    near clipping plane (camera z, m). Triangles wholly farther than `max_range_m` from
    the camera centre are skipped (faster; pixels whose only surface is beyond that range
    read inf), which is safe for occlusion tests of points within that range: such a
    triangle cannot lie in front of them. For many views of one mesh use `MeshRasteriser`.
    """
    return MeshRasteriser(vertices_cam_m, triangles).depth_map(
        np.eye(4), K, width, height, near_m=near_m, max_range_m=max_range_m
    )


class MeshRasteriser:
    """One mesh (world frame) rendered into depth maps from many cameras; the triangles'
    bounding spheres are computed once and cull, per view, what is behind the camera,
    outside the image or beyond the range of interest."""

    def __init__(self, vertices_m: FloatArray, triangles: IntArray) -> None:
        self.vertices_m = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        corners = self.vertices_m[self.triangles]
        self._centres = corners.mean(axis=1)
        self._radii = np.max(np.linalg.norm(corners - self._centres[:, None, :], axis=2), axis=1)

    def depth_map(
        self,
        cam_from_world: FloatArray,
        K: FloatArray,
        width: int,
        height: int,
        *,
        near_m: float = 0.05,
        max_range_m: float = np.inf,
    ) -> npt.NDArray[np.float32]:
        """Depth map (height, width) float32 seen by the camera at `cam_from_world`
        (4x4, m) with pinhole intrinsics K of this image size: see `rasterise_depth`."""
        R, p = np.asarray(cam_from_world, dtype=np.float64)[:3, :3], cam_from_world[:3, 3]
        depth = np.full(height * width, np.inf)
        centres = self._centres @ R.T + p
        r = self._radii
        keep = centres[:, 2] + r >= near_m
        if np.isfinite(max_range_m):
            keep &= np.linalg.norm(centres, axis=1) - r <= max_range_m
        # The four side planes of the view frustum (through the camera centre, normals
        # pointing out of the image, unit length): a sphere wholly outside one is unseen.
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        x_lo, x_hi = (-0.5 - cx) / fx, (width - 0.5 - cx) / fx
        y_lo, y_hi = (-0.5 - cy) / fy, (height - 0.5 - cy) / fy
        planes = np.array([[-1.0, 0.0, x_lo], [1.0, 0.0, -x_hi], [0.0, -1.0, y_lo],
                           [0.0, 1.0, -y_hi]])  # fmt: skip
        planes /= np.linalg.norm(planes, axis=1, keepdims=True)
        keep &= np.all(centres @ planes.T <= r[:, None], axis=1)
        tri = self.triangles[keep]
        if len(tri) == 0:
            return depth.reshape(height, width).astype(np.float32)
        used, local = np.unique(tri, return_inverse=True)
        v_cam = self.vertices_m[used] @ R.T + p
        P = v_cam[local.reshape(-1, 3)]
        if np.any(P[:, :, 2] < near_m):
            P = _clip_near(P, near_m)
        if len(P) > 0:
            _draw(depth, P, K, width, height)
        return depth.reshape(height, width).astype(np.float32)


def _draw(depth: FloatArray, P: FloatArray, K: FloatArray, width: int, height: int) -> None:
    """z-buffer the triangles P (T,3,3), camera frame, all vertices in front, into the
    flat depth buffer (height*width) in place."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    inv_z = 1.0 / P[:, :, 2]
    u = fx * P[:, :, 0] * inv_z + cx
    w = fy * P[:, :, 1] * inv_z + cy  # the v pixel coordinates of the corners
    u0 = np.maximum(np.ceil(u.min(axis=1)), 0).astype(np.int64)
    u1 = np.minimum(np.floor(u.max(axis=1)), width - 1).astype(np.int64)
    v0 = np.maximum(np.ceil(w.min(axis=1)), 0).astype(np.int64)
    v1 = np.minimum(np.floor(w.max(axis=1)), height - 1).astype(np.int64)
    # Twice the signed screen area; edge-on triangles cover no pixel centre.
    area = (u[:, 1] - u[:, 0]) * (w[:, 2] - w[:, 0]) - (u[:, 2] - u[:, 0]) * (w[:, 1] - w[:, 0])
    ok = (u1 >= u0) & (v1 >= v0) & (np.abs(area) > 1e-12)
    u, w, inv_z, area = u[ok], w[ok], inv_z[ok], area[ok]
    u0, v0 = u0[ok], v0[ok]
    box_w = u1[ok] - u0 + 1
    box_h = v1[ok] - v0 + 1
    sizes = box_w * box_h
    if len(sizes) == 0:
        return
    # Every screen quantity below is affine in the pixel (pu, pv): the barycentric
    # weights (edge functions over twice the area, either orientation) and 1/z (affine in
    # screen space under perspective). Rows: (d/du, d/dv, value at the box's corner).
    coef: FloatArray = np.empty((len(u), 4, 3))
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):
        du = -(w[:, k] - w[:, j]) / area
        dv = (u[:, k] - u[:, j]) / area
        coef[:, i, 0], coef[:, i, 1] = du, dv
        coef[:, i, 2] = du * (u0 - u[:, j]) + dv * (v0 - w[:, j])
    b = coef[:, :3]
    # 1/z = sum_i b_i * inv_z_i.
    coef[:, 3] = np.einsum("ti,tij->tj", inv_z, b)
    coef = coef.reshape(len(u), 12)
    # Scan lines: on row dv of its box each barycentric weight is affine in du, so the
    # covered span [lo, hi] follows from three half-lines; only covered pixels are made.
    tri = np.repeat(np.arange(len(sizes)), box_h)
    dv = (np.arange(len(tri)) - np.repeat(np.cumsum(box_h) - box_h, box_h)).astype(np.float64)
    c = coef[tri]
    lo = np.zeros(len(tri))
    hi = (box_w[tri] - 1).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            slope = c[:, 3 * i]
            rest = c[:, 3 * i + 1] * dv + c[:, 3 * i + 2] + _EDGE_EPS  # b_i + eps at du = 0
            bound = -rest / slope
            lo = np.where(slope > 0, np.maximum(lo, np.ceil(bound)), lo)
            hi = np.where(slope < 0, np.minimum(hi, np.floor(bound)), hi)
            hi = np.where((slope == 0) & (rest < 0), -1.0, hi)
    count = np.maximum(hi - lo + 1, 0).astype(np.int64)
    rows = np.flatnonzero(count)
    tri, dv, lo, count = tri[rows], dv[rows], lo[rows], count[rows]
    pixels = np.repeat(np.arange(len(rows)), count)
    du = lo[pixels] + (np.arange(len(pixels)) - np.repeat(np.cumsum(count) - count, count))
    dv = dv[pixels]
    c = coef[tri[pixels]][:, 9:]
    iz = c[:, 0] * du + c[:, 1] * dv + c[:, 2]
    t = tri[pixels]
    pixel = (v0[t] + dv.astype(np.int64)) * width + u0[t] + du.astype(np.int64)
    np.minimum.at(depth, pixel, 1.0 / iz)
