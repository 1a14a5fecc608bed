"""The mesh as glTF 2.0 (`.gltf` + `.bin`, or one binary `.glb`) with vertex colours.

glTF is y up (its spec: +Y up, metres), our world frame is z up, so vertices are written
as (x, z, -y): Blender, three.js and every glTF viewer show the wreck upright, and
Blender's importer turns it back into (x, y, z). Positions are float32 (a local frame
tens of metres across keeps them to a few micrometres), normals float32 (area-weighted
vertex normals), indices uint32. The spec defines COLOR_0 as linear RGB, and our colours
are sRGB (from the images): they are converted and stored as normalised uint16 RGBA
(alpha 1), so the dark water tones keep their gradation (uint8 linear would band them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.errors import InputError
from shared.fsutil import atomic_path

FloatArray = npt.NDArray[np.float64]

# Rows map world (x, y, z) to glTF (x, y, z): glTF y is world up.
GLTF_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def srgb_to_linear(srgb: npt.NDArray[np.uint8]) -> FloatArray:
    """Linear RGB in [0, 1] of 8-bit sRGB values (the sRGB transfer function, IEC
    61966-2-1)."""
    c = np.asarray(srgb, float) / 255.0
    linear: FloatArray = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return linear


def vertex_normals(vertices: FloatArray, faces: npt.NDArray[np.int64]) -> FloatArray:
    """Unit area-weighted vertex normals (a vertex no face uses gets +z)."""
    tri = vertices[faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    unit: FloatArray = np.where(length > 0, normals / np.maximum(length, 1e-300), [0, 0, 1])
    return unit


def gltf_document(
    vertices_m: FloatArray, faces: npt.NDArray[np.int64], colors: npt.NDArray[np.uint8] | None
) -> tuple[object, bytes]:
    """The pygltflib document of one mesh (one node, one primitive) and its buffer."""
    import pygltflib as g  # type: ignore[import-untyped]

    positions = (np.asarray(vertices_m, float) @ GLTF_FROM_WORLD.T).astype("<f4")
    normals = (vertex_normals(np.asarray(vertices_m, float), faces) @ GLTF_FROM_WORLD.T).astype(
        "<f4"
    )
    indices = np.asarray(faces, "<u4").reshape(-1)
    arrays: list[tuple[npt.NDArray[np.generic], int, str, int | None, bool]] = [
        (indices, g.UNSIGNED_INT, g.SCALAR, g.ELEMENT_ARRAY_BUFFER, False),
        (positions, g.FLOAT, g.VEC3, g.ARRAY_BUFFER, False),
        (normals, g.FLOAT, g.VEC3, g.ARRAY_BUFFER, False),
    ]
    if colors is not None:
        # RGBA (alpha 1): vertex attribute elements must be 4-byte aligned (the spec),
        # which three uint16 are not.
        linear = np.rint(srgb_to_linear(colors) * 65535).astype("<u2")
        rgba = np.column_stack((linear, np.full(len(linear), 65535, "<u2")))
        arrays.append((rgba, g.UNSIGNED_SHORT, g.VEC4, g.ARRAY_BUFFER, True))
    blob = b""
    views, accessors = [], []
    for k, (data, component, kind, target, normalized) in enumerate(arrays):
        blob += b"\0" * (-len(blob) % 4)  # every view starts 4-byte aligned
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes,
                                  target=target))  # fmt: skip
        accessor = g.Accessor(bufferView=k, componentType=component, count=len(data),
                              type=kind, normalized=normalized or None)  # fmt: skip
        if k == 1:  # POSITION needs its bounds
            accessor.min = data.min(axis=0).tolist()
            accessor.max = data.max(axis=0).tolist()
        accessors.append(accessor)
        blob += data.tobytes()
    blob += b"\0" * (-len(blob) % 4)
    attributes = g.Attributes(POSITION=1, NORMAL=2, COLOR_0=3 if colors is not None else None)
    document = g.GLTF2(
        asset=g.Asset(version="2.0", generator="wreckmap export"),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0, name="wreck")],
        meshes=[g.Mesh(primitives=[g.Primitive(attributes=attributes, indices=0,
                                               mode=g.TRIANGLES)])],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
    )  # fmt: skip
    return document, blob


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
    3) uint8 sRGB per vertex, or None. Returns `path`."""
    path = Path(path)
    if path.suffix not in (".glb", ".gltf"):
        raise ValueError(f"{path}: expected a .glb or .gltf name")
    faces = np.asarray(faces, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(f"{path.name}: the mesh has no triangles")
    document, blob = gltf_document(vertices_m, faces, colors)
    if path.suffix == ".glb":
        document.set_binary_blob(blob)  # type: ignore[attr-defined]
        data = b"".join(document.save_to_bytes())  # type: ignore[attr-defined]
        with atomic_path(path, overwrite=overwrite) as tmp:
            tmp.write_bytes(data)
        return path
    buffer_name = path.stem + ".bin"
    document.buffers[0].uri = buffer_name  # type: ignore[attr-defined]
    with atomic_path(path.with_name(buffer_name), overwrite=overwrite) as tmp:
        tmp.write_bytes(blob)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(document.gltf_to_json(), encoding="utf-8")  # type: ignore[attr-defined]
    return path
