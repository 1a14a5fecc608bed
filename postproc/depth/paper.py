"""The paper's depth correction (Mapping Pamir, "Absolute Water Depth Correction").

Kept as a baseline (`--method paper`) to compare with `sync.fit_depth_sync`.
Pure math, same time conventions as `postproc.depth.sync` (relative seconds):

1. keep the period common to both series (on the clocks as they are, after an
   optional whole shift the user already knows, such as a time-zone error);
2. resample both linearly to 100 Hz;
3. take the lag of the maximum of the cross-correlation of the two
   mean-removed series as the time shift (so the shift is a multiple of
   0.01 s and the dive profile between its 10 s samples is a straight line);
4. interpolate the trajectory z at every dive sample (shifted) and fit a line
   depth = a + b z by ordinary least squares: the depth offset is a, the
   scale -b (z is up, depth down).

The paper estimates no clock drift; its shift is a single number.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from postproc.depth.sync import DepthSync, SyncError, valid_mask

FloatArray = npt.NDArray[np.float64]


def paper_depth_sync(
    traj_t_s: npt.ArrayLike,
    traj_z_m: npt.ArrayLike,
    dive_t_s: npt.ArrayLike,
    dive_depth_m: npt.ArrayLike,
    *,
    prior_offset_s: float = 0.0,
    rate_hz: float = 100.0,
    min_common_s: float = 60.0,
    max_gap_s: float = 5.0,
) -> DepthSync:
    """Time shift by 100 Hz cross-correlation, depth offset and scale by linear regression.

    `prior_offset_s` is a dive-minus-camera shift applied before choosing the
    common period (0 for the paper's clocks "approximately right"). Time
    sigma is not defined by the method and is reported as NaN; the depth
    offset and scale sigmas are the ordinary least-squares ones. Raises
    SyncError when the common period is shorter than `min_common_s`.
    """
    traj_t = np.asarray(traj_t_s, dtype=np.float64)
    traj_z = np.asarray(traj_z_m, dtype=np.float64)
    dive_t = np.asarray(dive_t_s, dtype=np.float64)
    depth = np.asarray(dive_depth_m, dtype=np.float64)
    finite = np.isfinite(depth)
    dive_t, depth = dive_t[finite], depth[finite]
    if dive_t.size < 3:
        raise SyncError(f"only {dive_t.size} dive samples with a depth (need at least 3)")
    shifted = dive_t - prior_offset_s
    start = max(traj_t[0], shifted[0])
    end = min(traj_t[-1], shifted[-1])
    if end - start < min_common_s:
        raise SyncError(
            f"the trajectory and the dive share {max(end - start, 0.0):.0f} s on the clocks as "
            f"they are (shift {prior_offset_s:+.0f} s); the paper's method needs at least "
            f"{min_common_s:.0f} s in common"
        )
    dt = 1.0 / rate_hz
    grid = start + dt * np.arange(int(np.floor((end - start) / dt)) + 1)
    camera = -np.interp(grid, traj_t, traj_z)  # depth-like (down), arbitrary origin
    dive = np.interp(grid, shifted, depth)
    a = camera - camera.mean()
    b = dive - dive.mean()
    size = 1 << int(np.ceil(np.log2(2 * grid.size)))
    full = np.fft.irfft(np.conj(np.fft.rfft(a, size)) * np.fft.rfft(b, size), size)
    # corr[s] = sum_i a[i] b[i + s], s = -(n - 1) .. n - 1; the dive lags the camera by s.
    corr = np.concatenate([full[size - (grid.size - 1) :], full[: grid.size]])
    lag = int(np.argmax(corr)) - (grid.size - 1)
    offset = prior_offset_s + lag * dt

    u = dive_t - offset
    use = valid_mask(traj_t, u, max_gap_s=max_gap_s)
    if np.count_nonzero(use) < 3:
        raise SyncError("fewer than 3 dive samples inside the trajectory after the shift")
    z = np.interp(u[use], traj_t, traj_z)
    d = depth[use]
    X = np.column_stack([np.ones_like(z), z])
    coef, *_ = np.linalg.lstsq(X, d, rcond=None)
    r = d - X @ coef
    dof = max(d.size - 2, 1)
    cov2 = float(r @ r) / dof * np.linalg.pinv(X.T @ X)
    cov = np.full((4, 4), 0.0)
    cov[0, 0] = np.nan
    cov[2:, 2:] = cov2 * np.array([[1.0, -1.0], [-1.0, 1.0]])
    return DepthSync(
        time_offset_s=float(offset),
        drift_ppm=0.0,
        depth_offset_m=float(coef[0]),
        depth_scale=float(-coef[1]),
        residual_rms_m=float(np.sqrt(np.mean(r * r))),
        time_offset_sigma_s=float("nan"),
        drift_sigma_ppm=0.0,
        depth_offset_sigma_m=float(np.sqrt(cov2[0, 0])),
        depth_scale_sigma=float(np.sqrt(cov2[1, 1])),
        used=int(d.size),
        inliers=int(d.size),
        robust_scale_m=float(np.sqrt(np.mean(r * r))),
        covariance=cov,
    )
