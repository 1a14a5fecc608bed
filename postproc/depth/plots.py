"""The depth stage's figure, after the paper's Fig. 4 (matplotlib, Agg, no display needed).

(a) the trajectory's -z and the dive profile, each on its own clock; (b) both
on the camera clock after the sync, still in their own depth origins;
(c) the regression scatter of dive depth against trajectory z with the fitted
line; (d) the trajectory at its true depth (and after depth fusion) over the
dive samples.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from postproc.depth.sync import DepthSync, valid_mask
from shared.fsutil import atomic_path

FloatArray = npt.NDArray[np.float64]


def plot_depth_sync(
    path: Path | str,
    *,
    traj_t_s: FloatArray,
    traj_z_m: FloatArray,
    dive_t_s: FloatArray,
    dive_depth_m: FloatArray,
    sync: DepthSync,
    fused_z_m: FloatArray | None = None,
    title: str = "",
    max_gap_s: float = 5.0,
    overwrite: bool = False,
) -> Path:
    """Write the four-panel PNG; times are relative seconds as in `postproc.depth.sync`."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 8), layout="constrained")
    ax = fig.subplots(2, 2)
    minutes = 1.0 / 60.0
    ax[0, 0].plot(traj_t_s * minutes, -traj_z_m, color="tab:red", lw=1, label="trajectory -z")
    ax[0, 0].plot(
        dive_t_s * minutes,
        dive_depth_m,
        ".-",
        color="tab:blue",
        ms=3,
        lw=0.5,
        label="dive computer",
    )
    ax[0, 0].set_title("(a) before: each on its own clock")
    ax[0, 0].set_xlabel("clock minus trajectory start [min]")

    cam_t = sync.camera_time_s(dive_t_s)
    inside = valid_mask(traj_t_s, cam_t, max_gap_s=max_gap_s)
    lo = traj_t_s[0] - 120.0
    hi = traj_t_s[-1] + 120.0
    near = (cam_t >= lo) & (cam_t <= hi)
    ax[0, 1].plot(traj_t_s * minutes, -traj_z_m, color="tab:red", lw=1, label="trajectory -z")
    ax[0, 1].plot(
        cam_t[near] * minutes,
        dive_depth_m[near],
        ".",
        color="tab:blue",
        ms=4,
        label="dive computer",
    )
    ax[0, 1].set_title(
        f"(b) on the camera clock: offset {sync.time_offset_s:.2f} s, "
        f"drift {sync.drift_ppm:.1f} ppm"
    )

    z_at = np.interp(cam_t[inside], traj_t_s, traj_z_m)
    ax[1, 0].plot(z_at, dive_depth_m[inside], ".", color="tab:blue", ms=4, label="samples")
    if z_at.size:
        line_z = np.linspace(z_at.min(), z_at.max(), 2)
        ax[1, 0].plot(
            line_z,
            sync.depth_m(line_z),
            color="k",
            lw=1,
            label=f"depth = {sync.depth_offset_m:.2f} - {sync.depth_scale:.3f} z",
        )
    ax[1, 0].set_title(f"(c) regression: residual RMS {sync.residual_rms_m:.3f} m")
    ax[1, 0].set_xlabel("trajectory z [m]")
    ax[1, 0].set_ylabel("dive-computer depth [m]")

    ax[1, 1].plot(
        traj_t_s * minutes, sync.depth_m(traj_z_m), color="tab:red", lw=1, label="trajectory depth"
    )
    if fused_z_m is not None:
        ax[1, 1].plot(
            traj_t_s * minutes, -fused_z_m, color="tab:green", lw=1, label="after depth factors"
        )
    ax[1, 1].plot(
        cam_t[near] * minutes,
        dive_depth_m[near],
        ".",
        color="tab:blue",
        ms=4,
        label="dive computer",
    )
    ax[1, 1].set_title("(d) after: true depth on the camera clock")
    for a in (ax[0, 0], ax[0, 1], ax[1, 1]):
        a.invert_yaxis()
        a.set_ylabel("depth [m]")
        if a is not ax[0, 0]:
            a.set_xlabel("camera time from trajectory start [min]")
    for a in ax.flat:
        a.grid(True, alpha=0.3)
        a.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    with atomic_path(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    return Path(path)
