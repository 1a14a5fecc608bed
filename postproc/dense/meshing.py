"""Screened Poisson meshing of the fused points, with the octree depth chosen from the
scene, then trimmed to the surface the points support.

COLMAP's defaults (depth 13, trim 10) suit dense laboratory captures; on a sparse cloud
they return an empty mesh. Here the octree's finest cell is matched to the point spacing:
depth = ceil(log2(extent / spacing)), and trimming removes mesh vertices farther than a few
point spacings from any fused point (Poisson closes holes with surface that nothing saw).
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.dense.options import MeshingOptions as MeshingOptions
from shared.errors import InputError, OutputExistsError, StageError
from shared.formats.ply import PlyData, read_ply, write_ply

FloatArray = npt.NDArray[np.float64]


def point_spacing_m(
    points_m: npt.ArrayLike, *, sample: int = 20000, seed: int = 0, tree: Any = None
) -> float:
    """Median distance from a point to its nearest neighbour (a random sample of points);
    tree: a `cKDTree` of these points already built (None: build one)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if len(points) < 2:
        raise ValueError("need at least two points to measure their spacing")
    tree = tree if tree is not None else cKDTree(points)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(points), size=min(sample, len(points)), replace=False)
    dist, _ = tree.query(points[idx], k=2)
    return float(np.median(dist[:, 1]))


def lone_points(
    points_m: FloatArray,
    neighbours: int,
    radius_m: float,
    *,
    radius_spacings: float = 0.0,
) -> npt.NDArray[np.bool_]:
    """True (N,) for the points with fewer than `neighbours` other points within
    `radius_m` (m), or within `radius_spacings` times their `point_spacing_m` where that
    is larger: a coarse cloud has fewer points in the same radius. The search stops at
    `neighbours` + 1, so a dense cloud costs no more than a sparse one."""
    from scipy.spatial import cKDTree

    if len(points_m) == 0:
        return np.zeros(0, bool)
    k = min(neighbours + 1, len(points_m))
    tree = cKDTree(points_m)
    if radius_spacings > 0 and len(points_m) > 1:
        radius_m = max(radius_m, radius_spacings * point_spacing_m(points_m, tree=tree))
    distances, _ = tree.query(points_m, k=[k], distance_upper_bound=radius_m, workers=-1)
    # The k-th nearest (the point itself first) missing: fewer than k - 1 others.
    lone: npt.NDArray[np.bool_] = ~np.isfinite(distances[:, 0])
    if k < neighbours + 1:  # fewer points in all than asked for
        lone[:] = True
    return lone


def scene_extent_m(points_m: npt.ArrayLike) -> float:
    """Longest side of the points' bounding box, robust to a few strays (0.5-99.5 %)."""
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    lo, hi = np.percentile(points, [0.5, 99.5], axis=0)
    return float(np.max(hi - lo))


def choose_octree_depth(
    extent_m: float, spacing_m: float, *, min_depth: int = 6, max_depth: int = 11
) -> int:
    """The octree depth whose finest cell is about one point spacing across the scene:
    ceil(log2(extent / spacing)), clamped to [min_depth, max_depth]."""
    if not (extent_m > 0 and spacing_m > 0):
        raise ValueError(f"extent and spacing must be positive, got {extent_m}, {spacing_m}")
    depth = math.ceil(math.log2(max(extent_m / spacing_m, 1.0)))
    return int(min(max(depth, min_depth), max_depth))


def trim_mesh(mesh: PlyData, points_m: FloatArray, max_distance_m: float) -> PlyData:
    """Keep the triangles whose three vertices lie within `max_distance_m` of a point;
    unused vertices are dropped and faces renumbered."""
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(points_m).query(mesh.vertices, distance_upper_bound=max_distance_m)
    return keep_vertices(mesh, np.isfinite(dist))


def keep_vertices(mesh: PlyData, keep: npt.NDArray[np.bool_]) -> PlyData:
    """The triangles of `mesh` whose three vertices are kept (`keep`, one flag a vertex);
    vertices no kept triangle uses are dropped and faces renumbered."""
    faces = mesh.faces if mesh.faces is not None else np.zeros((0, 3), np.int64)
    keep_faces = faces[np.all(keep[faces], axis=1)] if len(faces) else faces
    used = np.zeros(len(mesh.vertices), bool)
    used[keep_faces.ravel()] = True
    new_index = np.cumsum(used) - 1
    return PlyData(
        vertices=mesh.vertices[used],
        normals=None if mesh.normals is None else mesh.normals[used],
        colors=None if mesh.colors is None else mesh.colors[used],
        faces=new_index[keep_faces],
    )


def write_mesh(path: Path, surface: PlyData, *, empty: str, overwrite: bool = False) -> int:
    """Write `surface` to `path` (atomic) and return its triangle count; raises
    StageError(`empty`) instead when it has no triangle."""
    faces = 0 if surface.faces is None else len(surface.faces)
    if faces == 0:
        raise StageError(empty)
    write_ply(path, surface, overwrite=overwrite)
    return faces


@dataclass
class MeshReport:
    """What meshing chose and produced."""

    octree_depth: int
    spacing_m: float
    extent_m: float
    vertices: int
    faces: int


def mesh(
    options: MeshingOptions, fused_ply: Path, mesh_ply: Path, *, overwrite: bool = False
) -> MeshReport:
    """Poisson-mesh the points of `fused_ply` (with normals) into a trimmed `mesh_ply`."""
    import pycolmap

    mesh_ply = Path(mesh_ply)
    if mesh_ply.exists() and not overwrite:
        raise OutputExistsError(f"{mesh_ply}: already exists (refusing to overwrite)")
    cloud = read_ply(fused_ply)
    if len(cloud.vertices) < 10 or cloud.normals is None:
        raise InputError(
            f"{fused_ply}: {len(cloud.vertices)} points"
            f"{'' if cloud.normals is not None else ' without normals'} "
            "(expected a fused cloud with normals, at least 10 points)"
        )
    spacing = point_spacing_m(cloud.vertices)
    extent = scene_extent_m(cloud.vertices)
    depth = options.octree_depth or choose_octree_depth(
        extent, spacing, min_depth=options.min_depth, max_depth=options.max_depth
    )
    with tempfile.TemporaryDirectory(prefix=".poisson.", dir=mesh_ply.parent) as tmp:
        raw = Path(tmp) / "poisson.ply"
        pycolmap.poisson_meshing(
            str(fused_ply),
            str(raw),
            options=pycolmap.PoissonMeshingOptions(
                depth=depth,
                trim=options.poisson_trim,
                point_weight=options.point_weight,
                num_threads=options.num_threads,
                color=cloud.colors is not None,
            ),
        )
        if not raw.is_file():
            raise StageError(f"{fused_ply}: Poisson meshing wrote no mesh (depth {depth})")
        surface = read_ply(raw)
    if options.trim_distance_spacings > 0 and len(surface.vertices):
        # Mesh vertices are about one octree cell apart: never trim finer than that.
        cell = extent / 2.0**depth
        distance = options.trim_distance_spacings * max(spacing, cell)
        surface = trim_mesh(surface, cloud.vertices, distance)
    faces = write_mesh(
        mesh_ply,
        surface,
        empty=f"{fused_ply}: Poisson meshing gave an empty mesh (octree depth {depth}, "
        f"point spacing {spacing:.4f} m, extent {extent:.2f} m)",
        overwrite=overwrite,
    )
    return MeshReport(
        octree_depth=depth,
        spacing_m=spacing,
        extent_m=extent,
        vertices=len(surface.vertices),
        faces=faces,
    )
