"""Timed pose sequences and the absolute trajectory error (ATE).

A `Trajectory` is a list of poses `T_frame_body` (or `T_frame_cam`), 4x4 in
metres, with int64 nanosecond stamps since the UNIX epoch. The ATE follows the
usual practice (Sturm et al. 2012; evo): associate poses by nearest time stamp,
align the estimate to the reference (SE(3), Sim(3) or not at all) with
Umeyama's method on positions, and report the RMSE of the position errors.

Pure math: no I/O (see `shared.formats.tum` for files).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from shared.clock import seconds_from_ns
from shared.geometry import interpolate_poses, make_pose, umeyama

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass
class Trajectory:
    """Poses (N, 4, 4) `T_frame_body` at strictly increasing stamps (N,) int64 ns since the epoch.

    Raises ValueError when shapes disagree, stamps are not integers or not
    strictly increasing, or a pose is not finite with bottom row (0, 0, 0, 1).
    """

    stamps_ns: IntArray
    poses: FloatArray

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns)
        if stamps.ndim != 1:
            raise ValueError(f"Trajectory: stamps_ns must be 1-D, got shape {stamps.shape}")
        if stamps.size and not np.issubdtype(stamps.dtype, np.integer):
            raise ValueError(
                f"Trajectory: stamps_ns must be integer nanoseconds, got {stamps.dtype}"
            )
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.shape != (stamps.shape[0], 4, 4):
            raise ValueError(
                f"Trajectory: poses must have shape ({stamps.shape[0]}, 4, 4) to match stamps_ns, "
                f"got {poses.shape}"
            )
        stamps = stamps.astype(np.int64)
        if np.any(np.diff(stamps) <= 0):
            bad = int(np.argmax(np.diff(stamps) <= 0))
            raise ValueError(
                f"Trajectory: stamps_ns must be strictly increasing (index {bad + 1}: "
                f"{stamps[bad + 1]} ns after {stamps[bad]} ns)"
            )
        if not np.all(np.isfinite(poses)):
            raise ValueError("Trajectory: poses contain non-finite values")
        if poses.size and not np.allclose(poses[:, 3, :], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise ValueError("Trajectory: poses must be homogeneous (last row 0 0 0 1)")
        self.stamps_ns = stamps
        self.poses = poses

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def positions(self) -> FloatArray:
        """Origins of the body frame in the trajectory frame (N, 3), metres."""
        return self.poses[:, :3, 3]

    @property
    def rotations(self) -> FloatArray:
        """Rotations `R_frame_body` (N, 3, 3)."""
        return self.poses[:, :3, :3]

    @property
    def duration_s(self) -> float:
        """Time from the first to the last pose in seconds (0.0 for fewer than two poses)."""
        if len(self) < 2:
            return 0.0
        return seconds_from_ns(int(self.stamps_ns[-1]) - int(self.stamps_ns[0]))

    def path_length_m(self) -> float:
        """Length of the polyline through the positions, metres."""
        if len(self) < 2:
            return 0.0
        return float(np.sum(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    def slice_time(self, start_ns: int, end_ns: int) -> Trajectory:
        """Poses with start_ns <= stamp <= end_ns (both ns on this trajectory's clock)."""
        keep = (self.stamps_ns >= start_ns) & (self.stamps_ns <= end_ns)
        return Trajectory(self.stamps_ns[keep], self.poses[keep])

    def interpolate(self, query_ns: npt.ArrayLike) -> Trajectory:
        """Poses at the query stamps (int64 ns, strictly increasing), slerp + linear.

        Queries outside [first, last] stamp are dropped; the returned stamps are
        the kept queries. Raises ValueError on an empty trajectory.
        """
        query = np.asarray(query_ns)
        if query.ndim != 1 or (query.size and not np.issubdtype(query.dtype, np.integer)):
            raise ValueError(
                f"interpolate: query_ns must be 1-D integer ns, got {query.dtype} {query.shape}"
            )
        if len(self) == 0:
            raise ValueError("interpolate: empty trajectory")
        query = query.astype(np.int64)
        kept = query[(query >= self.stamps_ns[0]) & (query <= self.stamps_ns[-1])]
        return Trajectory(kept, interpolate_poses(self.stamps_ns, self.poses, kept))

    def transformed(self, left_from_frame: npt.ArrayLike) -> Trajectory:
        """Poses expressed in another frame: `left_from_frame @ T_frame_body` for every pose."""
        left = np.asarray(left_from_frame, dtype=np.float64)
        if left.shape != (4, 4):
            raise ValueError(f"transformed: expected a (4, 4) pose, got {left.shape}")
        return Trajectory(self.stamps_ns.copy(), left @ self.poses)

    def right_multiplied(self, T: npt.ArrayLike) -> Trajectory:
        """Poses of another attached frame: `T_frame_body @ T` (T = T_B_C gives camera poses)."""
        right = np.asarray(T, dtype=np.float64)
        if right.shape != (4, 4):
            raise ValueError(f"right_multiplied: expected a (4, 4) pose, got {right.shape}")
        return Trajectory(self.stamps_ns.copy(), self.poses @ right)


@dataclass
class AteResult:
    """Absolute trajectory error of an estimate against a reference.

    `errors_m` (matched,) are the position errors after alignment, metres.
    The aligned estimate position is `scale * R @ p + t` with
    `alignment = make_pose(R, t)` (4, 4) (identity for align="none") and
    `scale` (1.0 unless align="sim3"). `stamps_ns` are the estimate stamps
    that were matched.
    """

    rmse_m: float
    errors_m: FloatArray
    alignment: FloatArray
    scale: float
    matched: int
    stamps_ns: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def associate(
    stamps_a_ns: npt.ArrayLike, stamps_b_ns: npt.ArrayLike, *, max_dt_ns: int
) -> tuple[IntArray, IntArray]:
    """Index pairs (i, j) matching each stamp of a to the nearest stamp of b within max_dt_ns.

    Both inputs are sorted int64 ns. Each b stamp is used at most once (the
    closest a stamp wins), so a dense estimate cannot match one reference pose
    twice. Returns (indices into a, indices into b), increasing.
    """
    a = np.asarray(stamps_a_ns, dtype=np.int64)
    b = np.asarray(stamps_b_ns, dtype=np.int64)
    if a.size == 0 or b.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy()
    right = np.clip(np.searchsorted(b, a), 0, b.size - 1)
    left = np.clip(right - 1, 0, b.size - 1)
    dt_right = np.abs(b[right] - a)
    dt_left = np.abs(b[left] - a)
    j = np.where(dt_left <= dt_right, left, right)
    dt = np.minimum(dt_left, dt_right)
    i = np.arange(a.size)
    ok = dt <= max_dt_ns
    i, j, dt = i[ok], j[ok], dt[ok]
    # One a per b: sort by (j, dt) and keep the first of each j.
    order = np.lexsort((dt, j))
    i, j = i[order], j[order]
    first = np.ones(j.size, dtype=bool)
    first[1:] = j[1:] != j[:-1]
    i, j = i[first], j[first]
    order = np.argsort(i)
    return i[order].astype(np.int64), j[order].astype(np.int64)


def ate(
    estimate: Trajectory,
    reference: Trajectory,
    *,
    align: Literal["se3", "sim3", "none"] = "se3",
    max_dt_ns: int = 10_000_000,
) -> AteResult:
    """Absolute trajectory error (position RMSE, metres) of `estimate` against `reference`.

    Poses are associated by nearest stamp within `max_dt_ns` (both on the
    same clock). The estimate is aligned to the reference on positions with
    Umeyama: "se3" rigid, "sim3" with scale (monocular), "none" as is.
    Raises ValueError for an unknown `align` or fewer than 3 matches.
    """
    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"ate: align must be 'se3', 'sim3' or 'none', got {align!r}")
    i, j = associate(estimate.stamps_ns, reference.stamps_ns, max_dt_ns=max_dt_ns)
    if i.size < 3:
        raise ValueError(
            f"ate: only {i.size} pose(s) matched within {max_dt_ns} ns (need at least 3; "
            "are both trajectories on the same clock?)"
        )
    p_est = estimate.positions[i]
    p_ref = reference.positions[j]
    if align == "none":
        R, t, scale = np.eye(3), np.zeros(3), 1.0
    else:
        R, t, scale = umeyama(p_est, p_ref, with_scale=align == "sim3")
    aligned = scale * p_est @ R.T + t
    errors = np.linalg.norm(aligned - p_ref, axis=1)
    return AteResult(
        rmse_m=float(np.sqrt(np.mean(errors * errors))),
        errors_m=errors,
        alignment=make_pose(R, t),
        scale=float(scale),
        matched=int(i.size),
        stamps_ns=estimate.stamps_ns[i],
    )
