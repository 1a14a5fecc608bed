"""The joint pose graph: every constraint together, robust, with its covariance."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.merge.align import tilt_vector_rad
from postproc.merge.joint import (
    DriftShare,
    Edge,
    connected_nodes,
    shared_drift_covariance,
    solve_joint,
)
from shared.geometry import invert_pose, make_pose, pose_difference, so3_exp

COVARIANCE = np.diag([1e-6] * 3 + [1e-4] * 3)
TRUTH = {
    "a": np.eye(4),
    "b": make_pose(so3_exp([0.0, 0.0, 0.7]), [3.0, 1.0, 0.2]),
    "c": make_pose(so3_exp([0.0, 0.0, -1.2]), [-2.0, 4.0, 0.1]),
    "target:m": make_pose(so3_exp([0.3, 0.2, 1.0]), [1.0, 2.0, -1.0]),
}


def _measured(rng: np.random.Generator, parent: str, child: str) -> np.ndarray:
    relative = invert_pose(TRUTH[parent]) @ TRUTH[child]
    d = rng.multivariate_normal(np.zeros(6), COVARIANCE)
    return make_pose(so3_exp(d[:3]) @ relative[:3, :3], relative[:3, 3] + d[3:])


def _edges(rng: np.random.Generator) -> list[Edge]:
    edges = [
        Edge("features", f"{p}-{c}", p, c, _measured(rng, p, c), COVARIANCE)
        for p, c in (("a", "b"), ("b", "c"), ("a", "c"))
    ]
    edges += [
        Edge("target", f"m@{s}", s, "target:m", _measured(rng, s, "target:m"), COVARIANCE)
        for s in "abc"
    ]
    return edges


def test_joint_estimate_recovers_the_sessions_and_rejects_a_wrong_match():
    rng = np.random.default_rng(0)
    wrong = make_pose(so3_exp([0.0, 0.0, 0.9]), [4.0, 1.0, 0.2])
    edges = [*_edges(rng), Edge("features", "bad", "a", "b", wrong, COVARIANCE)]
    estimate = solve_joint("a", ["a", "b", "c", "d"], edges, tilt_sigma_rad=None)
    for node in ("b", "c"):
        rotation, translation = pose_difference(estimate.world_from_node[node], TRUTH[node])
        sigma = np.sqrt(np.diag(estimate.covariance[node]))
        assert rotation < 4 * np.linalg.norm(sigma[:3]) and translation < 4 * np.linalg.norm(
            sigma[3:]
        )
    assert estimate.unplaced == ("d",)
    by_label = {r.edge.label: r for r in estimate.residuals}
    assert by_label["bad"].outlier and by_label["bad"].weight == 0.0
    assert all(r.weight == 1.0 for label, r in by_label.items() if label != "bad")
    np.testing.assert_allclose(estimate.covariance["a"], np.zeros((6, 6)))


def test_covariance_is_honest_over_many_draws():
    errors = []
    covariances = []
    for seed in range(40):
        estimate = solve_joint(
            "a", ["a", "b", "c"], _edges(np.random.default_rng(seed)), tilt_sigma_rad=None
        )
        errors.append(estimate.world_from_node["b"][:3, 3] - TRUTH["b"][:3, 3])
        covariances.append(estimate.covariance["b"][3:, 3:])
    # Mean squared Mahalanobis distance of 3-D errors is 3 when the covariance is right.
    d2 = [e @ np.linalg.solve(c, e) for e, c in zip(errors, covariances, strict=True)]
    assert 1.5 < np.mean(d2) < 5.0


def test_gravity_and_depth_priors():
    tilted = make_pose(so3_exp([0.01, -0.01, 0.5]), [1.0, 0.0, 0.3])
    loose = np.diag([1e-2] * 3 + [1.0] * 3)
    edges = [Edge("features", "a-b", "a", "b", tilted, loose)]
    free = solve_joint("a", ["a", "b"], edges, tilt_sigma_rad=None)
    held = solve_joint("a", ["a", "b"], edges, tilt_sigma_rad=1e-5, depth_sigma_m=0.01)
    assert np.linalg.norm(tilt_vector_rad(free.world_from_node["b"][:3, :3])) > 0.01
    assert np.linalg.norm(tilt_vector_rad(held.world_from_node["b"][:3, :3])) < 1e-4
    assert abs(held.world_from_node["b"][2, 3]) < 0.001 < abs(free.world_from_node["b"][2, 3])
    assert held.covariance["b"][5, 5] < 2 * 0.01**2 + 1e-9


def test_connected_nodes_and_raise_paths():
    edges = [Edge("target", "m@a", "a", "target:m", np.eye(4), COVARIANCE)]
    assert connected_nodes("a", edges) == {"a", "target:m"}
    with pytest.raises(ValueError, match="reference"):
        solve_joint("z", ["a"], edges, tilt_sigma_rad=None)
    with pytest.raises(ValueError, match="tilt_sigma_rad"):
        solve_joint("a", ["a"], edges, tilt_sigma_rad=0.0)
    with pytest.raises(ValueError, match="depth_sigma_m"):
        solve_joint("a", ["a"], edges, tilt_sigma_rad=None, depth_sigma_m=-1.0)


def test_shared_drift_keeps_the_covariance_honest():
    """Two constraints of session b filmed at 100 s and 110 s share b's first 100 s of
    drift: counted as independent, the estimate claims twice the information it has."""
    rate = np.array([1e-7] * 3 + [1e-5] * 3)
    noise = np.array([1e-8] * 3 + [1e-6] * 3)
    times = (100.0, 110.0)
    eye = np.eye(6)[None]
    d2: dict[bool, list[float]] = {True: [], False: []}
    for seed in range(60):
        rng = np.random.default_rng(seed)
        first = rng.normal(0, np.sqrt(rate * times[0]))
        walk = (first, first + rng.normal(0, np.sqrt(rate * (times[1] - times[0]))))
        edges = []
        for k, (t, drift) in enumerate(zip(times, walk, strict=True)):
            d = drift + rng.normal(0, np.sqrt(noise))
            # b's drift d enters T_a_b (b the child) as the inverse, on the right: -d here.
            measured = make_pose(so3_exp(-d[:3]) @ TRUTH["b"][:3, :3], TRUTH["b"][:3, 3] - d[3:])
            share = DriftShare("b", np.array([t]), -eye)
            edges.append(
                Edge("features", f"ab{k}", "a", "b", measured, np.diag(rate * t + noise), (share,))
            )
        for modelled in (True, False):
            estimate = solve_joint(
                "a",
                ["a", "b"],
                edges,
                tilt_sigma_rad=None,
                drift_rates={"b": rate} if modelled else None,
            )
            error = estimate.world_from_node["b"][:3, 3] - TRUTH["b"][:3, 3]
            d2[modelled].append(
                float(error @ np.linalg.solve(estimate.covariance["b"][3:, 3:], error))
            )
    # Mean squared Mahalanobis distance of 3-D errors: 3 when the covariance is right.
    assert 2.0 < np.mean(d2[True]) < 4.2
    assert np.mean(d2[False]) > 4.5
    cross = shared_drift_covariance(edges[0], edges[1], {"b": rate})
    np.testing.assert_allclose(cross, np.diag(rate * times[0]))
    assert not shared_drift_covariance(edges[0], edges[1], {}).any()
