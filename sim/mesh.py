"""The simulated scene as a ground-truth triangle mesh (binary PLY with vertex colours).

`scene_mesh` is pure math: every visible box face (clipped at the seafloor; buried bottoms
left out), the textured seafloor rectangle and the AprilGrid boards, each split into cells
of at most `cell_m` with vertex colours taken from the face's texture (so a dense
reconstruction can be compared in geometry and in colour). `write_ply` writes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.formats.ply import PlyData
from shared.formats.ply import ply_bytes as encode_ply
from shared.formats.ply import write_ply as write_ply_file
from sim.scene import FACE_UV_AXES, WreckScene, face_hidden

FloatArray = npt.NDArray[np.float64]
MESH_PLY_COMMENT = "wreckmap simulated wreck, world frame W (z up, z=0 at the sea surface), metres"


def _grid(
    origin: FloatArray,
    axis_u: FloatArray,
    axis_v: FloatArray,
    size_u: float,
    size_v: float,
    cell_m: float,
) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Vertices (V,3) and triangles (F,3) of a rectangle origin + a*axis_u + b*axis_v."""
    nu = max(int(np.ceil(size_u / cell_m)), 1)
    nv = max(int(np.ceil(size_v / cell_m)), 1)
    a = np.linspace(0.0, size_u, nu + 1)
    b = np.linspace(0.0, size_v, nv + 1)
    aa, bb = np.meshgrid(a, b)
    verts = origin + aa.reshape(-1, 1) * axis_u + bb.reshape(-1, 1) * axis_v
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nv + 1, nu + 1)
    v00, v10 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    v01, v11 = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.column_stack((v00, v10, v11)), np.column_stack((v00, v11, v01))])
    return verts, tris


def _sample(
    texture: npt.NDArray[np.uint8], cols: FloatArray, rows: FloatArray
) -> npt.NDArray[np.uint8]:
    r = np.clip(np.rint(rows).astype(np.int64), 0, texture.shape[0] - 1)
    c = np.clip(np.rint(cols).astype(np.int64), 0, texture.shape[1] - 1)
    return texture[r, c]


@dataclass
class TruthMesh:
    """vertices (V,3) m in the world; colors (V,3) uint8 RGB; triangles (F,3) int32;
    triangle_face (F,) int32: the scene face of each triangle (scene numbering, targets
    after the seafloor)."""

    vertices: FloatArray
    colors: npt.NDArray[np.uint8]
    triangles: npt.NDArray[np.int32]
    triangle_face: npt.NDArray[np.int32]


def scene_mesh(scene: WreckScene, *, cell_m: float = 0.25) -> TruthMesh:
    """The scene's visible surfaces as a coloured triangle mesh.

    Triangles are wound counter-clockwise seen from outside (normals point out of boxes,
    up from the seafloor, out of the printed side of the targets).
    """
    all_v: list[FloatArray] = []
    all_c: list[npt.NDArray[np.uint8]] = []
    all_f: list[npt.NDArray[np.int64]] = []
    all_label: list[npt.NDArray[np.int64]] = []
    count = 0

    def add(
        verts: FloatArray,
        tris: npt.NDArray[np.int64],
        colors: npt.NDArray[np.uint8],
        flip: bool,
        label: int,
    ) -> None:
        nonlocal count
        all_v.append(verts)
        all_c.append(colors)
        all_f.append((tris[:, ::-1] if flip else tris) + count)
        all_label.append(np.full(len(tris), label, dtype=np.int64))
        count += len(verts)

    eye = np.eye(3)
    floor = scene.seafloor_z_m
    for b, box in enumerate(scene.boxes):
        lo, hi = np.array(box.lo_m), np.array(box.hi_m)
        for axis in range(3):
            u_axis, v_axis = FACE_UV_AXES[axis]
            for side in range(2):
                if face_hidden(scene.boxes, 6 * b + 2 * axis + side, floor):
                    continue
                v_lo = max(lo[v_axis], floor) if v_axis == 2 else lo[v_axis]
                if hi[v_axis] <= v_lo:
                    continue
                origin = lo.copy()
                origin[axis] = hi[axis] if side else lo[axis]
                origin[v_axis] = v_lo
                verts, tris = _grid(
                    origin,
                    eye[u_axis],
                    eye[v_axis],
                    hi[u_axis] - lo[u_axis],
                    hi[v_axis] - v_lo,
                    cell_m,
                )
                face = 6 * b + 2 * axis + side
                texel = scene.texel_m[face]
                cols = (verts[:, u_axis] - lo[u_axis]) / texel
                rows = (hi[v_axis] - verts[:, v_axis]) / texel
                colors = _sample(scene.textures[face], cols, rows)
                # u x v = +axis for axes 0 and 2 and -axis for axis 1 (u=x, v=z: x cross z = -y).
                outward = 1 if side else -1
                uv_sign = -1 if axis == 1 else 1
                add(verts, tris, colors, flip=outward != uv_sign, label=face)
    x0, x1, y0, y1 = scene.seafloor_extent_m
    verts, tris = _grid(np.array([x0, y0, floor]), eye[0], eye[1], x1 - x0, y1 - y0, 1.0)
    texel = scene.texel_m[scene.seafloor_face]
    colors = _sample(
        scene.textures[scene.seafloor_face], (verts[:, 0] - x0) / texel, (y1 - verts[:, 1]) / texel
    )
    add(verts, tris, colors, flip=False, label=scene.seafloor_face)
    for k, placement in enumerate(scene.targets):
        xa, xb, ya, yb = placement.bounds_m
        T = placement.world_from_target
        local, tris = _grid(np.array([xa, ya, 0.0]), eye[0], eye[1], xb - xa, yb - ya, 1.0)
        verts = local @ T[:3, :3].T + T[:3, 3]
        add(
            verts, tris, np.full((len(verts), 3), 200, dtype=np.uint8), flip=False,
            label=scene.seafloor_face + 1 + k,
        )  # fmt: skip
    return TruthMesh(
        vertices=np.concatenate(all_v),
        colors=np.concatenate(all_c),
        triangles=np.concatenate(all_f).astype(np.int32),
        triangle_face=np.concatenate(all_label).astype(np.int32),
    )


def _ply(mesh: TruthMesh) -> PlyData:
    return PlyData(
        vertices=mesh.vertices, colors=mesh.colors, faces=mesh.triangles.astype(np.int64)
    )


def ply_bytes(mesh: TruthMesh) -> bytes:
    """A binary little-endian PLY: float32 x, y, z, uchar red, green, blue; int32 faces."""
    return encode_ply(_ply(mesh), comments=[MESH_PLY_COMMENT])


def write_ply(path: Path | str, mesh: TruthMesh, *, overwrite: bool = False) -> Path:
    """Write a coloured triangle mesh as binary PLY (atomic; refuses to overwrite unless asked)."""
    return write_ply_file(path, _ply(mesh), comments=[MESH_PLY_COMMENT], overwrite=overwrite)
