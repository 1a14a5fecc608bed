"""Session-to-session transforms from shared targets, with covariances.

Pure math: no I/O, no logging. Covariances follow `averaging`'s convention:
6x6 of `[δθ, δt]` with `R = Exp(δθ) R̄`, `t = t̄ + δt` in the parent frame,
rotation first, radians and metres.

A target `m` seen in sessions A and B gives one candidate
`T_A_B = T_A_m @ inv(T_B_m)`. Several shared targets are combined:

* 6 DoF (`align_6dof`): the information-weighted SE(3) mean of the candidates.
* 4 DoF (`align_4dof`, for gravity-aligned sessions): only yaw and a
  translation are free. Each target gives its position (3 residuals) and its
  heading about z (1 residual); Gauss-Newton over (yaw, t) weighted by the
  propagated covariances. The target's tilt, which in a 6-DoF candidate turns
  into a translation error proportional to the target's distance from the
  session origin, is not used.
* 6 DoF with a gravity prior (`align_6dof(..., tilt_prior_sigma_rad=σ)`): every
  session frame is gravity-aligned up to its SLAM's roll/pitch error (σ per axis
  and session), so the relative roll and pitch of `T_A_B` get a zero-mean prior
  of σ√2 per axis on top of the candidates' information. Strong target evidence
  corrects the tilt; weak evidence leaves it near zero, the 4-DoF answer.

`place_sessions` chains these over many sessions: starting at the reference
session, it repeatedly places the unplaced session sharing the most targets
with those already placed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, cast

import numpy as np
import numpy.typing as npt

from postproc.merge.averaging import fuse_pose_estimates, pose_residuals
from shared.geometry import invert_pose, make_pose, rotation_angle_rad, skew, so3_exp, so3_log

FloatArray = npt.NDArray[np.float64]

Dof = Literal[4, 6]


def compose_with_covariance(
    a_from_b: FloatArray, cov_ab: FloatArray, b_from_c: FloatArray, cov_bc: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """`T_A_C = T_A_B @ T_B_C` and its covariance (the two inputs independent)."""
    R_ab = a_from_b[:3, :3]
    t_ac_rotated = R_ab @ b_from_c[:3, 3]
    J_ab = np.eye(6)
    J_ab[3:, :3] = -skew(t_ac_rotated)
    J_bc = np.zeros((6, 6))
    J_bc[:3, :3] = R_ab
    J_bc[3:, 3:] = R_ab
    covariance = J_ab @ cov_ab @ J_ab.T + J_bc @ cov_bc @ J_bc.T
    return a_from_b @ b_from_c, 0.5 * (covariance + covariance.T)


def invert_with_covariance(
    a_from_b: FloatArray, cov_ab: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """`T_B_A = inv(T_A_B)` and its covariance."""
    R = a_from_b[:3, :3]
    t = a_from_b[:3, 3]
    J = np.zeros((6, 6))
    J[:3, :3] = -R.T
    J[3:, :3] = -R.T @ skew(t)
    J[3:, 3:] = -R.T
    covariance = J @ cov_ab @ J.T
    return invert_pose(a_from_b), 0.5 * (covariance + covariance.T)


@dataclass(frozen=True)
class TargetPair:
    """One target seen in sessions A and B: its pose in each and their covariances."""

    name: str
    a_from_target: FloatArray
    a_covariance: FloatArray
    b_from_target: FloatArray
    b_covariance: FloatArray

    def candidate(self) -> tuple[FloatArray, FloatArray]:
        """The 6-DoF candidate `T_A_B = T_A_m @ inv(T_B_m)` and its covariance."""
        target_from_b, cov = invert_with_covariance(self.b_from_target, self.b_covariance)
        return compose_with_covariance(self.a_from_target, self.a_covariance, target_from_b, cov)


@dataclass(frozen=True)
class Alignment:
    """`T_A_B` from shared targets.

    a_from_b: (4, 4). covariance: (6, 6) (for 4 DoF the roll and pitch rows are zero:
    the model holds them fixed). dof: 4 or 6. target_names: the targets used.
    residuals_rad_m: per target (rotation angle rad, position error m) of the
    target's pose in A against `T_A_B @ T_B_m`.
    """

    a_from_b: FloatArray
    covariance: FloatArray
    dof: Dof
    target_names: tuple[str, ...]
    residuals_rad_m: tuple[tuple[float, float], ...] = field(default=())


def _residuals(
    pairs: Sequence[TargetPair], a_from_b: FloatArray
) -> tuple[tuple[float, float], ...]:
    out = []
    for pair in pairs:
        predicted = a_from_b @ pair.b_from_target
        angle = rotation_angle_rad(predicted[:3, :3].T @ pair.a_from_target[:3, :3])
        distance = float(np.linalg.norm(predicted[:3, 3] - pair.a_from_target[:3, 3]))
        out.append((angle, distance))
    return tuple(out)


def _check_pairs(pairs: Sequence[TargetPair], what: str) -> None:
    if len(pairs) == 0:
        raise ValueError(f"{what}: no shared target")


def tilt_vector_rad(rotation: FloatArray) -> FloatArray:
    """(2,) roll/pitch part `w` of `R = Exp([w, 0]) Rz(yaw)` (rad, parent frame).

    The rotation vector, perpendicular to z, that tilts z onto `R @ e_z`; zero for a
    rotation about z. A small rotation `Exp(δθ)` applied on the left adds
    `δθ[:2]` to it to first order.
    """
    z = np.asarray(rotation, dtype=np.float64)[:3, 2]
    axis = np.array([-z[1], z[0]])
    sine = float(np.linalg.norm(axis))
    angle = float(np.arctan2(sine, z[2]))
    if sine < 1e-15:
        return np.zeros(2) if z[2] > 0 else np.array([np.pi, 0.0])
    return np.asarray(axis * (angle / sine), dtype=np.float64)


def align_6dof(
    pairs: Sequence[TargetPair],
    *,
    tilt_prior_sigma_rad: float | None = None,
    max_iterations: int = 30,
) -> Alignment:
    """Full SE(3) `T_A_B`: the information-weighted mean of the per-target candidates.

    tilt_prior_sigma_rad: None for no prior; else the roll/pitch error (rad, 1 sigma
    per axis) of each session's gravity alignment: the relative tilt of `T_A_B`
    (`tilt_vector_rad`) gets a zero-mean Gaussian prior of sigma·√2 per axis, and the
    fit is the maximum a posteriori estimate by Gauss-Newton on SE(3). The
    covariance is that of the posterior (roll and pitch never looser than the prior).
    Raises ValueError for no pair or a sigma that is not positive and finite.
    """
    _check_pairs(pairs, "align_6dof")
    candidates = [pair.candidate() for pair in pairs]
    pose, covariance = fuse_pose_estimates(
        np.array([c[0] for c in candidates]), np.array([c[1] for c in candidates])
    )
    if tilt_prior_sigma_rad is not None:
        if not (tilt_prior_sigma_rad > 0 and np.isfinite(tilt_prior_sigma_rad)):
            raise ValueError(
                f"align_6dof: tilt_prior_sigma_rad must be positive, got {tilt_prior_sigma_rad}"
            )
        pose, covariance = _with_tilt_prior(
            np.array([c[0] for c in candidates]),
            cast(FloatArray, np.linalg.inv(covariance)),
            [cast(FloatArray, np.linalg.inv(c[1])) for c in candidates],
            pose,
            2.0 * tilt_prior_sigma_rad**2,
            max_iterations,
        )
    return Alignment(
        a_from_b=pose,
        covariance=covariance,
        dof=6,
        target_names=tuple(p.name for p in pairs),
        residuals_rad_m=_residuals(pairs, pose),
    )


def _with_tilt_prior(
    candidates: FloatArray,
    total_information: FloatArray,
    informations: Sequence[FloatArray],
    start: FloatArray,
    prior_variance_rad2: float,
    max_iterations: int,
) -> tuple[FloatArray, FloatArray]:
    """MAP of the candidates' Mahalanobis cost plus `|tilt|² / prior_variance`."""
    prior = np.zeros((6, 6))
    prior[0, 0] = prior[1, 1] = 1.0 / prior_variance_rad2
    hessian = total_information + prior
    pose = start.copy()
    for _ in range(max_iterations):
        r = pose_residuals(candidates, pose)
        gradient = sum((info @ ri for info, ri in zip(informations, r, strict=True)), np.zeros(6))
        gradient[:2] -= tilt_vector_rad(pose[:3, :3]) / prior_variance_rad2
        step = np.linalg.solve(hessian, gradient)
        pose = make_pose(so3_exp(step[:3]) @ pose[:3, :3], pose[:3, 3] + step[3:])
        if np.linalg.norm(step) < 1e-13:
            break
    covariance = np.linalg.inv(hessian)
    return pose, 0.5 * (covariance + covariance.T)


