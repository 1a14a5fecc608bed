"""Depth factors: the z prior's Jacobian and the removal of vertical VIO drift."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.depth.factors import FusionSettings, fuse_depth, select_nodes, z_prior_factor
from postproc.depth.sync import fit_depth_sync
from sim.dive import simulate_dive

from .inputs import relative_inputs

gtsam = pytest.importorskip("gtsam")


def test_z_prior_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(2):
        rot = gtsam.Rot3.Expmap(rng.normal(0.0, 0.5, 3))
        poses.append(gtsam.Pose3(rot, rng.normal(0.0, 3.0, 3)))
    factor = z_prior_factor(1, 2, 0.3, -12.0, gtsam.noiseModel.Unit.Create(1))
    values = gtsam.Values()
    values.insert(1, poses[0])
    values.insert(2, poses[1])
    linear = factor.linearize(values)
    A, b = linear.jacobian()
    expected_error = 0.7 * poses[0].z() + 0.3 * poses[1].z() + 12.0
    assert b[0] == pytest.approx(-expected_error)
    eps = 1e-6
    numeric = np.zeros((1, 12))
    for k, key in enumerate((1, 2)):
        for i in range(6):
            delta = np.zeros(6)
            delta[i] = eps
            shifted = gtsam.Values()
            shifted.insert(1, poses[0])
            shifted.insert(2, poses[1])
            shifted.update(key, values.atPose3(key).retract(delta))
            numeric[0, 6 * k + i] = (factor.unwhitenedError(shifted)[0] - expected_error) / eps
    np.testing.assert_allclose(A, numeric, atol=1e-5)


def test_select_nodes_keeps_ends_and_spacing():
    t = np.array([0.0, 0.2, 0.5, 1.1, 1.3, 2.4, 2.5])
    nodes = select_nodes(t, 1.0)
    assert nodes.tolist() == [0, 3, 5, 6]


def test_depth_factors_remove_vertical_drift():
    sim = simulate_dive(seed=21, time_offset_s=61.0, vio_z_drift_m_per_sqrt_s=0.01)
    traj_t, traj_z, dive_t, depth = relative_inputs(sim)
    sync = fit_depth_sync(traj_t, traj_z, dive_t, depth, initial_offset_s=61.0)
    world = sim.trajectory.poses.copy()
    world[:, 2, 3] = sync.world_z_m(traj_z)
    true_z = sim.truth_world.positions[:, 2]
    before = float(np.sqrt(np.mean((world[:, 2, 3] - true_z) ** 2)))
    result = fuse_depth(
        traj_t, world, sync.camera_time_s(dive_t), -depth, settings=FusionSettings()
    )
    after = float(np.sqrt(np.mean((result.poses[:, 2, 3] - true_z) ** 2)))
    assert before > 0.08  # the drift is there
    assert after < 0.5 * before
    # Horizontal shape and rotations barely change: the depth only moves z.
    assert np.max(np.abs(result.poses[:, :2, 3] - world[:, :2, 3])) < 0.1
    assert result.depth_factors > 100
    assert result.error_after < result.error_before


def test_fuse_depth_rejects_bad_shapes():
    with pytest.raises(ValueError, match="poses"):
        fuse_depth(np.arange(3.0), np.zeros((2, 4, 4)), np.zeros(1), np.zeros(1))
