"""ETH3D-style evaluation of a dense reconstruction against a truth mesh (pure math).

accuracy(d): fraction of reconstructed points within d of the truth surface;
completeness(d): fraction of truth-surface samples within d of a reconstructed point,
counting only the samples seen by at least `min_views` cameras (a surface nobody filmed
cannot be reconstructed); F1 is their harmonic mean. Distances to the truth are exact
point-to-triangle distances over the triangles near each point.

Which samples a camera saw: `visibility` against true depth maps, which `seen_counts`
makes itself with a numpy z-buffer of the truth mesh (`postproc.dense.zbuffer`) at low
resolution, in the pinhole `undistorted_canvas` that holds a distorted camera's view.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from shared.calibration.cameras import CameraModel

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def point_triangle_distance(
    points: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray
) -> FloatArray:
    """Euclidean distance (N,) from each point (N,3) to its triangle (a[i], b[i], c[i])
    (Ericson's closest-point regions, vectorised)."""
    p = np.asarray(points, dtype=np.float64)
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        closest = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        # Edge regions.
        t_ab = d1 / (d1 - d3)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        closest = np.where(on_ab[:, None], a + ab * t_ab[:, None], closest)
        t_ac = d2 / (d2 - d6)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        closest = np.where(on_ac[:, None], a + ac * t_ac[:, None], closest)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        closest = np.where(on_bc[:, None], b + (c - b) * t_bc[:, None], closest)
    # Vertex regions last (they take precedence).
    closest = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, closest)
    closest = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, closest)
    closest = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, closest)
    distances: FloatArray = np.linalg.norm(p - closest, axis=1)
    return distances


def sample_surface(
    vertices: FloatArray, triangles: IntArray, spacing_m: float, *, seed: int = 0
) -> tuple[FloatArray, IntArray]:
    """Random points on the triangles, about one per `spacing_m`^2 (at least one per
    triangle); returns (points (S,3), triangle index (S,))."""
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    counts = np.maximum(np.round(area / spacing_m**2).astype(np.int64), 1)
    tri = np.repeat(np.arange(len(t)), counts)
    r1, r2 = rng.random(len(tri)), rng.random(len(tri))
    flip = r1 + r2 > 1.0
    r1[flip], r2[flip] = 1.0 - r1[flip], 1.0 - r2[flip]
    points = a[tri] + (b[tri] - a[tri]) * r1[:, None] + (c[tri] - a[tri]) * r2[:, None]
    return points, tri