def yaw_rad(rotation: FloatArray) -> float:
    """Heading (rad) of the rotation about z closest to `rotation` (Frobenius norm)."""
    return float(np.arctan2(rotation[1, 0] - rotation[0, 1], rotation[0, 0] + rotation[1, 1]))


def _rot_z(angle: float) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(angle: FloatArray | float) -> FloatArray:
    return np.asarray((np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


def align_4dof(pairs: Sequence[TargetPair], *, max_iterations: int = 30) -> Alignment:
    """`T_A_B` restricted to a yaw about z and a translation (gravity-aligned sessions).

    Residuals per target: its heading difference (1) and its position in A
    against `Rz t_B_m + t` (3), weighted by the propagated 4x4 covariance.
    """
    _check_pairs(pairs, "align_4dof")
    e_z = np.array([0.0, 0.0, 1.0])
    headings = []
    informations = []
    for pair in pairs:
        R_ab = pair.a_from_target[:3, :3] @ pair.b_from_target[:3, :3].T
        headings.append(yaw_rad(R_ab))
        # Linearised 4-D residual [heading, position] against both target poses.
        J_a = np.zeros((4, 6))
        J_a[0, :3] = e_z
        J_a[1:, 3:] = np.eye(3)
        J_b = np.zeros((4, 6))
        J_b[0, :3] = -e_z @ R_ab
        J_b[1:, 3:] = -_rot_z(headings[-1])
        cov = J_a @ pair.a_covariance @ J_a.T + J_b @ pair.b_covariance @ J_b.T
        informations.append(np.linalg.inv(0.5 * (cov + cov.T)))
    heading_weights = np.array([info[0, 0] for info in informations])
    yaw = float(
        np.arctan2(
            np.sum(heading_weights * np.sin(headings)), np.sum(heading_weights * np.cos(headings))
        )
    )
    t = np.mean([p.a_from_target[:3, 3] - _rot_z(yaw) @ p.b_from_target[:3, 3] for p in pairs], 0)
    hessian = np.eye(4)
    for _ in range(max_iterations):
        hessian = np.zeros((4, 4))
        gradient = np.zeros(4)
        Rz = _rot_z(yaw)
        dRz = np.array(
            [[-np.sin(yaw), -np.cos(yaw), 0.0], [np.cos(yaw), -np.sin(yaw), 0.0], [0, 0, 0]]
        )
        for pair, heading, info in zip(pairs, headings, informations, strict=True):
            p_b = pair.b_from_target[:3, 3]
            r = np.concatenate(([_wrap(heading - yaw)], pair.a_from_target[:3, 3] - Rz @ p_b - t))
            J = np.zeros((4, 4))
            J[0, 0] = -1.0
            J[1:, 0] = -dRz @ p_b
            J[1:, 1:] = -np.eye(3)
            hessian += J.T @ info @ J
            gradient += J.T @ info @ r
        step = -np.linalg.solve(hessian, gradient)
        yaw = float(_wrap(yaw + step[0]))
        t = t + step[1:]
        if np.linalg.norm(step) < 1e-12:
            break
    cov4 = np.linalg.inv(hessian)
    covariance = np.zeros((6, 6))
    covariance[2, 2] = cov4[0, 0]
    covariance[2, 3:] = cov4[0, 1:]
    covariance[3:, 2] = cov4[1:, 0]
    covariance[3:, 3:] = cov4[1:, 1:]
    pose = make_pose(_rot_z(yaw), t)
    return Alignment(
        a_from_b=pose,
        covariance=0.5 * (covariance + covariance.T),
        dof=4,
        target_names=tuple(p.name for p in pairs),
        residuals_rad_m=_residuals(pairs, pose),
    )


def align_sessions(
    pairs: Sequence[TargetPair], *, dof: Dof, tilt_prior_sigma_rad: float | None = None
) -> Alignment:
    """`align_4dof` or `align_6dof` (with the tilt prior, if any) by `dof`.

    Raises ValueError for another dof.
    """
    if dof == 4:
        return align_4dof(pairs)
    if dof == 6:
        return align_6dof(pairs, tilt_prior_sigma_rad=tilt_prior_sigma_rad)
    raise ValueError(f"align_sessions: dof must be 4 or 6, got {dof!r}")


@dataclass(frozen=True)
class TargetEstimate:
    """A target's pose in a session frame, `T_S_m` (4, 4), with its 6x6 covariance."""

    pose: FloatArray
    covariance: FloatArray


@dataclass(frozen=True)
class Placement:
    """Where a session sits in the common frame W.

    world_from_session: `T_W_S` (4, 4); covariance (6, 6); alignment: how it was
    found (None for the reference); diagnostic_6dof: the 6-DoF fit when the
    alignment is 4-DoF; via: the sessions whose targets placed it.
    """

    world_from_session: FloatArray
    covariance: FloatArray
    alignment: Alignment | None = None
    diagnostic_6dof: Alignment | None = None
    via: tuple[str, ...] = ()


def place_sessions(
    targets: Mapping[str, Mapping[str, TargetEstimate]],
    reference: str,
    *,
    dof: Dof,
    reference_covariance: FloatArray | None = None,
    tilt_prior_sigma_rad: float | None = None,
) -> dict[str, Placement]:
    """Put sessions into the frame of `reference` through the targets they share.

    targets: session name -> target name -> its estimate in that session's frame.
    Returns the placed sessions only (those connected to the reference through
    shared targets). A target's world pose, used to place the next session, is
    the information-weighted fusion over the sessions already placed.
    tilt_prior_sigma_rad: with dof 6, each session's gravity-alignment error (rad,
    1 sigma per axis) for the prior on its roll and pitch in W (`align_6dof`).
    Raises ValueError when `reference` is not among the sessions.
    """
    if reference not in targets:
        raise ValueError(f"place_sessions: reference {reference!r} not among {sorted(targets)}")
    placed: dict[str, Placement] = {
        reference: Placement(
            world_from_session=np.eye(4),
            covariance=np.zeros((6, 6)) if reference_covariance is None else reference_covariance,
        )
    }
    while True:
        best: tuple[int, str] | None = None
        for session in sorted(targets):
            if session in placed:
                continue
            shared = [m for m in targets[session] if any(m in targets[p] for p in placed)]
            if shared and (best is None or len(shared) > best[0]):
                best = (len(shared), session)
        if best is None:
            return placed
        session = best[1]
        pairs = []
        via: set[str] = set()
        for name in sorted(targets[session]):
            world_estimates = []
            for other, placement in placed.items():
                if name in targets[other]:
                    estimate = targets[other][name]
                    # The placement's own uncertainty carries along a chain of sessions.
                    world_estimates.append(
                        compose_with_covariance(
                            placement.world_from_session,
                            placement.covariance,
                            estimate.pose,
                            estimate.covariance,
                        )
                    )
                    via.add(other)
            if not world_estimates:
                continue
            if len(world_estimates) == 1:
                world_pose, world_cov = world_estimates[0]
            else:
                world_pose, world_cov = fuse_pose_estimates(
                    np.array([e[0] for e in world_estimates]),
                    np.array([e[1] for e in world_estimates]),
                )
            estimate = targets[session][name]
            pairs.append(
                TargetPair(name, world_pose, world_cov, estimate.pose, estimate.covariance)
            )
        alignment = align_sessions(pairs, dof=dof, tilt_prior_sigma_rad=tilt_prior_sigma_rad)
        placed[session] = Placement(
            world_from_session=alignment.a_from_b,
            covariance=alignment.covariance,
            alignment=alignment,
            diagnostic_6dof=align_6dof(pairs) if dof == 4 else None,
            via=tuple(sorted(via)),
        )


def tilt_between_rad(a: FloatArray, b: FloatArray) -> float:
    """Angle (rad) between the z axes of two poses' rotations (a 6-DoF fit's tilt vs 4-DoF)."""
    za = a[:3, 2]
    zb = b[:3, 2]
    return float(np.arccos(np.clip(za @ zb, -1.0, 1.0)))


def rotation_difference_rad(a: FloatArray, b: FloatArray) -> float:
    """Angle (rad) of the rotation between two poses."""
    return float(np.linalg.norm(so3_log(a[:3, :3].T @ b[:3, :3])))
