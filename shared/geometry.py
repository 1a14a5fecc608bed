"""Rotations and rigid/similarity transforms, as plain numpy arrays.

Conventions (see docs/conventions.md): a rotation is a 3x3 matrix, a pose is a
4x4 homogeneous matrix, and `T_A_B` (named `a_from_b` in code) maps points of
frame B into frame A: `p_A = T_A_B @ p_B`. Lengths are metres, angles radians,
time stamps int64 nanoseconds. Quaternions appear only at file boundaries and
always carry their component order in the function name (`wxyz` or `xyzw`).

Pure math: no I/O, no logging.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# Below this angle (rad) the closed forms of exp/log lose precision to
# cancellation; their Taylor series are used instead.
_SMALL_ANGLE_RAD = 1e-6


def _as_float(a: npt.ArrayLike) -> FloatArray:
    return np.asarray(a, dtype=np.float64)


def _check_shape(name: str, a: FloatArray, tail: tuple[int, ...]) -> None:
    if a.ndim < len(tail) or a.shape[a.ndim - len(tail) :] != tail:
        expected = "(..., " + ", ".join(str(d) for d in tail) + ")"
        raise ValueError(f"{name}: expected shape {expected}, got {a.shape}")


def skew(v: npt.ArrayLike) -> FloatArray:
    """Cross-product matrix `[v]x` of a 3-vector (or of a batch `(..., 3)`): `[v]x @ w = v x w`."""
    v = _as_float(v)
    _check_shape("skew", v, (3,))
    out = np.zeros((*v.shape[:-1], 3, 3), dtype=np.float64)
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def so3_exp(rotvec: npt.ArrayLike) -> FloatArray:
    """Rotation matrix of a rotation vector (axis times angle in rad); batches `(..., 3)` work too.

    Rodrigues' formula, with Taylor series of the coefficients for tiny angles.
    """
    w = _as_float(rotvec)
    _check_shape("so3_exp", w, (3,))
    theta2 = np.sum(w * w, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, theta)
    # A = sin(t)/t, B = (1 - cos(t))/t^2
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    k = skew(w)
    eye = np.broadcast_to(np.eye(3), k.shape)
    result: FloatArray = eye + a[..., None, None] * k + b[..., None, None] * (k @ k)
    return result


def so3_log(R: npt.ArrayLike) -> FloatArray:
    """Rotation vector (rad, angle in [0, pi]) of a rotation matrix; batches `(..., 3, 3)` too.

    Goes through the unit quaternion (Shepperd's method), which stays accurate
    both near the identity and near a half turn, where arccos of the trace and
    the antisymmetric part each lose precision.
    """
    q = quat_wxyz_from_matrix(R)
    w = q[..., 0]
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1)
    small = n < 0.5 * _SMALL_ANGLE_RAD
    # angle = 2 atan2(|v|, w); rotvec = angle * v / |v|. For tiny |v| (w ~ 1),
    # 2 atan2(n, w) / n = (2 / w) (1 - n^2 / (3 w^2) + ...).
    safe_n = np.where(small, 1.0, n)
    factor = np.where(
        small,
        2.0 / w * (1.0 - (n * n) / (3.0 * w * w)),
        2.0 * np.arctan2(n, w) / safe_n,
    )
    result: FloatArray = factor[..., None] * v
    return result


def rotation_angle_rad(R: npt.ArrayLike) -> float:
    """Angle in rad, in [0, pi], of a single rotation matrix (accurate near 0 and near pi)."""
    R = _as_float(R)
    if R.shape != (3, 3):
        raise ValueError(f"rotation_angle_rad: expected shape (3, 3), got {R.shape}")
    sin_part = 0.5 * np.linalg.norm(
        np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    )
    cos_part = 0.5 * (np.trace(R) - 1.0)
    return float(np.arctan2(sin_part, cos_part))


def make_pose(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> FloatArray:
    """4x4 pose from a rotation (3, 3) and a translation (3,) in metres; batches broadcast."""
    R = _as_float(rotation)
    t = _as_float(translation)
    _check_shape("make_pose rotation", R, (3, 3))
    _check_shape("make_pose translation", t, (3,))
    lead = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros((*lead, 4, 4), dtype=np.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_pose(T: npt.ArrayLike) -> FloatArray:
    """Inverse of rigid poses `(..., 4, 4)`: `T_B_A` from `T_A_B` (uses R^T, no general inverse)."""
    T = _as_float(T)
    _check_shape("invert_pose", T, (4, 4))
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    t = T[..., :3, 3]
    return make_pose(R_t, -np.einsum("...ij,...j->...i", R_t, t))


def look_at(
    eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """`T_W_C` of an OpenCV camera (x right, y down, z forward) at `eye` looking at `target`.

    eye, target: (3,) or (..., 3) points in W (metres; batches broadcast); up: the
    direction the top of the image faces (camera x = z cross up, so camera y points
    away from `up`), W's z by default. Where `up` is along the line of sight, x = z
    cross (1, 0, 0). Returns (4, 4) or (..., 4, 4).
    """
    eye_w = _as_float(eye)
    z = _as_float(target) - eye_w
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, _as_float(up))
    length = np.linalg.norm(x, axis=-1, keepdims=True)
    along = length < 1e-9
    if np.any(along):
        x = np.where(along, np.cross(z, np.array([1.0, 0.0, 0.0])), x)
        length = np.linalg.norm(x, axis=-1, keepdims=True)
    x = x / length
    y = np.cross(z, x)
    return make_pose(np.stack((x, y, z), axis=-1), np.broadcast_to(eye_w, z.shape))


def transform_points(T: npt.ArrayLike, points: npt.ArrayLike) -> FloatArray:
    """Apply one pose `T_A_B` (4, 4) to points `p_B` (N, 3); returns `p_A` (N, 3)."""
    T = _as_float(T)
    p = _as_float(points)
    if T.shape != (4, 4):
        raise ValueError(f"transform_points: expected a (4, 4) pose, got {T.shape}")
    _check_shape("transform_points points", p, (3,))
    result: FloatArray = p @ T[:3, :3].T + T[:3, 3]
    return result


# --- quaternions (file boundaries only) ---------------------------------------------------


def _canonical_quat_wxyz(q: FloatArray) -> FloatArray:
    """Normalise and choose the sign with w >= 0 (for w == 0: first non-zero component > 0)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    # Sign decided by the first component that is clearly non-zero, in w, x, y, z order.
    significant = np.abs(q) > 1e-12
    first = np.argmax(significant, axis=-1)
    lead = np.take_along_axis(q, first[..., None], axis=-1)[..., 0]
    sign = np.where(lead < 0.0, -1.0, 1.0)
    result: FloatArray = q * sign[..., None]
    # A numerically zero w may come out as -1e-17; make "w >= 0" hold exactly.
    w = result[..., 0]
    result[..., 0] = np.where(np.abs(w) <= 1e-12, np.abs(w), w)
    return result


def quat_wxyz_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """Unit quaternions (w, x, y, z), w >= 0, of rotation matrices `(..., 3, 3)` -> `(..., 4)`.

    Shepperd's method: of the four algebraically equivalent formulas, use the
    one whose pivot (4 w^2, 4 x^2, 4 y^2 or 4 z^2) is largest, so the division
    is never by a small number.
    """
    R = _as_float(R)
    _check_shape("quat_wxyz_from_matrix", R, (3, 3))
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = r00 + r11 + r22
    # Rows: candidate quaternions scaled by 4*(pivot component), pivot w, x, y, z.
    c_w = np.stack(
        [
            1.0 + trace,
            R[..., 2, 1] - R[..., 1, 2],
            R[..., 0, 2] - R[..., 2, 0],
            R[..., 1, 0] - R[..., 0, 1],
        ],
        axis=-1,
    )
    c_x = np.stack(
        [
            R[..., 2, 1] - R[..., 1, 2],
            1.0 + r00 - r11 - r22,
            R[..., 0, 1] + R[..., 1, 0],
            R[..., 0, 2] + R[..., 2, 0],
        ],
        axis=-1,
    )
    c_y = np.stack(
        [
            R[..., 0, 2] - R[..., 2, 0],
            R[..., 0, 1] + R[..., 1, 0],
            1.0 - r00 + r11 - r22,
            R[..., 1, 2] + R[..., 2, 1],
        ],
        axis=-1,
    )
    c_z = np.stack(
        [
            R[..., 1, 0] - R[..., 0, 1],
            R[..., 0, 2] + R[..., 2, 0],
            R[..., 1, 2] + R[..., 2, 1],
            1.0 - r00 - r11 + r22,
        ],
        axis=-1,
    )
    candidates = np.stack([c_w, c_x, c_y, c_z], axis=-2)  # (..., 4, 4)
    pivots = np.stack(
        [1.0 + trace, 1.0 + r00 - r11 - r22, 1.0 - r00 + r11 - r22, 1.0 - r00 - r11 + r22], axis=-1
    )
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    return _canonical_quat_wxyz(q)


def matrix_from_quat_wxyz(quat_wxyz: npt.ArrayLike) -> FloatArray:
    """Rotation matrices `(..., 3, 3)` of quaternions (w, x, y, z) `(..., 4)`; normalises first.

    Raises ValueError for a (near) zero or non-finite quaternion.
    """
    q = _as_float(quat_wxyz)
    _check_shape("matrix_from_quat_wxyz", q, (4,))
    norm = np.linalg.norm(q, axis=-1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError("matrix_from_quat_wxyz: quaternion with zero or non-finite norm")
    q = q / norm[..., None]
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty((*q.shape[:-1], 3, 3), dtype=np.float64)
    R[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[..., 0, 1] = 2.0 * (x * y - w * z)
    R[..., 0, 2] = 2.0 * (x * z + w * y)
    R[..., 1, 0] = 2.0 * (x * y + w * z)
    R[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[..., 1, 2] = 2.0 * (y * z - w * x)
    R[..., 2, 0] = 2.0 * (x * z - w * y)
    R[..., 2, 1] = 2.0 * (y * z + w * x)
    R[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def quat_xyzw_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """Unit quaternions (x, y, z, w), w >= 0 (TUM, scipy order) of rotations `(..., 3, 3)`."""
    q = quat_wxyz_from_matrix(R)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def matrix_from_quat_xyzw(quat_xyzw: npt.ArrayLike) -> FloatArray:
    """Rotation matrices `(..., 3, 3)` of quaternions (x, y, z, w) `(..., 4)`; normalises first."""
    q = _as_float(quat_xyzw)
    _check_shape("matrix_from_quat_xyzw", q, (4,))
    return matrix_from_quat_wxyz(np.concatenate([q[..., 3:], q[..., :3]], axis=-1))


# --- interpolation ------------------------------------------------------------------------


def interpolate_poses(
    stamps_ns: npt.ArrayLike, poses: npt.ArrayLike, query_ns: npt.ArrayLike
) -> FloatArray:
    """Poses at `query_ns` (M,) from knots `stamps_ns` (N,) (int64 ns, strictly increasing).

    Rotation by slerp (geodesic on SO(3)) and translation linearly between the
    two surrounding knots. A query equal to a knot returns that knot exactly.
    Raises ValueError for a query outside [stamps_ns[0], stamps_ns[-1]]: callers
    clip first (see `Trajectory.interpolate`).
    """
    stamps = np.asarray(stamps_ns)
    query = np.asarray(query_ns)
    T = _as_float(poses)
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise ValueError(
            "interpolate_poses: stamps_ns must be a 1-D integer array, "
            f"got {stamps.dtype} {stamps.shape}"
        )
    if query.ndim != 1 or not np.issubdtype(query.dtype, np.integer):
        raise ValueError(
            "interpolate_poses: query_ns must be a 1-D integer array, "
            f"got {query.dtype} {query.shape}"
        )
    if T.shape != (stamps.shape[0], 4, 4):
        raise ValueError(
            f"interpolate_poses: poses must have shape ({stamps.shape[0]}, 4, 4), got {T.shape}"
        )
    if stamps.shape[0] == 0:
        raise ValueError("interpolate_poses: no knots")
    stamps = stamps.astype(np.int64)
    query = query.astype(np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise ValueError("interpolate_poses: stamps_ns must be strictly increasing")
    if query.size and (query.min() < stamps[0] or query.max() > stamps[-1]):
        raise ValueError(
            f"interpolate_poses: queries span [{query.min()}, {query.max()}] ns, outside the "
            f"knots [{stamps[0]}, {stamps[-1]}] ns (clip first)"
        )
    if stamps.shape[0] == 1:
        return np.repeat(T, query.shape[0], axis=0)
    i0 = np.clip(np.searchsorted(stamps, query, side="right") - 1, 0, stamps.shape[0] - 2)
    i1 = i0 + 1
    # Integer differences first: exact, then a small float ratio.
    alpha = (query - stamps[i0]).astype(np.float64) / (stamps[i1] - stamps[i0]).astype(np.float64)
    R0 = T[i0, :3, :3]
    R1 = T[i1, :3, :3]
    delta = so3_log(np.swapaxes(R0, -1, -2) @ R1)
    R = R0 @ so3_exp(alpha[:, None] * delta)
    t = (1.0 - alpha)[:, None] * T[i0, :3, 3] + alpha[:, None] * T[i1, :3, 3]
    out = make_pose(R, t)
    # Exact knots where a query hits one (slerp at alpha 0 is exact anyway; alpha 1 is not).
    hit = query == stamps[i1]
    out[hit] = T[i1[hit]]
    return out


# --- alignment ---------------------------------------------------------------------------


def umeyama(
    source: npt.ArrayLike, target: npt.ArrayLike, *, with_scale: bool
) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares similarity (or rigid) transform with `target ≈ scale * R @ source + t`.

    Umeyama 1991, "Least-squares estimation of transformation parameters
    between two point patterns": R from the SVD of the cross-covariance, with
    the sign of the last singular direction flipped when needed so R is a
    proper rotation (never a reflection). `source` and `target` are (N, 3)
    corresponding points (metres), N >= 3. Returns `(R (3, 3), t (3,), scale)`;
    scale is 1.0 when `with_scale` is false. Raises ValueError for mismatched
    shapes, fewer than 3 points, or (with scale) all source points identical.
    """
    src = _as_float(source)
    dst = _as_float(target)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"umeyama: expected two (N, 3) arrays, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs, got {n}")
    mu_src = src.mean(axis=0)
    mu_dst = dst.mean(axis=0)
    src_c = src - mu_src
    dst_c = dst - mu_dst
    cov = dst_c.T @ src_c / n  # Sigma_xy of the paper (target x source)
    U, d, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt
    if with_scale:
        var_src = float(np.sum(src_c * src_c) / n)
        if var_src <= 0.0:
            raise ValueError("umeyama: all source points coincide, scale is undefined")
        scale = float(np.dot(d, S) / var_src)
    else:
        scale = 1.0
    t = mu_dst - scale * R @ mu_src
    return R, t, scale


def umeyama_pose(source: npt.ArrayLike, target: npt.ArrayLike) -> FloatArray:
    """Rigid (SE(3)) least-squares pose `T_target_source` (4, 4) from point pairs (N, 3)."""
    R, t, _ = umeyama(source, target, with_scale=False)
    return make_pose(R, t)


# --- averaging ---------------------------------------------------------------------------


def _weights(n: int, weights: npt.ArrayLike | None) -> FloatArray:
    if weights is None:
        return np.full(n, 1.0 / max(n, 1))
    w = _as_float(weights)
    if w.shape != (n,):
        raise ValueError(f"weights: expected shape ({n},), got {w.shape}")
    if np.any(w < 0.0) or not np.all(np.isfinite(w)) or w.sum() <= 0.0:
        raise ValueError("weights: must be finite, non-negative, with a positive sum")
    normalised: FloatArray = w / w.sum()
    return normalised


def _check_rotations(name: str, R: FloatArray) -> None:
    if R.ndim != 3 or R.shape[1:] != (3, 3) or R.shape[0] == 0:
        raise ValueError(f"{name}: expected a non-empty (N, 3, 3) array, got {R.shape}")


def project_to_so3(M: npt.ArrayLike) -> FloatArray:
    """Closest rotation (Frobenius norm) to a 3x3 matrix, via SVD with a det = +1 correction."""
    M = _as_float(M)
    U, _, Vt = np.linalg.svd(M)
    S = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)) or 1.0)])
    result: FloatArray = U @ S @ Vt
    return result


def rotation_mean_chordal(
    rotations: npt.ArrayLike, weights: npt.ArrayLike | None = None
) -> FloatArray:
    """Chordal L2 mean of rotations (N, 3, 3): the rotation closest to their weighted sum.

    Weights (N,) are relative (normalised here); None means equal weights.
    """
    R = _as_float(rotations)
    _check_rotations("rotation_mean_chordal", R)
    w = _weights(R.shape[0], weights)
    return project_to_so3(np.einsum("n,nij->ij", w, R))


def rotation_mean_quaternion(
    rotations: npt.ArrayLike, weights: npt.ArrayLike | None = None
) -> FloatArray:
    """Quaternion mean of rotations (N, 3, 3) (Markley et al. 2007, "Averaging quaternions").

    The mean is the eigenvector of the largest eigenvalue of sum_i w_i q_i q_i^T,
    which is insensitive to the sign ambiguity of each q_i.
    """
    R = _as_float(rotations)
    _check_rotations("rotation_mean_quaternion", R)
    w = _weights(R.shape[0], weights)
    q = quat_wxyz_from_matrix(R)
    M = np.einsum("n,ni,nj->ij", w, q, q)
    _, vecs = np.linalg.eigh(M)
    return matrix_from_quat_wxyz(vecs[:, -1])


def pose_difference(T_a: npt.ArrayLike, T_b: npt.ArrayLike) -> tuple[float, float]:
    """Rotation error (rad, angle of R_a^T R_b) and translation error (m, |t_a - t_b|) of two poses.

    Both poses (4, 4) must be expressed in the same frame (`T_W_B` and
    `T_W_B'`); the translation error is the distance between the two origins.
    """
    A = _as_float(T_a)
    B = _as_float(T_b)
    if A.shape != (4, 4) or B.shape != (4, 4):
        raise ValueError(f"pose_difference: expected two (4, 4) poses, got {A.shape} and {B.shape}")
    rotation_error_rad = rotation_angle_rad(A[:3, :3].T @ B[:3, :3])
    translation_error_m = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    return rotation_error_rad, translation_error_m
