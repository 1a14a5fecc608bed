"""Top and side views of merged sessions and targets (like the paper's Fig. 7)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.fsutil import atomic_path

FloatArray = npt.NDArray[np.float64]


def _outline(pose: FloatArray, extent_m: tuple[float, float]) -> FloatArray:
    """(5, 3) closed outline of a target's tag area in W (metres)."""
    w, h = extent_m
    corners = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0], [0, 0, 0]], dtype=np.float64)
    result: FloatArray = corners @ pose[:3, :3].T + pose[:3, 3]
    return result


def plot_merge(
    top_path: Path,
    side_path: Path,
    *,
    trajectories: Mapping[str, FloatArray],
    targets: Mapping[str, FloatArray],
    extents: Mapping[str, tuple[float, float]],
    overwrite: bool = False,
) -> None:
    """Write the top view (x-y) and the side view (x-z) as PNGs.

    trajectories: session name -> (N, 3) keyframe positions in W (metres).
    targets: target name -> `T_W_m` (4, 4); extents: its (width, height) in metres.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for path, (a, b), title in (
        (top_path, (0, 1), "top view (x, y)"),
        (side_path, (0, 2), "side view (x, z)"),
    ):
        figure, axes = plt.subplots(figsize=(8, 6), dpi=110)
        for name, positions in trajectories.items():
            axes.plot(positions[:, a], positions[:, b], lw=0.8, label=name)
        for name, pose in targets.items():
            outline = _outline(pose, extents[name])
            axes.plot(outline[:, a], outline[:, b], "k-", lw=2.0)
            axes.annotate(name, (pose[a, 3], pose[b, 3]), fontsize=8)
        axes.set_xlabel("x (m)")
        axes.set_ylabel("y (m)" if b == 1 else "z (m)")
        axes.set_aspect("equal", adjustable="datalim")
        axes.set_title(f"merged sessions: {title}")
        axes.grid(True, lw=0.3)
        if trajectories:
            axes.legend(fontsize=8, loc="best")
        with atomic_path(path, overwrite=overwrite) as tmp:
            figure.savefig(tmp, format="png")
        plt.close(figure)
