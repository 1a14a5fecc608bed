"""Start-up of the visual-inertial estimate: gravity direction, stillness tests, alignment.

Pure math, no I/O. Divers move slowly and often hover, so the estimator does
not wait for a motion-rich start (which may never come): the first keyframe
is placed from gravity alone (roll and pitch from the mean specific force over
the first ~second, yaw zero), velocity gets a loose prior around zero, and
landmarks join the graph only once they are seen with enough parallax. While
the camera hardly moves, a zero-velocity constraint holds the state instead of
letting the IMU drift (no reset loop). `imu_stillness` tells from the IMU's
spread whether the body rests (then gravity, the gyro bias and zero velocity
come from the still IMU; see estimator).

Session frame S (documented in postproc/slam/stage.py): z up, origin at the
body (IMU) position of the first keyframe, yaw such that the first
keyframe's body x axis points along +x of S when projected on the horizontal.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from postproc.slam.types import FloatArray, ImuSamples
from shared.clock import ns_from_seconds, seconds_from_ns
from shared.errors import StageError
from shared.geometry import so3_exp


def session_from_body_rotation(accel_body_m_s2: FloatArray) -> FloatArray:
    """`R_S_B` (3, 3) of a body whose accelerometer reads `accel_body_m_s2` (3,) at rest.

    At rest the specific force points up, so it becomes +z of S. Yaw is zero:
    the body x axis projects onto +x of S (the body y axis when x is vertical).
    Raises StageError for a near-zero reading (no gravity seen).
    """
    a = np.asarray(accel_body_m_s2, dtype=np.float64)
    norm = float(np.linalg.norm(a))
    if not np.isfinite(norm) or norm < 1.0:
        raise StageError(
            f"cannot find gravity: mean specific force is {norm:.3f} m/s^2 (expected about 9.81)"
        )
    up = a / norm
    reference = np.array([1.0, 0.0, 0.0])
    if abs(float(up @ reference)) > 0.95:
        reference = np.array([0.0, 1.0, 0.0])
    x_s = reference - (reference @ up) * up
    x_s /= np.linalg.norm(x_s)
    y_s = np.cross(up, x_s)
    # Rows of R_S_B are the S axes written in B.
    return np.stack([x_s, y_s, up])


def mean_specific_force(imu: ImuSamples, start_ns: int, window_s: float) -> FloatArray:
    """Mean accelerometer reading (3,) over the window after `start_ns`, in the body frame
    at `start_ns`.

    Each sample is rotated into the body frame at `start_ns` with the
    integrated gyro first, so a diver who pitches or rolls while the average
    is taken does not tilt the gravity estimate (0.1 rad of pitch would put
    about 1 m/s^2 of gravity into the horizontal). The window is shortened to
    the IMU data available. Raises StageError when no IMU sample follows `start_ns`.
    """
    window_ns = ns_from_seconds(window_s)
    end_ns = min(start_ns + window_ns, int(imu.stamps_ns[-1])) if len(imu) else start_ns
    if len(imu) < 2 or start_ns < imu.stamps_ns[0] or end_ns <= start_ns:
        raise StageError(
            f"no IMU samples in the {window_s:.2f} s after the first keyframe "
            f"({start_ns} ns); check the camera-IMU time offset"
        )
    from postproc.slam.backend import imu_intervals

    accel, gyro, dt = imu_intervals(imu, start_ns, end_ns)
    # The orientation at the start of each piece (the exponentials all at once; the
    # products in order, as before: a 10 s window is 2000 pieces at 200 Hz).
    steps = so3_exp(gyro * dt[:, None])
    rotations = np.empty_like(steps)
    R = np.eye(3)
    for i, step in enumerate(steps):
        rotations[i] = R
        R = R @ step
    total = np.einsum("nij,nj,n->i", rotations, accel, dt)
    result: FloatArray = total / dt.sum()
    return result


@dataclass
class ImuStillness:
    """What the IMU says about the body around a time: at rest or not, and what rest gives.

    still: the gyro and accelerometer hardly vary over the window (see `imu_stillness`).
    duration_s: IMU time the statistics cover (s).
    gyro_mean_rad_s (3,): mean angular rate; at rest, the gyro bias (plus Earth's
        7.3e-5 rad/s, which is below every consumer gyro's bias uncertainty).
    gyro_std_rad_s / accel_std_m_s2: largest per-axis standard deviation of the samples.
    accel_mean_m_s2 (3,): mean specific force (at rest: gravity, up, in the body frame).
    gyro_bias_sigma_rad_s: uncertainty of `gyro_mean_rad_s` as a bias: the standard
        error of the mean, floored (a hand-held "rest" still turns a little).
    accel_noise_density / gyro_noise_density: upper bounds on the white noise the
        spread shows (per-sample deviation times the square root of the sample
        interval; m/s^2/sqrt(Hz), rad/s/sqrt(Hz)): tremor adds to them. NaN when not
        still. Evidence beside the noise model, which they do not change.
    """

    still: bool
    duration_s: float
    gyro_mean_rad_s: FloatArray
    gyro_std_rad_s: float
    accel_mean_m_s2: FloatArray
    accel_std_m_s2: float
    gyro_bias_sigma_rad_s: float
    accel_noise_density: float = float("nan")
    gyro_noise_density: float = float("nan")


def imu_stillness(
    imu: ImuSamples,
    start_ns: int,
    end_ns: int,
    *,
    max_gyro_std_rad_s: float = 0.02,
    max_accel_std_m_s2: float = 0.15,
    max_gyro_rad_s: float = 0.1,
    min_duration_s: float = 0.5,
    gyro_bias_floor_rad_s: float = 1.0e-3,
    chunk_s: float = 0.25,
) -> ImuStillness:
    """Whether the body rests over [start_ns, end_ns] (IMU clock, cut to the IMU data).

    Rest is judged from the samples' spread, not from a noise model (Kalibr files
    often carry inflated or optimistic densities): a body at rest, even held in a
    hand, shows gyro deviations of a few mrad/s and accelerometer deviations of a few
    cm/s^2; walking, turning or swimming shows 0.1-1 rad/s and 0.3-3 m/s^2. The
    mean rate must also be small (a steady turn has a small spread too). Fewer than
    `min_duration_s` of IMU data is never called still. The spreads are taken over
    `chunk_s` pieces and the largest counts, so that a window whose last quarter
    second already moves is not diluted into "still" by the rest before it.
    """
    stamps = imu.stamps_ns
    inside = (stamps >= start_ns) & (stamps <= end_ns)
    n = int(inside.sum())
    if n < 3:
        return ImuStillness(False, 0.0, np.zeros(3), np.inf, np.zeros(3), np.inf, np.inf)
    times = stamps[inside]
    duration_s = seconds_from_ns(int(times[-1] - times[0]))
    gyro = imu.gyro_rad_s[inside]
    accel = imu.accel_m_s2[inside]
    gyro_mean = gyro.mean(axis=0)
    pieces = max(int(duration_s / chunk_s), 1)
    edges = np.linspace(0, n, pieces + 1).astype(int)
    gyro_std = max(float(gyro[a:b].std(axis=0).max()) for a, b in itertools.pairwise(edges))
    accel_std = max(float(accel[a:b].std(axis=0).max()) for a, b in itertools.pairwise(edges))
    still = (
        duration_s >= min_duration_s
        and gyro_std <= max_gyro_std_rad_s
        and accel_std <= max_accel_std_m_s2
        and float(np.linalg.norm(gyro_mean)) <= max_gyro_rad_s
    )
    sigma = max(3.0 * gyro_std / np.sqrt(n), gyro_bias_floor_rad_s)
    root_dt = float(np.sqrt(duration_s / (n - 1)))
    nan = float("nan")
    return ImuStillness(
        still=bool(still),
        duration_s=duration_s,
        gyro_mean_rad_s=gyro_mean,
        gyro_std_rad_s=gyro_std,
        accel_mean_m_s2=accel.mean(axis=0),
        accel_std_m_s2=accel_std,
        gyro_bias_sigma_rad_s=sigma,
        accel_noise_density=accel_std * root_dt if still else nan,
        gyro_noise_density=gyro_std * root_dt if still else nan,
    )


def is_still(
    *,
    derotated_flow_px: float,
    max_flow_px: float,
) -> bool:
    """Whether the camera hardly translated between two keyframes.

    `derotated_flow_px` is the median image motion of the shared features once
    the gyro-predicted rotation is taken out: a hovering diver who looks
    around translates no more than one who keeps still, and both get a
    zero-velocity update.
    """
    return bool(derotated_flow_px < max_flow_px)


# ------------------------------------------------------------------ visual-inertial alignment


@dataclass
class Preintegrated:
    """IMU motion from a start time, bias-free except for the gyro bias given.

    delta_rotation (3, 3): R_B0_Bt; delta_velocity_m_s / delta_position_m (3,) in B0
    (gravity not included); position_d_accel_bias (3, 3): d(delta_position)/d(accel bias).
    """

    duration_s: float
    delta_rotation: FloatArray
    delta_velocity_m_s: FloatArray
    delta_position_m: FloatArray
    position_d_accel_bias: FloatArray


def preintegrate(
    imu: ImuSamples, start_ns: int, end_ns: list[int], gyro_bias_rad_s: FloatArray
) -> list[Preintegrated]:
    """Preintegrate from `start_ns` to each of `end_ns` (sorted, IMU clock), numpy only.

    Euler integration on the midpoint-interpolated readings of
    `backend.imu_intervals`, plus the first-order Jacobian of the position
    with respect to a constant accelerometer bias (Forster et al. 2017, eq. 44
    without the rotation terms), which the linear alignment solves for.
    """
    from postproc.slam.backend import imu_intervals

    out: list[Preintegrated] = []
    R = np.eye(3)
    v = np.zeros(3)
    p = np.zeros(3)
    dv_dba = np.zeros((3, 3))
    dp_dba = np.zeros((3, 3))
    t = int(start_ns)
    total = 0.0
    for stop in end_ns:
        if stop > t:
            accel, gyro, dt = imu_intervals(imu, t, stop)
            for a, w, d in zip(accel, gyro, dt, strict=True):
                p = p + v * d + 0.5 * (R @ a) * d * d
                dp_dba = dp_dba + dv_dba * d - 0.5 * R * d * d
                v = v + (R @ a) * d
                dv_dba = dv_dba - R * d
                R = R @ so3_exp((w - gyro_bias_rad_s) * d)
                total += d
            t = stop
        out.append(Preintegrated(total, R.copy(), v.copy(), p.copy(), dp_dba.copy()))
    return out


def gyro_rotation(
    imu: ImuSamples, start_ns: int, end_ns: int, gyro_bias_rad_s: FloatArray
) -> FloatArray:
    """`R_B0_Bt` (3, 3): the gyro's rotation over [start_ns, end_ns] (IMU clock), bias removed.

    The rotation part of `preintegrate` (the same pieces and the same order of products),
    with the exponentials of all pieces computed at once: it runs for every image.
    """
    from postproc.slam.backend import imu_intervals

    R = np.eye(3)
    if end_ns <= start_ns:
        return R
    _, gyro, dt = imu_intervals(imu, int(start_ns), int(end_ns))
    for step in so3_exp((gyro - gyro_bias_rad_s) * dt[:, None]):
        R = R @ step
    return R


def translation_direction(
    rays_a: FloatArray,
    rays_b: FloatArray,
    *,
    rng: np.random.Generator,
    iterations: int = 200,
    threshold_rad: float = 0.002,
) -> tuple[FloatArray, int]:
    """Unit baseline direction from camera a to b, given matching rays rotated into one frame.

    With rotations known (gyro), the coplanarity constraint
    (c_b - c_a) . (f_a x f_b) = 0 is linear in the baseline; two
    correspondences fix it (the cross product of their normals), RANSAC picks
    the consensus and a least-squares fit refines it. The sign makes most
    points lie in front of both cameras. Returns (direction (3,), inliers).
    """
    f_a = rays_a / np.linalg.norm(rays_a, axis=1, keepdims=True)
    f_b = rays_b / np.linalg.norm(rays_b, axis=1, keepdims=True)
    normals = np.cross(f_a, f_b)
    n = len(normals)
    if n < 8:
        return np.full(3, np.nan), 0
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        i, j = rng.choice(n, size=2, replace=False)
        d = np.cross(normals[i], normals[j])
        norm = np.linalg.norm(d)
        if norm < 1e-12:
            continue
        inliers = np.abs(normals @ (d / norm)) < threshold_rad
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < 8:
        return np.full(3, np.nan), int(best.sum())
    _, _, vt = np.linalg.svd(normals[best])
    d = vt[-1]
    # Depth along f_a of the triangulated point: positive in front of camera a.
    # From c_a + s f_a = c_b + u f_b with c_b - c_a = d:
    # s = ((d x f_b) . (f_a x f_b)) / |f_a x f_b|^2
    nb = normals[best]
    s = np.einsum("ij,ij->i", np.cross(d, f_b[best]), nb) / np.maximum(
        np.einsum("ij,ij->i", nb, nb), 1e-18
    )
    if np.median(s) < 0:
        d = -d
    return d, int(best.sum())


@dataclass
class AlignmentResult:
    """Outcome of the visual-inertial alignment of the first keyframes.

    velocity_m_s: velocity of the first keyframe in S; accel_bias_m_s2: in B;
    scales: distance (m) of each later camera centre from the first;
    condition: ratio of the smallest to the largest singular value (0 = no scale info).
    """

    velocity_m_s: FloatArray
    accel_bias_m_s2: FloatArray
    scales_m: FloatArray
    condition: float


def align_visual_inertial(
    *,
    session_from_body0: FloatArray,
    imu_from_cam: FloatArray,
    directions_s: list[FloatArray],
    preintegrated: list[Preintegrated],
    gravity_m_s2: float,
) -> AlignmentResult:
    """Velocity, accelerometer bias and baseline lengths that fit IMU and image directions.

    For each later keyframe k (camera centre c_k, body position p_k, p_0 = 0):
      lambda_k d_k = c_k - c_0,   c_k = p_k + R_S_Bk t_BC,
      p_k = v_0 t_k + g t_k^2 / 2 + R_S_B0 (dp_k + J_k b_a),
    linear in (lambda_1..N, v_0, b_a): 3N equations, N + 6 unknowns (N >= 3).
    Scale needs acceleration: at constant velocity the condition number says so.
    """
    R0 = session_from_body0[:3, :3]
    t_bc = imu_from_cam[:3, 3]
    gravity = np.array([0.0, 0.0, -gravity_m_s2])
    n = len(directions_s)
    A = np.zeros((3 * n, n + 6))
    b = np.zeros(3 * n)
    for k, (d, pre) in enumerate(zip(directions_s, preintegrated, strict=True)):
        rows = slice(3 * k, 3 * k + 3)
        Rk = R0 @ pre.delta_rotation
        A[rows, k] = d
        A[rows, n : n + 3] = -np.eye(3) * pre.duration_s
        A[rows, n + 3 :] = -R0 @ pre.position_d_accel_bias
        b[rows] = 0.5 * gravity * pre.duration_s**2 + R0 @ pre.delta_position_m + (Rk - R0) @ t_bc
    # Column scaling so the condition number compares like with like.
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    x, *_ = np.linalg.lstsq(A / scale, b, rcond=None)
    singular = np.linalg.svd(A / scale, compute_uv=False)
    x = x / scale
    return AlignmentResult(
        velocity_m_s=x[n : n + 3],
        accel_bias_m_s2=x[n + 3 :],
        scales_m=x[:n],
        condition=float(singular[-1] / singular[0]) if singular[0] > 0 else 0.0,
    )