def distance_to_surface(
    points: FloatArray,
    vertices: FloatArray,
    triangles: npt.NDArray[np.integer],
    *,
    nearest_vertices: int = 4,
) -> FloatArray:
    """Distance (N,) from each point to a fine mesh (a reconstruction's: many small
    triangles sharing their vertices): exact point-to-triangle distance over the triangles
    around the `nearest_vertices` nearest vertices (upper bound of the true distance,
    exact wherever the nearest triangle touches one of them). `distance_to_mesh` suits a
    coarse mesh and few points; here each vertex is in the search tree once."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if len(points) == 0:
        return np.zeros(0)
    if len(t) == 0 or len(v) == 0:
        return np.full(len(points), np.inf)
    _, near = cKDTree(v).query(points, k=min(nearest_vertices, len(v)))
    near = np.asarray(near).reshape(len(points), -1)
    # The triangles around each vertex, grouped by vertex.
    flat = t.ravel()
    order = np.argsort(flat, kind="stable")
    around = order // 3
    counts = np.bincount(flat, minlength=len(v))
    starts = np.concatenate(([0], np.cumsum(counts)))
    best = np.full(len(points), np.inf)
    for column in range(near.shape[1]):
        vertex = near[:, column]
        for j in range(int(counts[vertex].max(initial=0))):
            has = np.flatnonzero(counts[vertex] > j)
            tri = t[around[starts[vertex[has]] + j]]
            d = point_triangle_distance(points[has], v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
            best[has] = np.minimum(best[has], d)
    return best


def distance_to_mesh(
    points: FloatArray,
    vertices: FloatArray,
    triangles: npt.NDArray[np.integer],
    *,
    sample_spacing_m: float = 0.05,
    candidates: int = 8,
    max_distance_m: float = 1.0,
) -> FloatArray:
    """Distance (N,) from each point to the mesh: exact point-to-triangle distance over the
    triangles of the `candidates` nearest surface samples (upper bound of the true
    distance, exact wherever the nearest triangle is among them).

    Only triangles whose bounding box comes within `max_distance_m` of the points' bounding
    box are considered (a large truth mesh, small reconstruction), so distances beyond
    `max_distance_m` are upper bounds (inf when no triangle is that close)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if len(points) == 0:
        return np.zeros(0)
    lo, hi = points.min(axis=0) - max_distance_m, points.max(axis=0) + max_distance_m
    corners = v[t]
    near = np.all(corners.max(axis=1) >= lo, axis=1) & np.all(corners.min(axis=1) <= hi, axis=1)
    t = t[near]
    if len(t) == 0:
        return np.full(len(points), np.inf)
    samples, tri_of_sample = sample_surface(v, t, sample_spacing_m)
    # Triangle vertices themselves are samples too, so small triangles are never missed.
    samples = np.concatenate([samples, v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]])
    tri_of_sample = np.concatenate([tri_of_sample, np.tile(np.arange(len(t)), 3)])
    _, nearest = cKDTree(samples).query(points, k=min(candidates, len(samples)))
    nearest = nearest.reshape(len(points), -1)
    best = np.full(len(points), np.inf)
    for k in range(nearest.shape[1]):
        tri = t[tri_of_sample[nearest[:, k]]]
        d = point_triangle_distance(points, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
        best = np.minimum(best, d)
    return best


def visibility_counts(
    points_m: FloatArray,
    Ks: list[FloatArray],
    cams_from_world: list[FloatArray],
    depth_maps_m: list[npt.NDArray[np.float32]],
    *,
    tolerance_m: float = 0.02,
    tolerance_rel: float = 0.01,
    max_range_m: float = np.inf,
) -> IntArray:
    """How many cameras see each point: it projects inside the (pinhole) image, in front,
    no farther than `max_range_m` from the camera centre, and the camera's true depth map
    there agrees with its depth (so a surface behind another is not seen)."""
    # With a range limit, the ranges from every camera that sees a point (one pass).
    limited = bool(np.isfinite(max_range_m))
    counts, ranges = visibility(
        points_m, Ks, cams_from_world, depth_maps_m, tolerance_m=tolerance_m,
        tolerance_rel=tolerance_rel, nearest=len(Ks) if limited else 0,
    )  # fmt: skip
    if limited:
        within: npt.NDArray[np.int64] = np.sum(ranges <= max_range_m, axis=1).astype(np.int64)
        return within
    return counts


def visibility(
    points_m: FloatArray,
    Ks: list[FloatArray],
    cams_from_world: list[FloatArray],
    depth_maps_m: list[npt.NDArray[np.float32]],
    *,
    tolerance_m: float = 0.02,
    tolerance_rel: float = 0.01,
    nearest: int = 3,
    one_sided: bool = False,
) -> tuple[IntArray, FloatArray]:
    """(counts (N,), ranges (N, nearest) m): how many cameras see each point (see
    `visibility_counts`, occlusion tested on the true depth maps `depth_maps_m`, camera
    z in m, inf or nan where nothing is hit) and the distances from the `nearest` closest
    of those cameras, ascending (inf where fewer see it). `ranges[:, 2]` is the range
    within which a point is seen by three cameras.

    one_sided: only a surface nearer than the point (beyond the tolerance) hides it; a
    depth map reading farther, or inf, does not (for points on the depth maps' own
    surface: at a silhouette the pixel centre may miss the point's surface). NaN pixels
    still see nothing."""
    points = np.asarray(points_m, dtype=np.float64)
    counts = np.zeros(len(points), np.int64)
    ranges = np.full((len(points), nearest + 1), np.inf)
    for K, pose, depth in zip(Ks, cams_from_world, depth_maps_m, strict=True):
        height, width = depth.shape
        pc = points @ pose[:3, :3].T + pose[:3, 3]
        front = np.flatnonzero(pc[:, 2] > 1e-3)
        uv = (pc[front] @ K.T)[:, :2] / pc[front, 2:3]
        u = np.round(uv[:, 0]).astype(np.int64)
        v = np.round(uv[:, 1]).astype(np.int64)
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        idx, u, v = front[inside], u[inside], v[inside]
        z = pc[idx, 2]
        true_z = depth[v, u].astype(np.float64)
        slack = tolerance_m + tolerance_rel * z
        if one_sided:
            with np.errstate(invalid="ignore"):
                seen = true_z >= z - slack  # False for NaN
        else:
            seen = np.isfinite(true_z) & (np.abs(true_z - z) <= slack)
        idx = idx[seen]
        counts[idx] += 1
        if nearest > 0:
            # Keep the `nearest` smallest ranges: put the new one in the spare last
            # column and sort the row.
            ranges[idx, nearest] = np.linalg.norm(pc[idx], axis=1)
            ranges[idx] = np.sort(ranges[idx], axis=1)
            ranges[idx, nearest] = np.inf
    return counts, ranges[:, :nearest]


@dataclass
class Scores:
    """Accuracy, completeness and F1 (fractions 0..1) at one distance threshold (m)."""

    threshold_m: float
    accuracy: float
    completeness: float

    @property
    def f1(self) -> float:
        s = self.accuracy + self.completeness
        return 0.0 if s == 0 else 2.0 * self.accuracy * self.completeness / s


def evaluate(
    recon_points_m: FloatArray,
    truth_vertices: FloatArray,
    truth_triangles: IntArray,
    truth_samples_m: FloatArray,
    *,
    thresholds_m: tuple[float, ...] = (0.02, 0.05, 0.10),
) -> list[Scores]:
    """Scores of a reconstruction (points) against the truth mesh, completeness measured
    on `truth_samples_m` (already restricted to the surface that was seen)."""
    from scipy.spatial import cKDTree

    recon = np.asarray(recon_points_m, dtype=np.float64).reshape(-1, 3)
    samples = np.asarray(truth_samples_m, dtype=np.float64).reshape(-1, 3)
    if len(recon) == 0:
        return [Scores(threshold_m=d, accuracy=0.0, completeness=0.0) for d in thresholds_m]
    to_truth = distance_to_mesh(recon, truth_vertices, truth_triangles)
    to_recon, _ = cKDTree(recon).query(samples) if len(samples) else (np.zeros(0), None)
    return [
        Scores(
            threshold_m=d,
            accuracy=float(np.mean(to_truth <= d)),
            completeness=float(np.mean(to_recon <= d)) if len(samples) else 0.0,
        )
        for d in thresholds_m
    ]


def undistorted_canvas(
    camera: CameraModel, scale: float = 0.25
) -> tuple[FloatArray, int, int, npt.NDArray[np.bool_]]:
    """A pinhole image that holds the whole field of view of a distorted camera, for
    depth maps: (K 3x3, width, height, filmed (height, width) bool).

    The pinhole has the camera's focal lengths times `scale` and is just large enough for
    the undistorted outline of the real image (barrel distortion pushes its corners
    out); `filmed` marks the pixels whose ray lands inside the real image, so a depth map
    set to NaN elsewhere makes `visibility` count only what the camera really filmed."""
    width, height = camera.width, camera.height
    K0 = camera.intrinsic_matrix
    # The real image's outline (pixel edges, OpenCV centres) undistorted to rays.
    n = 4 * max(width, height)
    s = np.linspace(0.0, 1.0, n)
    x_edge, y_edge = width * s - 0.5, height * s - 0.5
    outline = np.concatenate([
        np.column_stack([x_edge, np.full(n, -0.5)]),
        np.column_stack([x_edge, np.full(n, height - 0.5)]),
        np.column_stack([np.full(n, -0.5), y_edge]),
        np.column_stack([np.full(n, width - 0.5), y_edge]),
    ])  # fmt: skip
    rays = camera.unproject(outline)
    rays = rays[np.all(np.isfinite(rays), axis=1)]
    fx, fy = K0[0, 0] * scale, K0[1, 1] * scale
    x_lo, x_hi = rays[:, 0].min(), rays[:, 0].max()
    y_lo, y_hi = rays[:, 1].min(), rays[:, 1].max()
    canvas_w = int(np.ceil((x_hi - x_lo) * fx))
    canvas_h = int(np.ceil((y_hi - y_lo) * fy))
    # Pixel u spans [u - 0.5, u + 0.5]: the left edge -0.5 is at x_lo.
    K = np.array([[fx, 0.0, -x_lo * fx - 0.5], [0.0, fy, -y_lo * fy - 0.5], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.arange(canvas_w), np.arange(canvas_h))
    xy = np.column_stack([(u.ravel() - K[0, 2]) / fx, (v.ravel() - K[1, 2]) / fy])
    pixels = camera.project(np.column_stack([xy, np.ones(len(xy))]))
    with np.errstate(invalid="ignore"):
        filmed = (
            (pixels[:, 0] >= -0.5)
            & (pixels[:, 0] < width - 0.5)
            & (pixels[:, 1] >= -0.5)
            & (pixels[:, 1] < height - 0.5)
        )
    return K, canvas_w, canvas_h, filmed.reshape(canvas_h, canvas_w)


def seen_counts(
    points_m: FloatArray,
    vertices_m: FloatArray,
    triangles: IntArray,
    K: FloatArray,
    width: int,
    height: int,
    cams_from_world: list[FloatArray] | FloatArray,
    *,
    filmed: npt.NDArray[np.bool_] | None = None,
    max_range_m: float = np.inf,
    near_m: float = 0.05,
    tolerance_m: float = 0.02,
    tolerance_rel: float = 0.015,
    progress_label: str | None = None,
) -> IntArray:
    """How many cameras see each point (N,) of the mesh's surface, occlusion included:
    the mesh (world frame, m) is z-buffered into a pinhole depth map per camera
    (`postproc.dense.zbuffer`, intrinsics K of a width x height image, NaN outside
    `filmed` when given) and `visibility` tests each point within `max_range_m` of the
    camera centre against it.

    The points must lie on the mesh: only a surface in front of a point hides it (a
    one-sided test), which is what lets a low-resolution depth map work: a point is
    rounded to the nearest pixel centre, whose depth differs from the point's by up to
    about z * (0.7 px / f) * tan(incidence), under 1.5 % of z up to ~60 degrees
    incidence for f ~ 85 px (a quarter of a 640 px GoPro-like image), and at a silhouette
    the pixel centre may fall on the background, which does not hide the point. A nearer
    surface hides a point when it is more than tolerance_m + tolerance_rel * z in front
    of it; points within half a pixel of an occluding edge, or closer behind an occluder
    than that tolerance, may be counted wrongly. On the demo's scene (120 true views, a
    quarter of the image) the samples seen by 3 views agree with a full-resolution ray
    cast to about 1 % either way (with 0.03 + 0.03 z: 3 % too many, points close behind
    a nearer surface).

    progress_label: show a progress bar over the cameras with this label."""
    from scipy.spatial import cKDTree

    from postproc.dense.zbuffer import MeshRasteriser

    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    counts = np.zeros(len(points), np.int64)
    if len(points) == 0:
        return counts
    rasteriser = MeshRasteriser(vertices_m, triangles)
    tree = cKDTree(points) if np.isfinite(max_range_m) else None
    poses = [np.asarray(p, dtype=np.float64) for p in cams_from_world]
    loop: Iterable[FloatArray] = poses
    if progress_label is not None:
        from shared.progress import progress

        loop = progress(poses, total=len(poses), desc=progress_label, unit="view")
    for pose in loop:
        if tree is not None:
            centre = -pose[:3, :3].T @ pose[:3, 3]
            near = np.asarray(tree.query_ball_point(centre, max_range_m), dtype=np.int64)
        else:
            near = np.arange(len(points))
        if len(near) == 0:
            continue
        depth = rasteriser.depth_map(pose, K, width, height, near_m=near_m,
                                     max_range_m=max_range_m)  # fmt: skip
        if filmed is not None:
            depth[~filmed] = np.nan
        seen, _ = visibility(points[near], [K], [pose], [depth], tolerance_m=tolerance_m,
                             tolerance_rel=tolerance_rel, nearest=0, one_sided=True)  # fmt: skip
        counts[near] += seen
    return counts
