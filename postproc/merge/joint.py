"""The session transforms from every constraint together: a robust pose graph.

Pure math: no I/O, no logging. Nodes are the sessions (frames `S_k`) and the
targets (`m`); the unknowns are their poses in W, the reference session's
frame (held at the identity). Constraints:

* `Edge`: a measured relative pose `T_parent_child` with its 6x6 covariance:
  a target's drift-weighted pose in a session (`T_S_m`), or a natural-feature
  pair's drift-aware mean (`T_Sa_Sb`, `places.pair_place_mean`).
* gravity (`tilt_sigma_rad`): every session frame is gravity-aligned by its
  IMU up to its roll/pitch error σ, so each session's tilt in W gets a
  zero-mean prior of σ√2 per axis (both frames err); dof 4 holds it at zero.
* depth (`depth_sigma_m`): depth-fused sessions are at absolute depth, so
  each session's z offset in W gets a zero-mean prior of σ√2.

Each session's drift model is inside the edges' covariances (a constraint far
in time from the session anchor carries the drift since). Two constraints of one
session share the drift up to the earlier of them: a target filmed at 60 s and a
natural-feature place filmed at 40 s both carry the drift of the first 40 s, so
their errors are correlated, and treating them as independent counts that drift
twice and leans on it (targets and features together were then worse than targets
alone on the simulated wreck). An edge's `drift` terms say which weighted
combination of its session's random walk it carries (`DriftShare`); with the
sessions' `drift_rates`, the estimate uses the full covariance of all edges
together, off-diagonal blocks `Σ_ef = A_e diag(q wₑᵀ min(τₑ, τ_f) w_f) A_fᵀ`.

The estimate is Gauss-Newton on the Mahalanobis cost with Huber weights on each
edge (an edge whose whitened residual, by its own covariance, exceeds `huber_k` is
down-weighted and flagged); the covariance is the inverse of the weighted Hessian,
in `averaging`'s convention (6x6 of `[δθ, δt]`, `R = Exp(δθ) R̄`, `t = t̄ + δt` in
W, rotation first, radians and metres).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
import numpy.typing as npt

from postproc.merge.align import tilt_vector_rad
from postproc.merge.averaging import pose_residuals
from shared.geometry import invert_pose, make_pose, so3_exp

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class DriftShare:
    """The part of an edge's error that is one session's SLAM drift.

    The edge's residual holds `Σ_i gains[i] @ d(times_s[i])` of the session's random
    walk `d` (6,) `[δθ, δt]` (rotation about the camera, then a shift, in the session
    frame; zero at its anchor). times_s (N,): seconds since the anchor; gains
    (N, 6, 6): for a mean of N observations, each one's weight (per axis, a diagonal)
    times how its drift enters the edge's residual.
    """

    session: str
    times_s: FloatArray
    gains: FloatArray


@dataclass(frozen=True)
class Edge:
    """A measured `T_parent_child` (4, 4) with covariance (6, 6); kind: "target" or "features".

    drift: the session drift it carries (`DriftShare`), for its correlation with the
    other edges of the same sessions; empty: independent of every other edge.
    """

    kind: str
    label: str
    parent: str
    child: str
    parent_from_child: FloatArray
    covariance: FloatArray
    drift: tuple[DriftShare, ...] = ()


def shared_drift_covariance(e: Edge, f: Edge, drift_rates: Mapping[str, FloatArray]) -> FloatArray:
    """Cross-covariance (6, 6) of two edges' residuals through their sessions' common drift.

    A random walk with variance rate q (6,) per second has `cov(d(s), d(t)) = q min(s, t)`
    per axis; negative times count as 0. Sessions without a rate give nothing.
    """
    out = np.zeros((6, 6))
    for a in e.drift:
        for b in f.drift:
            if a.session != b.session or a.session not in drift_rates:
                continue
            shared = np.minimum.outer(np.maximum(a.times_s, 0.0), np.maximum(b.times_s, 0.0))
            rate = np.asarray(drift_rates[a.session], dtype=np.float64)
            out += np.einsum("iak,k,ij,jbk->ab", a.gains, rate, shared, b.gains)
    return out


def _joint_covariance(
    edges: Sequence[Edge], drift_rates: Mapping[str, FloatArray] | None
) -> FloatArray:
    """(6E, 6E) covariance of all edges' residuals: own blocks plus shared drift.

    The cross terms come from the drift model, the own blocks from each edge's
    estimate (never tighter than the model); should the whole still not be positive
    definite, the cross terms are halved until it is.
    """
    size = 6 * len(edges)
    own = np.zeros((size, size))
    cross = np.zeros((size, size))
    for i, e in enumerate(edges):
        own[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = 0.5 * (e.covariance + e.covariance.T)
        if drift_rates is None:
            continue
        for j in range(i + 1, len(edges)):
            block = shared_drift_covariance(e, edges[j], drift_rates)
            cross[6 * i : 6 * i + 6, 6 * j : 6 * j + 6] = block
            cross[6 * j : 6 * j + 6, 6 * i : 6 * i + 6] = block.T
    for _ in range(20):
        total = own + cross
        try:
            np.linalg.cholesky(total)
            return total
        except np.linalg.LinAlgError:
            cross *= 0.5
    return own


@dataclass(frozen=True)
class EdgeResidual:
    """One constraint at the solution: rotation (deg), translation (m), whitened norm, weight
    (1 inside `huber_k`, less beyond, 0 when rejected)."""

    edge: Edge
    rotation_deg: float
    translation_m: float
    mahalanobis: float
    weight: float

    @property
    def outlier(self) -> bool:
        """True when the constraint was dropped as a gross outlier."""
        return self.weight == 0.0


@dataclass(frozen=True)
class JointEstimate:
    """Poses `T_W_node` (4, 4) and marginal covariances (6, 6) of the placed nodes.

    unplaced: nodes with no chain of constraints to the reference.
    residuals: one per edge used. iterations: Gauss-Newton steps taken.
    """

    world_from_node: dict[str, FloatArray]
    covariance: dict[str, FloatArray]
    unplaced: tuple[str, ...]
    residuals: tuple[EdgeResidual, ...]
    iterations: int


def connected_nodes(reference: str, edges: Sequence[Edge]) -> set[str]:
    """Nodes reachable from `reference` through the edges (either direction)."""
    neighbours: dict[str, set[str]] = {}
    for e in edges:
        neighbours.setdefault(e.parent, set()).add(e.child)
        neighbours.setdefault(e.child, set()).add(e.parent)
    seen = {reference}
    queue = deque([reference])
    while queue:
        node = queue.popleft()
        for other in neighbours.get(node, ()):
            if other not in seen:
                seen.add(other)
                queue.append(other)
    return seen


def _initial_poses(reference: str, edges: Sequence[Edge], nodes: set[str]) -> dict[str, FloatArray]:
    """A spanning tree from the reference, most certain edges first."""
    poses = {reference: np.eye(4)}
    ordered = sorted(edges, key=lambda e: float(np.trace(e.covariance)))
    while len(poses) < len(nodes):
        grown = False
        for e in ordered:
            if e.parent in poses and e.child not in poses:
                poses[e.child] = poses[e.parent] @ e.parent_from_child
                grown = True
            elif e.child in poses and e.parent not in poses:
                poses[e.parent] = poses[e.child] @ invert_pose(e.parent_from_child)
                grown = True
        if not grown:
            break
    return poses


def _perturbed(pose: FloatArray, delta: FloatArray) -> FloatArray:
    return make_pose(so3_exp(delta[:3]) @ pose[:3, :3], pose[:3, 3] + delta[3:])


def _edge_residual(e: Edge, poses: dict[str, FloatArray]) -> FloatArray:
    predicted = invert_pose(poses[e.parent]) @ poses[e.child]
    residual: FloatArray = pose_residuals(e.parent_from_child[None], predicted)[0]
    return residual


def _edge_jacobian(
    e: Edge, poses: dict[str, FloatArray], index: dict[str, int], size: int
) -> FloatArray:
    """(6, size) derivative of the edge residual by the free nodes' perturbations."""
    jacobian = np.zeros((6, size))
    for node in (e.parent, e.child):
        if node not in index:
            continue
        for axis in range(6):
            h = np.zeros(6)
            h[axis] = 1e-6
            moved = dict(poses)
            moved[node] = _perturbed(poses[node], h)
            plus = _edge_residual(e, moved)
            moved[node] = _perturbed(poses[node], -h)
            minus = _edge_residual(e, moved)
            jacobian[:, 6 * index[node] + axis] = (plus - minus) / 2e-6
    return jacobian


