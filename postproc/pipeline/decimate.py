"""Meshes and point clouds cut down to a budget for the report's 3D viewer.

Pure math, no I/O. Meshes are simplified by vertex clustering (Rossignac and Borrel):
the vertices in one cubic cell of a grid merge into their mean (colours too), triangles
whose corners fall into fewer than three cells vanish, duplicates go. It keeps the shape
to within about one cell and needs nothing beyond numpy; the cell is the smallest (to a
few per cent) that meets the triangle budget. Point clouds are subsampled at random with
a fixed seed (every point equally likely: dense areas stay dense).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
ByteArray = npt.NDArray[np.uint8]

# What the page carries: a few MB of geometry, drawn at interactive rates by a laptop's
# integrated GPU (and by SwiftShader on a machine without one).
MESH_TRIANGLE_BUDGET = 200_000
POINT_BUDGET = 300_000


@dataclass(kw_only=True)
class DecimatedMesh:
    """A simplified mesh: vertices (V,3) m, faces (F,3), colours (V,3) uint8 or None;
    cell_m is the clustering cell (0.0 when the mesh was within budget and kept as is)."""

    vertices_m: FloatArray
    faces: IntArray
    colours: ByteArray | None
    cell_m: float


def cluster_vertices(
    vertices_m: FloatArray,
    faces: IntArray,
    colours: ByteArray | None,
    *,
    cell_m: float,
) -> DecimatedMesh:
    """Merge the vertices in each cubic cell of side `cell_m` (grid anchored at the
    vertices' minimum corner); drop triangles that collapse and repeated triangles."""
    if cell_m <= 0:
        raise ValueError(f"cell_m must be positive, got {cell_m}")
    v = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    cells = np.floor((v - v.min(axis=0)) / cell_m).astype(np.int64)
    _, cluster, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    cluster = cluster.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, cluster, v)
    new_vertices = sums / counts[:, None]
    new_colours = None
    if colours is not None:
        colour_sums = np.zeros((len(counts), 3))
        np.add.at(colour_sums, cluster, np.asarray(colours, dtype=np.float64))
        new_colours = np.clip(np.rint(colour_sums / counts[:, None]), 0, 255).astype(np.uint8)
    g = cluster[f]
    keep = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
    g = g[keep]
    # The same triangle twice (either winding): keep the first.
    _, first = np.unique(np.sort(g, axis=1), axis=0, return_index=True)
    g = g[np.sort(first)]
    # Vertices no triangle uses any more are dropped, indices renumbered.
    used, g_local = np.unique(g, return_inverse=True)
    return DecimatedMesh(
        vertices_m=new_vertices[used],
        faces=g_local.reshape(-1, 3).astype(np.int64),
        colours=None if new_colours is None else new_colours[used],
        cell_m=float(cell_m),
    )


def decimate_mesh(
    vertices_m: FloatArray,
    faces: IntArray,
    colours: ByteArray | None,
    *,
    max_triangles: int = MESH_TRIANGLE_BUDGET,
) -> DecimatedMesh:
    """The mesh with at most `max_triangles` triangles: unchanged when it has no more,
    else vertex-clustered with the smallest cell (bisection in log scale, to 3 %) that
    meets the budget."""
    v = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) <= max_triangles:
        return DecimatedMesh(vertices_m=v, faces=f, colours=colours, cell_m=0.0)
    if max_triangles < 1:
        raise ValueError(f"max_triangles must be at least 1, got {max_triangles}")
    extent = float(np.max(v.max(axis=0) - v.min(axis=0)))
    # Mean edge length: a cell this size changes little; the whole extent leaves nothing.
    edges = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1)
    lo, hi = max(float(np.mean(edges)), extent * 1e-6), max(extent, 1e-9)
    best = cluster_vertices(v, f, colours, cell_m=hi)
    for _ in range(40):
        if hi / lo < 1.03:
            break
        mid = float(np.sqrt(lo * hi))
        trial = cluster_vertices(v, f, colours, cell_m=mid)
        if len(trial.faces) <= max_triangles:
            best, hi = trial, mid
        else:
            lo = mid
    return best


def subsample_points(count: int, *, max_points: int = POINT_BUDGET, seed: int = 0) -> IntArray:
    """Indices (sorted) of at most `max_points` of `count` points, drawn uniformly with
    the given seed; all indices when there are no more than that."""
    if count <= max_points:
        return np.arange(count, dtype=np.int64)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(count, size=max_points, replace=False)).astype(np.int64)
