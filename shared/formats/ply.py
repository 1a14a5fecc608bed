"""PLY point clouds and meshes (binary little-endian), the one reader and writer of the tree.

What is read: any binary_little_endian file whose elements hold scalar properties or
one list property of triangles (faces), as COLMAP's fusion and Poisson meshing, and
every writer below, write them. The vertex element gives x, y, z and, when present,
nx, ny, nz and red, green, blue; other elements and properties are skipped. ASCII
and big-endian files are refused with an error naming the format (no caller writes
or needs them).

What is written: vertices as float32 x, y, z, optional float32 normals and uchar
colours, optional triangles as `list uchar int vertex_indices`, and `comment` lines
after the format line (the frame and units of the coordinates, say). Written to a
temporary name and renamed, never over an existing file unless asked.

Callers: SLAM landmarks (`map.ply`), the dense stage (fused points, meshes), the
export and report tools, the simulator's truth mesh.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.errors import InputError
from shared.fsutil import atomic_path

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip


@dataclass
class PlyData:
    """vertices (V,3) float64 m; normals (V,3) or None; colors (V,3) uint8 or None;
    faces (F,3) int64 (empty for point clouds)."""

    vertices: npt.NDArray[np.float64]
    normals: npt.NDArray[np.float64] | None = None
    colors: npt.NDArray[np.uint8] | None = None
    faces: npt.NDArray[np.int64] | None = None


def read_ply(path: Path | str) -> PlyData:
    """Read a binary little-endian PLY (vertex element with x, y, z; optional face element
    of triangles)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such PLY file")
    data = path.read_bytes()
    lines, offset = _header_lines(path, data)
    header = [line.decode("ascii", errors="replace") for line in lines]
    elements: list[tuple[str, int, list[tuple[str, ...]]]] = []
    fmt = ""
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            elements[-1][2].append(tuple(words[1:]))
    if fmt != "binary_little_endian":
        raise InputError(f"{path}: PLY format {fmt!r} (expected binary_little_endian)")
    result = PlyData(vertices=np.zeros((0, 3)))
    for name, count, props in elements:
        if any(p[0] == "list" for p in props):
            if len(props) != 1 or count == 0:
                if count == 0:
                    continue
                raise InputError(f"{path}: element {name} mixes list and scalar properties")
            _, count_type, index_type, _ = props[0]
            ctype, itype = np.dtype(_TYPES[count_type]), np.dtype(_TYPES[index_type])
            # Triangles only (what Poisson meshing writes): fixed-size records.
            record = np.dtype([("n", ctype), ("idx", itype, (3,))])
            size = record.itemsize * count
            rec = np.frombuffer(data, dtype=record, count=count, offset=offset)
            if np.any(rec["n"] != 3):
                raise InputError(f"{path}: faces other than triangles are not supported")
            if name == "face":
                result.faces = rec["idx"].astype(np.int64)
            offset += size
            continue
        try:
            record = np.dtype([(p[1], _TYPES[p[0]]) for p in props])
        except KeyError as error:
            raise InputError(f"{path}: unknown PLY property type {error}") from error
        rec = np.frombuffer(data, dtype=record, count=count, offset=offset)
        offset += record.itemsize * count
        if name != "vertex":
            continue
        names = record.names or ()
        result.vertices = np.column_stack([rec[a] for a in ("x", "y", "z")]).astype(np.float64)
        if all(a in names for a in ("nx", "ny", "nz")):
            result.normals = np.column_stack([rec[a] for a in ("nx", "ny", "nz")]).astype(
                np.float64
            )
        if all(a in names for a in ("red", "green", "blue")):
            result.colors = np.column_stack([rec[a] for a in ("red", "green", "blue")]).astype(
                np.uint8
            )
    return result


def vertex_ply_header(path: Path | str) -> tuple[list[bytes], int, int]:
    """(header lines before `end_header`, vertex count, byte offset of the body) of a
    PLY holding one vertex element only (a point cloud), read without its body."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such PLY file")
    with path.open("rb") as f:
        lines, offset = _header_lines(path, f.read(1 << 16))
    elements = [ln for ln in lines if ln.startswith(b"element ")]
    if len(elements) != 1 or not elements[0].startswith(b"element vertex "):
        raise InputError(f"{path}: expected a point cloud (one vertex element), got {elements}")
    return lines, int(elements[0].split()[2]), offset


def _header_lines(path: Path, data: bytes) -> tuple[list[bytes], int]:
    """The header lines of the PLY whose bytes start `data`, up to `end_header` (not
    included), and the byte offset of its body."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path}: not a PLY file (expected 'ply' ... 'end_header')")
    return data[:end].splitlines(), end + len(b"end_header\n")


def ply_bytes(ply: PlyData, *, comments: Sequence[str] = ()) -> bytes:
    """Encode as binary little-endian PLY (float32 coordinates and normals, uchar colours,
    int32 triangle indices), with one `comment` line per entry of `comments`."""
    if any("\n" in c or "\r" in c for c in comments):
        raise ValueError("PLY comments must be single lines")
    v = np.asarray(ply.vertices, dtype=np.float64).reshape(-1, 3)
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if ply.normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if ply.colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    record = np.empty(len(v), dtype=np.dtype(fields))
    for k, axis in enumerate("xyz"):
        record[axis] = v[:, k]
    if ply.normals is not None:
        for k, axis in enumerate(("nx", "ny", "nz")):
            record[axis] = ply.normals[:, k]
    if ply.colors is not None:
        for k, axis in enumerate(("red", "green", "blue")):
            record[axis] = ply.colors[:, k]
    names = {"<f4": "float", "u1": "uchar"}
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {len(v)}")
    lines += [f"property {names[t]} {n}" for n, t in fields]
    faces = np.zeros((0, 3), np.int64) if ply.faces is None else np.asarray(ply.faces)
    if ply.faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    body = record.tobytes()
    if ply.faces is not None:
        frec = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
        frec["n"] = 3
        frec["idx"] = faces
        body += frec.tobytes()
    return ("\n".join(lines) + "\n").encode("ascii") + body


def write_ply(
    path: Path | str, ply: PlyData, *, comments: Sequence[str] = (), overwrite: bool = False
) -> Path:
    """Write `ply` (atomic; refuses to overwrite unless asked); returns `path`."""
    data = ply_bytes(ply, comments=comments)
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)