def solve_joint(
    reference: str,
    sessions: Sequence[str],
    edges: Sequence[Edge],
    *,
    tilt_sigma_rad: float | None,
    depth_sigma_m: float | None = None,
    drift_rates: Mapping[str, FloatArray] | None = None,
    huber_k: float = 4.1,
    reject_k: float = 12.0,
    max_iterations: int = 30,
) -> JointEstimate:
    """Every node's pose in the reference frame from all constraints at once.

    sessions: the session nodes (the gravity and depth priors apply to them).
    tilt_sigma_rad: each session's roll/pitch error (rad, 1 sigma per axis), None for
    no gravity prior. depth_sigma_m: each session's absolute-depth error (m), None
    when the sessions are not depth-fused. drift_rates: per session its random-walk
    variance rates (6,) (rad²/s, m²/s), for the edges' shared drift (`DriftShare`);
    None: every edge independent. huber_k: whitened residual norm beyond
    which an edge is down-weighted (4.1: the 99 % point of chi-square with 6 dof);
    reject_k: beyond which it is dropped once the Huber estimate has converged.
    Raises ValueError when the reference is not a session or a sigma is not positive.
    """
    if reference not in sessions:
        raise ValueError(f"solve_joint: reference {reference!r} not among {list(sessions)}")
    for name, value in (("tilt_sigma_rad", tilt_sigma_rad), ("depth_sigma_m", depth_sigma_m)):
        if value is not None and not (value > 0 and np.isfinite(value)):
            raise ValueError(f"solve_joint: {name} must be positive, got {value}")
    nodes = connected_nodes(reference, edges)
    used = [e for e in edges if e.parent in nodes and e.child in nodes]
    poses = _initial_poses(reference, used, nodes)
    free = sorted(n for n in nodes if n != reference)
    index = {n: i for i, n in enumerate(free)}
    size = 6 * len(free)
    informations = [np.linalg.inv(0.5 * (e.covariance + e.covariance.T)) for e in used]
    priors: list[tuple[str, str, float]] = []
    for s in sessions:
        if s in index:
            if tilt_sigma_rad is not None:
                priors.append((s, "tilt", 2.0 * tilt_sigma_rad**2))
            if depth_sigma_m is not None:
                priors.append((s, "depth", 2.0 * depth_sigma_m**2))
    weights = np.ones(len(used))
    hessian = np.zeros((size, size))
    iterations = 0
    joint_covariance = _joint_covariance(used, drift_rates)
    # Huber weights first; then edges beyond `reject_k` (gross outliers, which even a
    # Huber weight lets pull) are dropped and the estimate converges again.
    saved: tuple[dict[str, FloatArray], FloatArray, FloatArray] | None = None
    for reject in (np.inf, reject_k):
        if saved is None and np.isfinite(reject):
            saved = (dict(poses), weights.copy(), hessian.copy())
        for _ in range(max_iterations):
            iterations += 1
            hessian = np.zeros((size, size))
            gradient = np.zeros(size)
            current = [_edge_residual(e, poses) for e in used]
            for k, (r, info) in enumerate(zip(current, informations, strict=True)):
                whitened = float(np.sqrt(max(float(r @ info @ r), 0.0)))
                if whitened > reject:
                    weights[k] = 0.0
                else:
                    weights[k] = 1.0 if whitened <= huber_k else huber_k / whitened
            kept = np.flatnonzero(weights > 0)
            if len(kept):
                rows = (6 * kept[:, None] + np.arange(6)).reshape(-1)
                # A Huber weight w scales the edge's covariance by 1/w (IRLS); the
                # dropped edges are marginalised out (their rows and columns removed).
                scale = np.repeat(1.0 / np.sqrt(weights[kept]), 6)
                information = np.linalg.inv(
                    joint_covariance[np.ix_(rows, rows)] * np.outer(scale, scale)
                )
                jacobian = np.vstack([_edge_jacobian(used[k], poses, index, size) for k in kept])
                stacked = np.concatenate([current[k] for k in kept])
                hessian += jacobian.T @ information @ jacobian
                gradient -= jacobian.T @ information @ stacked
            for node, what, variance in priors:
                i = 6 * index[node]
                if what == "tilt":
                    # d tilt / d δθ[:2] is the identity to first order (`tilt_vector_rad`).
                    hessian[i : i + 2, i : i + 2] += np.eye(2) / variance
                    gradient[i : i + 2] -= tilt_vector_rad(poses[node][:3, :3]) / variance
                else:
                    hessian[i + 5, i + 5] += 1.0 / variance
                    gradient[i + 5] -= poses[node][2, 3] / variance
            # Gauss-Newton: H δ = -Jᵀ Σ⁻¹ r (the gradient above carries the sign).
            try:
                step = cast(FloatArray, np.linalg.solve(hessian, gradient)) if size else np.zeros(0)
            except np.linalg.LinAlgError:
                if saved is None:
                    raise
                # Dropping the gross outliers left a node unconstrained: every edge
                # disagrees at that level, so keep the Huber estimate and report them all.
                poses, weights, hessian = saved
                break
            for node, i in index.items():
                poses[node] = _perturbed(poses[node], step[6 * i : 6 * i + 6])
            if size == 0 or np.linalg.norm(step) < 1e-10:
                break
    covariance_all = np.linalg.inv(hessian) if size else np.zeros((0, 0))
    covariance = {reference: np.zeros((6, 6))}
    for node, i in index.items():
        block = covariance_all[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]
        covariance[node] = 0.5 * (block + block.T)
    residuals = []
    for e, info, w in zip(used, informations, weights, strict=True):
        r = _edge_residual(e, poses)
        residuals.append(
            EdgeResidual(
                e,
                float(np.rad2deg(np.linalg.norm(r[:3]))),
                float(np.linalg.norm(r[3:])),
                float(np.sqrt(max(float(r @ info @ r), 0.0))),
                float(w),
            )
        )
    everything = set(sessions) | {n for e in edges for n in (e.parent, e.child)}
    return JointEstimate(
        world_from_node={n: poses[n] for n in sorted(nodes)},
        covariance=covariance,
        unplaced=tuple(sorted(everything - nodes)),
        residuals=tuple(residuals),
        iterations=iterations,
    )
