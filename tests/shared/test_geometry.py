"""Rotations, poses, quaternions, interpolation, Umeyama and rotation means."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from shared.geometry import (
    interpolate_poses,
    invert_pose,
    look_at,
    make_pose,
    matrix_from_quat_wxyz,
    matrix_from_quat_xyzw,
    pose_difference,
    project_to_so3,
    quat_wxyz_from_matrix,
    quat_xyzw_from_matrix,
    rotation_angle_rad,
    rotation_mean_chordal,
    rotation_mean_quaternion,
    skew,
    so3_exp,
    so3_log,
    transform_points,
    umeyama,
    umeyama_pose,
)

# Derandomized: the same examples every run (fixed seeds), still searching edge cases.
SETTINGS = settings(max_examples=80, deadline=None, derandomize=True)

finite = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)
vectors = st.tuples(finite, finite, finite).map(np.array)
translations = st.tuples(*[st.floats(-100.0, 100.0)] * 3).map(np.array)


@st.composite
def rotvecs(draw: st.DrawFn, max_angle: float = np.pi - 1e-9) -> np.ndarray:
    axis = np.array(draw(st.tuples(finite, finite, finite)))
    n = float(np.linalg.norm(axis))
    if n < 1e-3:
        axis, n = np.array([0.0, 0.0, 1.0]), 1.0
    angle = draw(
        st.one_of(
            st.floats(0.0, max_angle),
            st.floats(0.0, 1e-7),  # near identity
            st.floats(max(0.0, max_angle - 1e-6), max_angle),  # near a half turn
        )
    )
    rotvec: np.ndarray = axis / n * angle
    return rotvec


@st.composite
def rotations(draw: st.DrawFn) -> np.ndarray:
    return so3_exp(draw(rotvecs()))


@st.composite
def poses(draw: st.DrawFn) -> np.ndarray:
    return make_pose(draw(rotations()), draw(translations))


def is_rotation(R: np.ndarray, tol: float = 1e-12) -> bool:
    return bool(np.allclose(R.T @ R, np.eye(3), atol=tol) and np.isclose(np.linalg.det(R), 1.0))


# --- so(3) ----------------------------------------------------------------------------------


@SETTINGS
@given(vectors, vectors)
def test_skew_is_cross_product(v: np.ndarray, w: np.ndarray) -> None:
    np.testing.assert_allclose(skew(v) @ w, np.cross(v, w), atol=1e-15)
    np.testing.assert_array_equal(skew(v), -skew(v).T)


@SETTINGS
@given(rotvecs())
def test_exp_log_round_trip(w: np.ndarray) -> None:
    R = so3_exp(w)
    assert is_rotation(R)
    np.testing.assert_allclose(so3_log(R), w, atol=1e-9)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    assert rotation_angle_rad(R) == pytest.approx(np.linalg.norm(w), abs=1e-9)


@SETTINGS
@given(rotations())
def test_log_exp_round_trip(R: np.ndarray) -> None:
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-12)


def test_log_at_exact_half_turn_and_identity() -> None:
    for axis in np.eye(3):
        R = so3_exp(np.pi * axis)
        w = so3_log(R)
        assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-12)
        np.testing.assert_allclose(np.abs(w), np.pi * axis, atol=1e-12)
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))
    assert rotation_angle_rad(np.eye(3)) == 0.0
    tiny = np.array([1e-12, -2e-12, 3e-12])
    np.testing.assert_allclose(so3_log(so3_exp(tiny)), tiny, rtol=1e-6, atol=1e-20)


def test_exp_log_batch_matches_single() -> None:
    rng = np.random.default_rng(1)
    w = rng.normal(size=(5, 7, 3))
    R = so3_exp(w)
    assert R.shape == (5, 7, 3, 3)
    np.testing.assert_allclose(R[2, 3], so3_exp(w[2, 3]), atol=0)
    np.testing.assert_allclose(so3_log(R)[4, 1], so3_log(R[4, 1]), atol=0)


def test_shape_errors() -> None:
    with pytest.raises(ValueError, match="so3_exp"):
        so3_exp(np.zeros(4))
    with pytest.raises(ValueError, match=r"quat_wxyz_from_matrix"):
        so3_log(np.eye(4))
    with pytest.raises(ValueError, match="rotation_angle_rad"):
        rotation_angle_rad(np.eye(4))
    with pytest.raises(ValueError, match="transform_points"):
        transform_points(np.eye(3), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="pose_difference"):
        pose_difference(np.eye(4), np.eye(3))
    with pytest.raises(ValueError, match="invert_pose"):
        invert_pose(np.eye(3))


# --- poses ----------------------------------------------------------------------------------


@SETTINGS
@given(poses(), poses())
def test_compose_invert_identities(T_a_b: np.ndarray, T_b_c: np.ndarray) -> None:
    np.testing.assert_allclose(T_a_b @ invert_pose(T_a_b), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert_pose(invert_pose(T_a_b)), T_a_b, atol=1e-12)
    np.testing.assert_allclose(
        invert_pose(T_a_b @ T_b_c), invert_pose(T_b_c) @ invert_pose(T_a_b), atol=1e-10
    )
    points = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-4.0, 0.5, 2.0]])
    np.testing.assert_allclose(
        transform_points(T_a_b @ T_b_c, points),
        transform_points(T_a_b, transform_points(T_b_c, points)),
        atol=1e-10,
    )


def test_invert_pose_batch() -> None:
    rng = np.random.default_rng(2)
    T = make_pose(so3_exp(rng.normal(size=(4, 3))), rng.normal(size=(4, 3)))
    np.testing.assert_allclose(
        T @ invert_pose(T), np.broadcast_to(np.eye(4), (4, 4, 4)), atol=1e-12
    )


@SETTINGS
@given(poses(), poses())
def test_pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> None:
    rot, trans = pose_difference(T_a, T_b)
    expected_rot = Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).magnitude()
    assert rot == pytest.approx(expected_rot, abs=1e-7)
    assert trans == pytest.approx(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]), abs=1e-12)
    assert pose_difference(T_a, T_a) == pytest.approx((0.0, 0.0), abs=1e-7)


# --- quaternions ----------------------------------------------------------------------------


@SETTINGS
@given(rotations())
def test_quaternion_round_trips(R: np.ndarray) -> None:
    q_wxyz = quat_wxyz_from_matrix(R)
    q_xyzw = quat_xyzw_from_matrix(R)
    assert np.linalg.norm(q_wxyz) == pytest.approx(1.0, abs=1e-15)
    assert q_wxyz[0] >= 0.0
    np.testing.assert_array_equal(q_xyzw, np.r_[q_wxyz[1:], q_wxyz[0]])
    np.testing.assert_allclose(matrix_from_quat_wxyz(q_wxyz), R, atol=1e-14)
    np.testing.assert_allclose(matrix_from_quat_xyzw(q_xyzw), R, atol=1e-14)
    # Same convention as scipy (x, y, z, w), up to the sign of q.
    q_scipy = Rotation.from_matrix(R).as_quat()
    assert abs(np.dot(q_scipy, q_xyzw)) == pytest.approx(1.0, abs=1e-12)


@SETTINGS
@given(st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_quaternion_canonical_and_unnormalised(q: tuple[float, ...]) -> None:
    q_wxyz = np.array(q)
    R = matrix_from_quat_wxyz(q_wxyz)
    assert is_rotation(R, tol=1e-12)
    back = quat_wxyz_from_matrix(R)
    unit = q_wxyz / np.linalg.norm(q_wxyz)
    sign = np.sign(np.dot(back, unit))
    np.testing.assert_allclose(back, sign * unit, atol=1e-12)
    # Canonical sign: the first component that is not (numerically) zero is positive.
    lead = back[np.argmax(np.abs(back) > 1e-12)]
    assert lead > 0.0
    assert back[0] >= 0.0


def test_quaternion_known_values_and_batch() -> None:
    half_turn_z = np.diag([-1.0, -1.0, 1.0])
    np.testing.assert_allclose(quat_wxyz_from_matrix(half_turn_z), [0.0, 0.0, 0.0, 1.0])
    quarter_x = so3_exp([np.pi / 2, 0.0, 0.0])
    s = np.sqrt(0.5)
    np.testing.assert_allclose(quat_xyzw_from_matrix(quarter_x), [s, 0.0, 0.0, s], atol=1e-15)
    batch = so3_exp(np.random.default_rng(3).normal(size=(2, 5, 3)))
    q = quat_xyzw_from_matrix(batch)
    assert q.shape == (2, 5, 4)
    np.testing.assert_allclose(matrix_from_quat_xyzw(q), batch, atol=1e-14)


def test_zero_quaternion_rejected() -> None:
    with pytest.raises(ValueError, match="zero or non-finite"):
        matrix_from_quat_wxyz(np.zeros(4))
    with pytest.raises(ValueError, match="zero or non-finite"):
        matrix_from_quat_xyzw([np.nan, 0.0, 0.0, 1.0])


# --- interpolation --------------------------------------------------------------------------


def _random_knots(seed: int, n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1_000_000, 100_000_000, n))
    T = make_pose(so3_exp(rng.normal(scale=0.8, size=(n, 3))), rng.normal(size=(n, 3)))
    return stamps.astype(np.int64), T


@pytest.mark.parametrize("seed", range(5))
def test_interpolation_hits_knots_and_is_continuous(seed: int) -> None:
    stamps, T = _random_knots(seed)
    np.testing.assert_array_equal(interpolate_poses(stamps, T, stamps), T)
    # Just beside each knot the pose is just beside the knot's pose.
    for k in range(1, len(stamps) - 1):
        near = interpolate_poses(stamps, T, np.array([stamps[k] - 1, stamps[k] + 1]))
        for side in near:
            rot, trans = pose_difference(side, T[k])
            assert rot < 1e-6
            assert trans < 1e-6
    # Midpoint: rotation halfway along the geodesic, translation the average.
    mid = (stamps[:-1] + stamps[1:]) // 2
    alpha = (mid - stamps[:-1]) / (stamps[1:] - stamps[:-1])
    out = interpolate_poses(stamps, T, mid)
    for k in range(len(mid)):
        total = rotation_angle_rad(T[k, :3, :3].T @ T[k + 1, :3, :3])
        first = rotation_angle_rad(T[k, :3, :3].T @ out[k, :3, :3])
        assert first == pytest.approx(alpha[k] * total, abs=1e-9)
        np.testing.assert_allclose(
            out[k, :3, 3], (1 - alpha[k]) * T[k, :3, 3] + alpha[k] * T[k + 1, :3, 3], atol=1e-12
        )
        assert is_rotation(out[k, :3, :3])


def test_interpolation_matches_scipy_slerp() -> None:
    from scipy.spatial.transform import Slerp

    stamps, T = _random_knots(7)
    query = np.linspace(stamps[0], stamps[-1], 50).astype(np.int64)
    t = (stamps - stamps[0]).astype(float)
    expected = Slerp(t, Rotation.from_matrix(T[:, :3, :3]))((query - stamps[0]).astype(float))
    out = interpolate_poses(stamps, T, query)
    np.testing.assert_allclose(out[:, :3, :3], expected.as_matrix(), atol=1e-9)


def test_interpolation_errors() -> None:
    stamps, T = _random_knots(8)
    with pytest.raises(ValueError, match="outside the knots"):
        interpolate_poses(stamps, T, np.array([stamps[0] - 1]))
    with pytest.raises(ValueError, match="outside the knots"):
        interpolate_poses(stamps, T, np.array([stamps[-1] + 1]))
    with pytest.raises(ValueError, match="strictly increasing"):
        interpolate_poses(stamps[::-1].copy(), T, stamps[:1])
    with pytest.raises(ValueError, match="stamps_ns must be a 1-D integer"):
        interpolate_poses(stamps.astype(float), T, stamps)
    with pytest.raises(ValueError, match="query_ns must be a 1-D integer"):
        interpolate_poses(stamps, T, stamps.astype(float))
    with pytest.raises(ValueError, match="poses must have shape"):
        interpolate_poses(stamps, T[:-1], stamps)
    with pytest.raises(ValueError, match="no knots"):
        interpolate_poses(np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros(0, np.int64))
    one = interpolate_poses(stamps[:1], T[:1], np.array([stamps[0]] * 2))
    np.testing.assert_array_equal(one, T[[0, 0]])


# --- Umeyama --------------------------------------------------------------------------------


@SETTINGS
@given(rotations(), translations, st.floats(0.01, 100.0), st.integers(0, 2**32 - 1))
def test_umeyama_recovers_sim3(R: np.ndarray, t: np.ndarray, scale: float, seed: int) -> None:
    source = np.random.default_rng(seed).normal(scale=5.0, size=(20, 3))
    target = scale * source @ R.T + t
    R_est, t_est, s_est = umeyama(source, target, with_scale=True)
    assert is_rotation(R_est)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    assert s_est == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-7 * max(1.0, scale))


@SETTINGS
@given(poses(), st.integers(0, 2**32 - 1))
def test_umeyama_recovers_se3(T: np.ndarray, seed: int) -> None:
    source = np.random.default_rng(seed).normal(scale=5.0, size=(10, 3))
    target = transform_points(T, source)
    R_est, t_est, s_est = umeyama(source, target, with_scale=False)
    assert s_est == 1.0
    np.testing.assert_allclose(make_pose(R_est, t_est), T, atol=1e-9)
    np.testing.assert_allclose(umeyama_pose(source, target), T, atol=1e-9)


def test_umeyama_never_returns_a_reflection() -> None:
    rng = np.random.default_rng(4)
    source = rng.normal(size=(30, 3))
    mirrored = source * np.array([1.0, 1.0, -1.0])  # best orthogonal fit is a reflection
    R, _, _ = umeyama(source, mirrored, with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # Planar points: the reflection is as good as the rotation; still a rotation.
    flat = np.c_[rng.normal(size=(10, 2)), np.zeros(10)]
    R, _, _ = umeyama(flat, flat, with_scale=False)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)


def test_umeyama_errors() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)), with_scale=False)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        umeyama(np.zeros((4, 3)), np.zeros((5, 3)), with_scale=False)
    with pytest.raises(ValueError, match="coincide"):
        umeyama(np.ones((4, 3)), np.zeros((4, 3)), with_scale=True)


# --- rotation means -------------------------------------------------------------------------


@SETTINGS
@given(rotations(), st.lists(rotvecs(max_angle=0.5), min_size=1, max_size=5))
def test_rotation_means_recover_symmetric_perturbations(
    R: np.ndarray, deltas: list[np.ndarray]
) -> None:
    # Each perturbation together with its inverse: the mean is exactly R for both estimators.
    perturbed = np.array([R @ so3_exp(s * d) for d in deltas for s in (1.0, -1.0)])
    np.testing.assert_allclose(rotation_mean_chordal(perturbed), R, atol=1e-9)
    np.testing.assert_allclose(rotation_mean_quaternion(perturbed), R, atol=1e-9)


def test_rotation_mean_weights() -> None:
    rng = np.random.default_rng(5)
    Rs = so3_exp(rng.normal(size=(3, 3)))
    for mean in (rotation_mean_chordal, rotation_mean_quaternion):
        np.testing.assert_allclose(mean(Rs, np.array([0.0, 1.0, 0.0])), Rs[1], atol=1e-12)
        np.testing.assert_allclose(mean(Rs[:1]), Rs[0], atol=1e-12)
        with pytest.raises(ValueError, match="weights"):
            mean(Rs, np.array([1.0, -1.0, 1.0]))
        with pytest.raises(ValueError, match="weights"):
            mean(Rs, np.ones(2))
        with pytest.raises(ValueError, match=r"\(N, 3, 3\)"):
            mean(np.zeros((0, 3, 3)))


def test_rotation_means_agree_with_scipy() -> None:
    rng = np.random.default_rng(6)
    center = so3_exp(rng.normal(size=3))
    Rs = center @ so3_exp(rng.normal(scale=0.2, size=(50, 3)))
    w = rng.uniform(0.1, 1.0, size=50)
    expected = Rotation.from_matrix(Rs).mean(weights=w).as_matrix()  # Markley's method
    np.testing.assert_allclose(rotation_mean_quaternion(Rs, w), expected, atol=1e-10)
    # Chordal and quaternion means differ at second order in the spread only.
    assert rotation_angle_rad(rotation_mean_chordal(Rs, w).T @ expected) < 1e-2


def test_project_to_so3() -> None:
    R = so3_exp([0.3, -0.2, 1.0])
    noisy = R + 1e-3 * np.random.default_rng(7).normal(size=(3, 3))
    P = project_to_so3(noisy)
    assert is_rotation(P)
    assert rotation_angle_rad(P.T @ R) < 1e-2
    assert is_rotation(project_to_so3(-np.eye(3)))


def test_look_at_puts_the_target_on_the_optical_axis_with_the_image_top_up() -> None:
    eye = np.array([1.0, -2.0, -10.0])
    target = np.array([4.0, 2.0, -12.0])
    world_from_cam = look_at(eye, target)
    R = world_from_cam[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(world_from_cam[:3, 3], eye)
    in_cam = invert_pose(world_from_cam) @ np.r_[target, 1.0]
    np.testing.assert_allclose(in_cam[:2], 0.0, atol=1e-12)
    assert in_cam[2] == pytest.approx(np.linalg.norm(target - eye))
    # OpenCV axes: x horizontal (no roll about W's z), y (image down) points down in W.
    assert abs(R[2, 0]) < 1e-12
    assert R[2, 1] < 0.0
    # Another up: the image top faces it.
    sideways = look_at(eye, target, up=(0.0, 1.0, 0.0))[:3, :3]
    assert abs(sideways[:, 0] @ [0.0, 1.0, 0.0]) < 1e-12
    assert sideways[1, 1] < 0.0


def test_look_at_batches_and_looking_along_up() -> None:
    rng = np.random.default_rng(4)
    eyes, targets = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    batch = look_at(eyes, targets)
    assert batch.shape == (6, 4, 4)
    for i in range(6):
        np.testing.assert_array_equal(batch[i], look_at(eyes[i], targets[i]))
    # Straight down along -up: x falls back to z cross (1, 0, 0), still a rotation.
    down = look_at([0.0, 0.0, 0.0], [0.0, 0.0, -3.0])[:3, :3]
    np.testing.assert_allclose(down[:, 2], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(down.T @ down, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(down[:, 0], np.cross([0.0, 0.0, -1.0], [1.0, 0.0, 0.0]))
