"""Figures of the calibration stage (matplotlib, Agg: no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.fsutil import atomic_path

FloatArray = npt.NDArray[np.float64]


def plot_coverage(
    path: Path,
    *,
    image_size: tuple[int, int],
    corners_px: list[FloatArray],
    errors_px: list[FloatArray],
    cells: tuple[int, int],
    title: str,
    overwrite: bool = False,
) -> Path:
    """Corners of every view used over the image (one colour per view), the coverage cells
    that hold none shaded, and a histogram of the reprojection errors; written as PNG."""
    from matplotlib.figure import Figure

    width, height = image_size
    figure = Figure(figsize=(11, 4.6), layout="constrained")
    image_axes, error_axes = figure.subplots(1, 2, width_ratios=(2.2, 1))
    columns, rows = cells
    hit = np.zeros((rows, columns), dtype=bool)
    for points in corners_px:
        u = np.clip((points[:, 0] + 0.5) / width * columns, 0, columns - 1).astype(int)
        v = np.clip((points[:, 1] + 0.5) / height * rows, 0, rows - 1).astype(int)
        hit[v, u] = True
    image_axes.imshow(
        ~hit,
        extent=(-0.5, width - 0.5, height - 0.5, -0.5),
        cmap="Reds",
        vmin=0,
        vmax=3,
        interpolation="nearest",
    )
    colours = np.linspace(0.0, 1.0, max(len(corners_px), 1))
    for colour, points in zip(colours, corners_px, strict=False):
        image_axes.scatter(points[:, 0], points[:, 1], s=3, color=_viridis(colour))
    image_axes.set_xlim(-0.5, width - 0.5)
    image_axes.set_ylim(height - 0.5, -0.5)
    image_axes.set_aspect("equal")
    image_axes.set_xlabel("u (px)")
    image_axes.set_ylabel("v (px)")
    image_axes.set_title(f"corners of {len(corners_px)} views (red cells: none)")
    every_error = np.concatenate(errors_px) if errors_px else np.zeros(0)
    every_error = every_error[np.isfinite(every_error)]
    if len(every_error):
        error_axes.hist(every_error, bins=40, color="0.3")
    error_axes.set_xlabel("reprojection error (px)")
    error_axes.set_ylabel("corners")
    figure.suptitle(title)
    with atomic_path(path, overwrite=overwrite) as tmp:
        figure.savefig(tmp, format="png", dpi=110)
    return path


def _viridis(value: float) -> tuple[float, float, float, float]:
    from matplotlib import colormaps

    rgba = colormaps["viridis"](value)
    return (float(rgba[0]), float(rgba[1]), float(rgba[2]), float(rgba[3]))


def plot_rates(
    path: Path,
    *,
    times_s: FloatArray,
    camera_rates: FloatArray,
    imu_rates: FloatArray,
    title: str,
    labels: tuple[str, str] = ("camera", "gyro in camera frame"),
    overwrite: bool = False,
) -> Path:
    """Angular rates (rad/s, 3 axes) of two sensors after alignment, one panel per axis."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11, 6.5), layout="constrained")
    axes = figure.subplots(3, 1, sharex=True)
    for axis, name in enumerate("xyz"):
        axes[axis].plot(times_s, camera_rates[:, axis], ".", ms=2.5, label=labels[0])
        axes[axis].plot(times_s, imu_rates[:, axis], "-", lw=0.8, label=labels[1])
        axes[axis].set_ylabel(f"omega_{name} (rad/s)")
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time (s)")
    figure.suptitle(title)
    with atomic_path(path, overwrite=overwrite) as tmp:
        figure.savefig(tmp, format="png", dpi=110)
    return path
