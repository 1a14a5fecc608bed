"""The paper's method: Euler conventions, per-tag poses, one-sigma rejection, combination."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.merge.paper import (
    combine_candidates,
    euler_mean_pose,
    euler_rpy_from_matrix,
    matrix_from_euler_rpy,
    one_sigma_average,
    per_tag_target_pose,
)
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.aprilgrid_detection import GridObservation
from shared.geometry import invert_pose, look_at, make_pose, pose_difference, so3_exp
from sim.targets import default_camera


def test_euler_round_trip_and_convention():
    rpy = np.array([0.3, -0.4, 2.0])
    R = matrix_from_euler_rpy(rpy)
    np.testing.assert_allclose(euler_rpy_from_matrix(R), rpy, atol=1e-12)
    # R = Rz(yaw) Ry(pitch) Rx(roll): a pure yaw turns x into y.
    np.testing.assert_allclose(
        matrix_from_euler_rpy([0, 0, np.pi / 2]) @ [1, 0, 0], [0, 1, 0], atol=1e-12
    )


def test_euler_mean_fails_across_the_yaw_wrap_where_ours_does_not():
    # Two yaws of +-179 deg: the paper's Euler mean gives ~0, the truth is 180.
    a = make_pose(matrix_from_euler_rpy([0, 0, np.deg2rad(179)]), [0, 0, 0])
    b = make_pose(matrix_from_euler_rpy([0, 0, np.deg2rad(-179)]), [0, 0, 0])
    mean = euler_mean_pose(np.array([a, b]))
    assert abs(euler_rpy_from_matrix(mean[:3, :3])[2]) < 1e-9


def test_one_sigma_rejection_drops_good_data_too():
    rng = np.random.default_rng(2)
    truth = make_pose(so3_exp([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    poses = np.array(
        [
            make_pose(
                so3_exp(rng.normal(0, 0.005, 3)) @ truth[:3, :3],
                truth[:3, 3] + rng.normal(0, 0.01, 3),
            )
            for _ in range(50)
        ]
    )
    result = one_sigma_average(poses)
    # About a third of clean data fall outside one sigma on the distance test alone.
    assert 0.2 < result.inliers.mean() < 0.75
    rot, trans = pose_difference(result.pose, truth)
    assert np.rad2deg(rot) < 0.5 and trans < 0.01
    with pytest.raises(ValueError, match="poses"):
        one_sigma_average(np.zeros((0, 4, 4)))


def test_combine_candidates_is_the_arithmetic_mean():
    a = make_pose(matrix_from_euler_rpy([0.1, 0.0, 0.2]), [1, 0, 0])
    b = make_pose(matrix_from_euler_rpy([0.3, 0.0, 0.4]), [3, 0, 0])
    c = combine_candidates(np.array([a, b]))
    np.testing.assert_allclose(euler_rpy_from_matrix(c[:3, :3]), [0.2, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(c[:3, 3], [2, 0, 0])


def test_per_tag_pose_matches_the_truth_without_noise():
    grid = AprilGridTarget(tag_rows=2, tag_cols=4, tag_size_m=0.088, tag_spacing_ratio=0.3)
    camera = default_camera()
    truth = invert_pose(
        look_at(np.array([0.3, -0.2, 0.9]), np.array([0.2, 0.1, 0]), np.array([0, 1.0, 0]))
    )
    ids, points = grid.all_corner_points()
    pixels = np.array([camera.project(p @ truth[:3, :3].T + truth[:3, 3]) for p in points])
    observation = GridObservation(0, ids, pixels, points)
    pose = per_tag_target_pose(camera, observation)
    assert pose is not None
    rot, trans = pose_difference(pose, truth)
    assert rot < 1e-6 and trans < 1e-6
    empty = GridObservation(0, ids[:1], np.full((1, 4, 2), np.nan), points[:1])
    assert per_tag_target_pose(camera, empty) is None
