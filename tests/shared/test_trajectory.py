"""Trajectory container and the absolute trajectory error."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shared.geometry import invert_pose, make_pose, pose_difference, so3_exp
from shared.trajectory import AteResult, Trajectory, associate, ate

T0_NS = 1_700_000_000_000_000_000


def helix(n: int = 50, *, dt_ns: int = 100_000_000, seed: int = 0) -> Trajectory:
    """A body moving along a helix, turning as it goes, with small random wobble."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    positions = np.c_[np.cos(0.2 * k), np.sin(0.2 * k), 0.05 * k]
    rotvecs = np.c_[0.05 * rng.normal(size=n), 0.05 * rng.normal(size=n), 0.2 * k]
    return Trajectory(T0_NS + k.astype(np.int64) * dt_ns, make_pose(so3_exp(rotvecs), positions))


def test_properties() -> None:
    traj = helix(11)
    assert len(traj) == 11
    assert traj.positions.shape == (11, 3)
    assert traj.rotations.shape == (11, 3, 3)
    assert traj.duration_s == pytest.approx(1.0)
    steps = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    assert traj.path_length_m() == pytest.approx(float(steps.sum()))
    assert traj.path_length_m() > 0.0
    single = Trajectory(traj.stamps_ns[:1], traj.poses[:1])
    assert single.duration_s == 0.0
    assert single.path_length_m() == 0.0
    assert traj.stamps_ns.dtype == np.int64


def test_validation() -> None:
    traj = helix(5)
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(traj.stamps_ns[[0, 2, 1, 3, 4]], traj.poses)
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(traj.stamps_ns[[0, 1, 1, 3, 4]], traj.poses)
    with pytest.raises(ValueError, match="shape"):
        Trajectory(traj.stamps_ns[:4], traj.poses)
    with pytest.raises(ValueError, match="1-D"):
        Trajectory(traj.stamps_ns[None, :], traj.poses)
    with pytest.raises(ValueError, match="integer nanoseconds"):
        Trajectory(traj.stamps_ns.astype(np.float64), traj.poses)
    bad = traj.poses.copy()
    bad[2, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        Trajectory(traj.stamps_ns, bad)
    bad = traj.poses.copy()
    bad[1, 3, 0] = 0.5
    with pytest.raises(ValueError, match="homogeneous"):
        Trajectory(traj.stamps_ns, bad)


def test_slice_time_inclusive() -> None:
    traj = helix(10)
    part = traj.slice_time(int(traj.stamps_ns[2]), int(traj.stamps_ns[5]))
    np.testing.assert_array_equal(part.stamps_ns, traj.stamps_ns[2:6])
    np.testing.assert_array_equal(part.poses, traj.poses[2:6])
    assert len(traj.slice_time(0, T0_NS - 1)) == 0


def test_interpolate_clips_to_span() -> None:
    traj = helix(10)
    query = np.array([T0_NS - 5, T0_NS, T0_NS + 50_000_000, int(traj.stamps_ns[-1]), 2 * T0_NS])
    out = traj.interpolate(query)
    np.testing.assert_array_equal(out.stamps_ns, query[1:4])
    np.testing.assert_array_equal(out.poses[0], traj.poses[0])
    np.testing.assert_array_equal(out.poses[2], traj.poses[-1])
    np.testing.assert_allclose(
        out.positions[1], 0.5 * (traj.positions[0] + traj.positions[1]), atol=1e-12
    )
    with pytest.raises(ValueError, match="empty trajectory"):
        Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4))).interpolate(query)
    with pytest.raises(ValueError, match="integer ns"):
        traj.interpolate(query.astype(float))


