"""The fused point cloud as LAS 1.4 / LAZ (laspy; LAZ through the lazrs backend).

Point format 7 (LAS 1.4: xyz, intensity, GPS time, RGB). Coordinates are stored as int32
counts of `scale` from `offset`: a 1 mm scale keeps every point within 0.5 mm, and the
offset (the cloud's minimum, rounded down to a metre) keeps the counts small. RGB is
16 bits in LAS: 8-bit colours are multiplied by 257 (255 -> 65535). No CRS is written:
the frame is the run's local world frame (x, y horizontal, z up, 0 at the sea surface).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.errors import InputError
from shared.fsutil import atomic_path

FloatArray = npt.NDArray[np.float64]

POINT_FORMAT = 7
LAS_VERSION = "1.4"


def write_points_las(
    path: Path | str,
    points_m: FloatArray,
    colors: npt.NDArray[np.uint8] | None,
    *,
    scale_m: float = 0.001,
    overwrite: bool = False,
) -> Path:
    """Write points (N, 3) m with optional RGB (N, 3) uint8 to `.las` or `.laz` (by the
    suffix of `path`). Raises InputError when there are no points or the extent does
    not fit int32 counts of `scale_m`."""
    import laspy  # type: ignore[import-untyped]

    path = Path(path)
    if path.suffix not in (".las", ".laz"):
        raise ValueError(f"{path}: expected a .las or .laz name")
    points = np.asarray(points_m, float).reshape(-1, 3)
    if len(points) == 0:
        raise InputError(f"{path.name}: no points to write")
    offset = np.floor(points.min(axis=0))
    span = points.max(axis=0) - offset
    if np.any(span / scale_m >= 2**31 - 1):
        raise InputError(
            f"{path.name}: extent {span.max():.0f} m does not fit {scale_m} m steps in LAS"
        )
    header = laspy.LasHeader(point_format=POINT_FORMAT, version=LAS_VERSION)
    header.offsets = offset
    header.scales = np.full(3, scale_m)
    header.generating_software = "wreckmap"
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        rgb = np.asarray(colors, np.uint16) * 257
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    # Given a name, laspy chooses compression from its suffix (the temporary has none):
    # hand it an open file instead.
    with atomic_path(path, overwrite=overwrite) as tmp, tmp.open("wb") as f:
        las.write(f, do_compress=path.suffix == ".laz")
    return path
