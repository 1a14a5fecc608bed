"""The mesh as glTF 2.0 (`.gltf` + `.bin`, or one binary `.glb`) with vertex colours.

glTF is y up (its spec: +Y up, metres), our world frame is z up, so vertices are written
as (x, z, -y): Blender, three.js and every glTF viewer show the wreck upright, and
Blender's importer turns it back into (x, y, z). Coordinates are float32: a local frame
tens of metres across keeps them to a few micrometres.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.errors import InputError
from shared.fsutil import atomic_path

FloatArray = npt.NDArray[np.float64]

# Rows map world (x, y, z) to glTF (x, y, z): glTF y is world up.
GLTF_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def write_mesh_gltf(
    path: Path | str,
    vertices_m: FloatArray,
    faces: npt.NDArray[np.int64],
    colors: npt.NDArray[np.uint8] | None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a triangle mesh in the world frame (metres) as `.glb` or `.gltf` (by the
    suffix of `path`; a `.gltf` gets its buffer in `<stem>.bin` beside it). colors: (V,
    3) uint8 RGB per vertex, or None. Returns `path`."""
    import trimesh

    path = Path(path)
    if path.suffix not in (".glb", ".gltf"):
        raise ValueError(f"{path}: expected a .glb or .gltf name")
    faces = np.asarray(faces, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(f"{path.name}: the mesh has no triangles")
    mesh = trimesh.Trimesh(
        vertices=np.asarray(vertices_m, float) @ GLTF_FROM_WORLD.T,
        faces=faces,
        vertex_colors=None if colors is None else np.asarray(colors, np.uint8),
        process=False,
    )
    if path.suffix == ".glb":
        data = trimesh.exchange.gltf.export_glb(  # type: ignore[no-untyped-call]
            mesh, include_normals=True
        )
        with atomic_path(path, overwrite=overwrite) as tmp:
            tmp.write_bytes(data)
        return path
    buffer_name = path.stem + ".bin"
    files = trimesh.exchange.gltf.export_gltf(  # type: ignore[no-untyped-call]
        mesh, include_normals=True, merge_buffers=True
    )
    document = json.loads(files.pop("model.gltf"))
    if len(files) != 1 or len(document["buffers"]) != 1:
        raise RuntimeError(f"trimesh wrote {len(files)} buffers (expected one)")
    (payload,) = files.values()
    # trimesh names the buffer "gltf_buffer_*.bin"; give it ours.
    document["buffers"][0]["uri"] = buffer_name
    with atomic_path(path.with_name(buffer_name), overwrite=overwrite) as tmp:
        tmp.write_bytes(payload)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(json.dumps(document), encoding="utf-8")
    return path