def test_transformed_and_right_multiplied() -> None:
    traj = helix(8)
    W_from_S = make_pose(so3_exp([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    B_from_C = make_pose(so3_exp([-0.5, 0.1, 0.0]), [0.02, 0.0, 0.05])
    in_w = traj.transformed(W_from_S)
    cams = traj.right_multiplied(B_from_C)
    for k in range(len(traj)):
        np.testing.assert_allclose(in_w.poses[k], W_from_S @ traj.poses[k], atol=1e-15)
        np.testing.assert_allclose(cams.poses[k], traj.poses[k] @ B_from_C, atol=1e-15)
    np.testing.assert_array_equal(in_w.stamps_ns, traj.stamps_ns)
    # Going back recovers the input.
    back = cams.right_multiplied(invert_pose(B_from_C)).transformed(invert_pose(np.eye(4)))
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-12)
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        traj.transformed(np.eye(3))
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        traj.right_multiplied(np.eye(3))


def test_associate_nearest_unique() -> None:
    a = np.array([0, 10, 11, 30, 100], dtype=np.int64)
    b = np.array([1, 12, 29, 60], dtype=np.int64)
    i, j = associate(a, b, max_dt_ns=5)
    # 10 and 11 both want b=12; 11 is closer. 100 has nothing within 5 ns.
    np.testing.assert_array_equal(i, [0, 2, 3])
    np.testing.assert_array_equal(j, [0, 1, 2])
    i, j = associate(a, np.zeros(0, np.int64), max_dt_ns=5)
    assert i.size == 0
    assert j.size == 0


def test_ate_zero_for_transformed_copy() -> None:
    reference = helix(60)
    T = make_pose(so3_exp([0.3, -1.0, 2.0]), [10.0, -4.0, 2.0])
    estimate = reference.transformed(T)
    result = ate(estimate, reference, align="se3")
    assert isinstance(result, AteResult)
    assert result.matched == 60
    assert result.rmse_m < 1e-9
    assert result.scale == 1.0
    np.testing.assert_allclose(result.alignment, invert_pose(T), atol=1e-9)
    np.testing.assert_array_equal(result.stamps_ns, reference.stamps_ns)
    unaligned = ate(estimate, reference, align="none")
    assert unaligned.rmse_m > 1.0
    np.testing.assert_array_equal(unaligned.alignment, np.eye(4))


def test_ate_sim3_recovers_scale() -> None:
    reference = helix(40)
    T = make_pose(so3_exp([0.0, 0.4, -0.2]), [1.0, 1.0, 1.0])
    scaled = Trajectory(reference.stamps_ns, reference.poses.copy())
    scaled.poses[:, :3, 3] *= 0.25  # monocular scale
    estimate = scaled.transformed(T)
    sim3 = ate(estimate, reference, align="sim3")
    assert sim3.rmse_m < 1e-9
    assert sim3.scale == pytest.approx(4.0, rel=1e-9)
    se3 = ate(estimate, reference, align="se3")
    assert se3.rmse_m > 0.1


def test_ate_known_noise_and_time_offset() -> None:
    reference = helix(200, dt_ns=50_000_000)
    rng = np.random.default_rng(3)
    noise = rng.normal(scale=0.01, size=(200, 3))
    poses = reference.poses.copy()
    poses[:, :3, 3] += noise
    # Estimate stamps 3 ms off: still associated with max_dt 10 ms, not with 2 ms.
    estimate = Trajectory(reference.stamps_ns + 3_000_000, poses)
    result = ate(estimate, reference, align="none")
    assert result.matched == 200
    assert result.rmse_m == pytest.approx(float(np.sqrt(np.mean(np.sum(noise**2, axis=1)))))
    np.testing.assert_allclose(result.errors_m, np.linalg.norm(noise, axis=1))
    with pytest.raises(ValueError, match="only 0 pose"):
        ate(estimate, reference, max_dt_ns=2_000_000)


def test_ate_errors() -> None:
    reference = helix(10)
    with pytest.raises(ValueError, match="only 2 pose"):
        ate(Trajectory(reference.stamps_ns[:2], reference.poses[:2]), reference)
    with pytest.raises(ValueError, match="align must be"):
        ate(reference, reference, align="sim2")  # type: ignore[arg-type]


def test_ate_agrees_with_pose_difference_without_alignment() -> None:
    reference = helix(20)
    perturb = make_pose(Rotation.from_euler("z", 0.1).as_matrix(), [0.0, 0.0, 0.2])
    estimate = reference.right_multiplied(perturb)
    result = ate(estimate, reference, align="none")
    for k in range(len(reference)):
        _, trans = pose_difference(estimate.poses[k], reference.poses[k])
        assert result.errors_m[k] == pytest.approx(trans)
