"""Stabilised video: the visual-only path, put in a gravity-aligned, metric frame by the IMU.

Pure math, no I/O. In an electronically stabilised clip (GoPro HyperSmooth,
the MAX in HERO mode) each image is re-rendered for a virtual camera that turns
less than, and later than, the body: no fixed `T_B_C` links image and IMU, so
the tightly coupled estimator would hold IMU dead reckoning against
observations it cannot explain (on the MAX sample: 11 landmarks, a path 4 m
up a staircase that was not there). The images still give a good path of the
virtual camera up to scale (two-view start, PnP, bundle adjustment:
`visual_only`), and the IMU gives what is robust to a few degrees of attitude
error:

- gravity: the accelerometer's specific force, turned into the visual frame by
  the virtual camera's attitude and averaged over the clip, points up (the
  body's own accelerations average out over seconds; the virtual camera's
  attitude error of a few degrees, zero-mean over the clip, averages out too);
- scale: over short windows of keyframes (about 1.5 s), the visual
  displacements times one scale must equal the IMU's double integral plus an
  unknown start velocity per window (the linear alignment of
  `initialization.align_visual_inertial`, with the rotations from the images
  and gravity known). One least-squares problem over all windows gives the
  scale and its standard error. A camera carried at a steady pace gives the
  accelerometer almost nothing to weigh (the MAX sample: fits from -1 to +8
  for window lengths of 3-6 keyframes); then the visual scale is kept and
  stats.json says `"metric_scale": false`, rather than inventing metres.

The result follows the session-frame convention (z up, origin and yaw at the
first keyframe's body frame) and is marked as such in its stats.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import numpy.typing as npt

from postproc.slam.estimator import SlamResult
from postproc.slam.initialization import preintegrate, session_from_body_rotation
from postproc.slam.types import FloatArray, ImuSamples
from shared.errors import StageError
from shared.geometry import make_pose


def mean_force_in_frame(
    stamps_ns: npt.NDArray[np.int64],
    frame_from_body: FloatArray,
    imu: ImuSamples,
    shift_ns: int,
) -> FloatArray:
    """Mean accelerometer reading (3,) rotated into the poses' frame, over their span.

    `stamps_ns` (N,) camera clock with `frame_from_body` (N, 4, 4); each IMU
    sample (IMU clock, t_imu = t_cam + shift) takes the attitude of the nearest
    earlier pose. StageError when no IMU sample falls in the span.
    """
    t = np.asarray(stamps_ns, dtype=np.int64) + shift_ns
    inside = (imu.stamps_ns >= t[0]) & (imu.stamps_ns <= t[-1])
    if not inside.any():
        raise StageError("no IMU samples within the visual trajectory's time span")
    nearest = np.clip(np.searchsorted(t, imu.stamps_ns[inside], side="right") - 1, 0, len(t) - 1)
    force: FloatArray = np.einsum(
        "nij,nj->ni", frame_from_body[nearest, :3, :3], imu.accel_m_s2[inside]
    ).mean(axis=0)
    return force


def imu_scale(
    stamps_ns: npt.NDArray[np.int64],
    session_from_body: FloatArray,
    imu: ImuSamples,
    *,
    shift_ns: int,
    gravity_m_s2: float,
    window: int = 4,
) -> tuple[float, float]:
    """Metric scale of a gravity-aligned, up-to-scale keyframe path, and its standard error.

    `session_from_body` (N, 4, 4): keyframe poses in a z-up frame, arbitrary
    scale; windows of `window` keyframes overlapping by half. Returns
    (scale, standard error of the scale from the least-squares residuals).
    StageError with fewer than `window` keyframes.
    """
    n = len(stamps_ns)
    if n < window:
        raise StageError(f"only {n} keyframes: too few to find the metric scale from the IMU")
    starts = list(range(0, n - window + 1, max(1, window // 2)))
    gravity = np.array([0.0, 0.0, -gravity_m_s2])
    rows: list[FloatArray] = []
    rhs: list[FloatArray] = []
    columns = 1 + 3 * len(starts)
    t = np.asarray(stamps_ns, dtype=np.int64) + shift_ns
    for w, i in enumerate(starts):
        later = list(range(i + 1, i + window))
        pre = preintegrate(imu, int(t[i]), [int(t[k]) for k in later], np.zeros(3))
        R_i = session_from_body[i, :3, :3]
        for k, p in zip(later, pre, strict=True):
            block = np.zeros((3, columns))
            block[:, 0] = session_from_body[k, :3, 3] - session_from_body[i, :3, 3]
            block[:, 1 + 3 * w : 4 + 3 * w] = -np.eye(3) * p.duration_s
            rows.append(block)
            rhs.append(0.5 * gravity * p.duration_s**2 + R_i @ p.delta_position_m)
    A = np.vstack(rows)
    b = np.concatenate(rhs)
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    scaled = A / norms
    x, *_ = np.linalg.lstsq(scaled, b, rcond=None)
    dof = max(len(b) - len(x), 1)
    sigma2 = float(np.sum((scaled @ x - b) ** 2)) / dof
    covariance = sigma2 * np.linalg.pinv(scaled.T @ scaled)
    return float(x[0] / norms[0]), float(np.sqrt(max(covariance[0, 0], 0.0)) / norms[0])


def gravity_and_scale(
    result: SlamResult,
    imu: ImuSamples,
    *,
    shift_ns: int,
    gravity_m_s2: float,
    max_relative_scale_error: float = 0.25,
) -> SlamResult:
    """The visual-only `result` in a gravity-aligned session frame, metric when it can be.

    The visual frame is the first keyframe's body frame, so the mean force
    expressed there gives `R_S_V` with the session yaw convention directly.
    When the IMU scale is not positive or its standard error exceeds
    `max_relative_scale_error` of it (a camera carried at a steady pace: no
    acceleration to weigh), the visual scale is kept (the first two-view
    baseline is 1) and stats say `"metric_scale": false`: not metres.
    """
    force = mean_force_in_frame(result.frame_stamps_ns, result.session_from_body, imu, shift_ns)
    R_S_V = session_from_body_rotation(force)
    turn = make_pose(R_S_V, np.zeros(3))
    keyframes = turn @ result.keyframe_session_from_body
    fitted, error = imu_scale(
        result.keyframe_stamps_ns, keyframes, imu, shift_ns=shift_ns, gravity_m_s2=gravity_m_s2
    )
    metric_scale = bool(
        np.isfinite(fitted) and fitted > 0 and error <= max_relative_scale_error * fitted
    )
    scale = fitted if metric_scale else 1.0

    def metric(poses: FloatArray) -> FloatArray:
        out = turn @ poses
        out[:, :3, 3] *= scale
        return out

    body = metric(result.session_from_body)
    kf_body = metric(result.keyframe_session_from_body)
    stats = dict(result.stats)
    stats.update(
        {
            "mode": "stabilised video: visual-only path, gravity from the IMU, "
            + ("metric scale from the IMU" if metric_scale else "scale arbitrary (not metres)"),
            "init": "two-view (visual only); gravity from the mean specific force"
            + ("; scale from windowed IMU alignment" if metric_scale else ""),
            "metric_scale": metric_scale,
            "imu_scale_fit": fitted,
            "imu_scale_standard_error": error,
        }
    )
    return dataclasses.replace(
        result,
        session_from_body=body,
        keyframe_session_from_body=kf_body,
        keyframe_session_from_cam=metric(result.keyframe_session_from_cam),
        landmarks_s=scale * (result.landmarks_s @ R_S_V.T),
        stats=stats,
    )
