"""Depth factors: re-optimise a trajectory with the dive computer's depth (GTSAM 4.3).

After the clock sync, every dive-computer sample is a measurement of the
world z of the trajectory frame at a known camera time. A single shift (what
the sync alone gives) keeps the VIO's vertical drift; here the trajectory is
re-optimised as a pose graph so that drift is removed along the whole dive:

* nodes: poses of the trajectory at most every `node_interval_s` (the poses
  in between follow their neighbouring nodes, so a 30 Hz trajectory costs no
  more than a 1 Hz one);
* odometry: a `BetweenFactorPose3` between consecutive nodes holding the
  original relative pose, with sigmas growing as sqrt(dt) (VIO drift is a
  random walk), plus a floor;
* depth: a z prior at each dive sample time, on the two nodes around it with
  the linear-interpolation weights (`ZPriorFactor`: a `gtsam.CustomFactor`
  with an analytic Jacobian; GTSAM 4.3 has no built-in one-axis prior and no
  prior between two poses), under a Huber loss so spikes do not pull;
* attitude: a loose prior on every node's rotation at the VIO's (gravity
  keeps VIO roll and pitch from drifting), so z corrections are not absorbed
  by tilting the path;
* gauge: a prior on the first node's rotation and horizontal position (depth
  fixes z; x, y and yaw are unobservable).

Pure math (gtsam and numpy), no I/O; gtsam is imported inside the functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from shared.geometry import invert_pose, make_pose, so3_exp, so3_log

FloatArray = npt.NDArray[np.float64]


@dataclass(kw_only=True)
class FusionSettings:
    """Noise model of the depth fusion.

    depth_sigma_m: one-sigma error of a depth sample as a measure of the
        trajectory frame's depth, metres (0.1 m resolution: 0.029, plus the
        offset between the wrist and the camera, waves).
    odometry_sigma_m_per_sqrt_s: VIO position random walk, m / sqrt(s).
    odometry_sigma_rad_per_sqrt_s: VIO rotation random walk, rad / sqrt(s).
    odometry_floor_m, odometry_floor_rad: smallest sigmas of one odometry step.
    attitude_sigma_rad: prior holding each node's rotation to the VIO's (VIO
        roll and pitch do not drift, gravity fixes them; depth says nothing
        about yaw), so depth corrections move positions and not attitudes.
    node_interval_s: shortest time between two optimised poses, seconds.
    huber_k: Huber threshold of the depth priors, in sigmas.
    max_iterations: Levenberg-Marquardt iterations.
    """

    depth_sigma_m: float = math.hypot(0.1 / math.sqrt(12.0), 0.05)
    odometry_sigma_m_per_sqrt_s: float = 0.01
    odometry_sigma_rad_per_sqrt_s: float = 0.001
    odometry_floor_m: float = 0.001
    odometry_floor_rad: float = 0.0002
    attitude_sigma_rad: float = 0.005
    node_interval_s: float = 1.0
    huber_k: float = 1.345
    max_iterations: int = 50


@dataclass
class FusionResult:
    """Fused poses (N, 4, 4) at the input stamps, and what the optimiser did.

    nodes: indices of the input poses that were optimised; depth_factors: the
    number of depth samples used; error_before / error_after: the graph's
    total error at the start and at the end (GTSAM units, half the weighted
    squared residuals).
    """

    poses: FloatArray
    nodes: npt.NDArray[np.int64]
    depth_factors: int
    error_before: float
    error_after: float
    iterations: int


def select_nodes(stamps_s: FloatArray, interval_s: float) -> npt.NDArray[np.int64]:
    """Indices of poses at least `interval_s` apart, always the first and the last."""
    chosen = [0]
    for i in range(1, stamps_s.size - 1):
        if stamps_s[i] - stamps_s[chosen[-1]] >= interval_s:
            chosen.append(i)
    if stamps_s.size > 1:
        chosen.append(stamps_s.size - 1)
    return np.asarray(chosen, dtype=np.int64)


def z_prior_factor(key_a: int, key_b: int, weight_b: float, z_m: float, noise: Any) -> Any:
    """A `gtsam.CustomFactor` on two Pose3: (1 - w) z_a + w z_b - z_m, w = `weight_b`.

    The Jacobian of a Pose3's translation with respect to its tangent
    (rotation first, then translation in the body frame) is [0 | R], so the z
    row is [0, 0, 0, R[2, :]].
    """
    import gtsam

    weight_a = 1.0 - weight_b

    def error(this: Any, values: Any, jacobians: Any) -> FloatArray:
        pose_a = values.atPose3(this.keys()[0])
        pose_b = values.atPose3(this.keys()[1])
        ta = pose_a.translation()
        tb = pose_b.translation()
        if jacobians is not None:
            ha = np.zeros((1, 6))
            hb = np.zeros((1, 6))
            ha[0, 3:] = weight_a * pose_a.rotation().matrix()[2, :]
            hb[0, 3:] = weight_b * pose_b.rotation().matrix()[2, :]
            jacobians[0] = ha
            jacobians[1] = hb
        return np.array([weight_a * ta[2] + weight_b * tb[2] - z_m])

    return gtsam.CustomFactor(noise, [key_a, key_b], error)


def fuse_depth(
    stamps_s: npt.ArrayLike,
    world_from_body: npt.ArrayLike,
    depth_stamps_s: npt.ArrayLike,
    depth_z_m: npt.ArrayLike,
    *,
    settings: FusionSettings | None = None,
) -> FusionResult:
    """Re-optimise poses `world_from_body` (N, 4, 4) at `stamps_s` (N,) with z measurements.

    `depth_stamps_s` (M,) are the dive samples' camera-clock times (same
    relative seconds as `stamps_s`, after the clock sync), `depth_z_m` their
    world z (metres, up: minus the depth). Samples outside the trajectory are
    ignored. Returns the poses at the same stamps.
    """
    import gtsam

    settings = settings or FusionSettings()
    t = np.asarray(stamps_s, dtype=np.float64)
    T = np.asarray(world_from_body, dtype=np.float64)
    zt = np.asarray(depth_stamps_s, dtype=np.float64)
    zm = np.asarray(depth_z_m, dtype=np.float64)
    if T.shape != (t.size, 4, 4) or t.size < 2:
        raise ValueError(f"fuse_depth: expected (N >= 2, 4, 4) poses for {t.size} stamps")
    keep = np.isfinite(zm) & (zt >= t[0]) & (zt <= t[-1])
    zt, zm = zt[keep], zm[keep]

    nodes = select_nodes(t, settings.node_interval_s)
    node_t = t[nodes]
    node_T = T[nodes]
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for k, pose in enumerate(node_T):
        initial.insert(k, gtsam.Pose3(pose))

    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(node_T[0]), _world_z_free_noise(node_T[0])))
    attitude = gtsam.noiseModel.Isotropic.Sigma(3, settings.attitude_sigma_rad)
    for k in range(nodes.size):
        graph.add(gtsam.PoseRotationPrior3D(k, gtsam.Pose3(node_T[k]), attitude))
    for k in range(nodes.size - 1):
        dt = max(node_t[k + 1] - node_t[k], 1e-6)
        rot = settings.odometry_floor_rad + settings.odometry_sigma_rad_per_sqrt_s * math.sqrt(dt)
        pos = settings.odometry_floor_m + settings.odometry_sigma_m_per_sqrt_s * math.sqrt(dt)
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot, rot, rot, pos, pos, pos]))
        relative = invert_pose(node_T[k]) @ node_T[k + 1]
        graph.add(gtsam.BetweenFactorPose3(k, k + 1, gtsam.Pose3(relative), noise))

    depth_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(settings.huber_k),
        gtsam.noiseModel.Isotropic.Sigma(1, settings.depth_sigma_m),
    )
    right = np.clip(np.searchsorted(node_t, zt, side="right"), 1, nodes.size - 1)
    for stamp, z_meas, b in zip(zt, zm, right, strict=True):
        a = b - 1
        w = float((stamp - node_t[a]) / (node_t[b] - node_t[a]))
        graph.add(z_prior_factor(int(a), int(b), w, float(z_meas), depth_noise))

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    error_before = float(graph.error(initial))
    result = optimizer.optimize()
    error_after = float(graph.error(result))
    fused_nodes = np.stack([result.atPose3(k).matrix() for k in range(nodes.size)])
    poses = _follow_nodes(t, T, nodes, fused_nodes)
    return FusionResult(
        poses=poses,
        nodes=nodes,
        depth_factors=int(zt.size),
        error_before=error_before,
        error_after=error_after,
        iterations=int(optimizer.iterations()),
    )


def _world_z_free_noise(world_from_body: FloatArray) -> Any:
    """Prior noise of the first node: rotation and x, y held, z free (depth decides it).

    GTSAM's Pose3 translation error is in the body frame, so the world-frame
    covariance diag(tight, tight, loose) is rotated into the body frame.
    """
    import gtsam

    R = world_from_body[:3, :3]
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * 1e-8
    world_cov = np.diag([1e-8, 1e-8, 1e4])
    cov[3:, 3:] = R.T @ world_cov @ R
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def _follow_nodes(
    t: FloatArray, T: FloatArray, nodes: npt.NDArray[np.int64], fused_nodes: FloatArray
) -> FloatArray:
    """Move every pose with its two neighbouring nodes, blended by time.

    A pose between nodes a and b keeps its original pose relative to each;
    the two predictions are blended (translation linearly, rotation on the
    geodesic) with the time weight, so the correction varies smoothly.
    """
    out = T.copy()
    out[nodes] = fused_nodes
    node_t = t[nodes]
    b = np.clip(np.searchsorted(node_t, t, side="right"), 1, nodes.size - 1)
    a = b - 1
    w = (t - node_t[a]) / (node_t[b] - node_t[a])
    from_a = fused_nodes[a] @ invert_pose(T[nodes[a]]) @ T
    from_b = fused_nodes[b] @ invert_pose(T[nodes[b]]) @ T
    Ra = from_a[:, :3, :3]
    delta = so3_log(np.swapaxes(Ra, -1, -2) @ from_b[:, :3, :3])
    R = Ra @ so3_exp(w[:, None] * delta)
    p = (1.0 - w)[:, None] * from_a[:, :3, 3] + w[:, None] * from_b[:, :3, 3]
    blended = make_pose(R, p)
    is_node = np.zeros(t.size, dtype=bool)
    is_node[nodes] = True
    out[~is_node] = blended[~is_node]
    return out
