"""Place recognition, verification, consistency and the drift-aware pair mean."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from postproc.merge.align import tilt_vector_rad
from postproc.merge.averaging import pose_residuals
from postproc.merge.places import (
    build_vocabulary,
    candidate_clusters,
    candidate_noise,
    consistent_candidates,
    extract_features,
    pair_place_mean,
    pivot_jacobian,
    place_candidates,
    refine_yaw_translation,
    reprojection_errors,
    triangulate_views,
    with_tilt_prior,
)
from shared.geometry import invert_pose, make_pose, pose_difference, so3_exp
from tests.postproc.merge import natural_scene


def _rz(angle: float) -> np.ndarray:
    return so3_exp([0.0, 0.0, angle])


def test_refine_yaw_translation_recovers_a_gravity_aligned_transform():
    rng = np.random.default_rng(3)
    truth = make_pose(_rz(0.8), [1.5, -2.0, 0.3])
    query_in_b = make_pose(so3_exp([1.7, 0.1, 0.2]), [0.4, 0.2, -1.0])
    cam_from_a = invert_pose(truth @ query_in_b)
    points_cam = np.column_stack((rng.uniform(-1, 1, (60, 2)), rng.uniform(1.5, 4.0, 60)))
    points_a = (points_cam - cam_from_a[:3, 3]) @ cam_from_a[:3, :3]
    rays = points_cam[:, :2] / points_cam[:, 2:3]
    rays[:5] += 0.2  # gross outliers: the Huber weights keep them from pulling
    start = make_pose(so3_exp([0.02, -0.01, 0.85]), [1.4, -1.9, 0.35])
    found = refine_yaw_translation(points_a, rays, query_in_b, start)
    rotation, translation = pose_difference(found, truth)
    assert rotation < 1e-4 and translation < 1e-4
    assert np.allclose(found[:3, 2], [0, 0, 1])  # no tilt: both frames gravity-aligned
    errors = reprojection_errors(points_a, rays, invert_pose(found @ query_in_b))
    assert np.count_nonzero(errors < 1e-4) >= 55


def test_triangulate_views_and_reprojection_behind_camera():
    point = np.array([0.3, -0.2, 3.0])
    poses = [make_pose(np.eye(3), [-x, 0.0, 0.0]) for x in (0.0, 0.3, 0.6)]
    rays = np.array([(point[:2] + p[:2, 3]) / point[2] for p in poses])
    triangulated = triangulate_views(poses, rays)
    assert triangulated is not None
    assert np.allclose(triangulated, point)
    behind = reprojection_errors(np.array([[0.0, 0.0, -1.0]]), np.zeros((1, 2)), np.eye(4))
    assert np.isinf(behind[0])


def test_consistent_candidates_keep_the_agreeing_group():
    rng = np.random.default_rng(0)
    truth = make_pose(_rz(0.4), [2.0, 1.0, 0.0])
    good = [
        make_pose(
            so3_exp(rng.normal(0, 0.002, 3)) @ truth[:3, :3], truth[:3, 3] + rng.normal(0, 0.02, 3)
        )
        for _ in range(8)
    ]
    wrong = [make_pose(_rz(a), [x, -1.0, 0.0]) for a, x in ((1.5, 0.0), (-0.7, 3.0), (2.5, 5.0))]
    poses = np.array(good + wrong)
    group = consistent_candidates(
        poses, np.ones(len(poses)), rotation_rad=np.deg2rad(1.5), translation_m=0.25
    )
    assert group.tolist() == [True] * 8 + [False] * 3
    assert consistent_candidates(
        np.zeros((0, 4, 4)), np.zeros(0), rotation_rad=1, translation_m=1
    ).shape == (0,)


def _pivoted(pose: np.ndarray, yaw: float, pivot: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """`pose` moved by a yaw about `pivot` (in the parent frame) and a shift."""
    rotation = _rz(yaw)
    moved: np.ndarray = make_pose(rotation, pivot - rotation @ pivot + shift) @ pose
    return moved


def _place_candidates(rng, truth, places, per_place, *, early_drift=0.0):
    """Candidates whose errors rotate about their place (about 10 m from Sb's origin)."""
    poses, positions, times = [], [], []
    for k, place in enumerate(places):
        shared = rng.normal(0, np.deg2rad(0.15))
        for _ in range(per_place):
            yaw = shared + rng.normal(0, np.deg2rad(0.4)) + (early_drift if k else 0.0)
            poses.append(_pivoted(truth, yaw, place, rng.normal(0, 0.004, 3)))
            positions.append(place)
            times.append(30.0 * k)
    return np.array(poses), np.array(positions), np.array(times)


def _without_drift(times: np.ndarray, start: np.ndarray) -> dict[str, Any]:
    """`pair_place_mean`'s settings for sessions without drift, places 5 s apart."""
    return dict(
        rate_a=np.array([1e-12] * 6),
        rate_b=np.array([1e-12] * 6),
        clusters=candidate_clusters(times, times, gap_s=5.0),
        floor=np.array([np.deg2rad(0.01) ** 2] * 3 + [0.002**2] * 3),
        start=start,
        fixed_axes=2,
    )


def test_pair_place_mean_keeps_the_yaw_out_of_the_translation():
    truth = make_pose(_rz(0.3), [1.0, 2.0, 0.0])
    places = np.array([[9.0, 8.0, -1.0], [-6.0, 9.0, 0.5], [8.0, -7.0, 0.0], [-9.0, -5.0, -0.5]])
    rate = np.array([1e-12] * 3 + [1e-12] * 3)
    floor = np.array([np.deg2rad(0.01) ** 2] * 3 + [0.002**2] * 3)
    errors, plain_errors, d2 = [], [], []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        poses, positions, times = _place_candidates(rng, truth, places, 6)
        clusters = candidate_clusters(times, times, gap_s=5.0)
        mean = pair_place_mean(
            poses,
            times,
            times,
            positions,
            positions,
            rate_a=rate,
            rate_b=rate,
            clusters=clusters,
            floor=floor,
            start=poses[0],
            fixed_axes=2,
        )
        error = mean.a_from_b[:3, 3] - truth[:3, 3]
        errors.append(np.linalg.norm(error))
        plain_errors.append(np.linalg.norm(np.mean(poses[:, :3, 3], axis=0) - truth[:3, 3]))
        yaw = pose_difference(mean.a_from_b, truth)[0]
        free = np.r_[yaw, error]
        d2.append(free @ np.linalg.solve(mean.covariance[2:, 2:], free))
    rms = float(np.sqrt(np.mean(np.square(errors))))
    # A 0.4 deg yaw about a place 10 m away moves Sb's origin by 7 cm; modelled where it
    # pivots, the candidates' translations agree to their own millimetres.
    assert rms < 0.3 * float(np.sqrt(np.mean(np.square(plain_errors))))
    assert rms < 0.01
    # The covariance is of the size of the errors (4 free axes: yaw and translation).
    assert 1.5 < np.mean(d2) < 9.0


def test_pair_place_mean_leans_on_the_earliest_places():
    truth = make_pose(_rz(0.3), [1.0, 2.0, 0.0])
    places = np.array([[9.0, 8.0, -1.0], [-6.0, 9.0, 0.5], [8.0, -7.0, 0.0]])
    # Places after the first one were filmed after 0.5 deg of yaw drift in both sessions.
    rng = np.random.default_rng(7)
    poses, positions, times = _place_candidates(rng, truth, places, 5, early_drift=np.deg2rad(0.5))
    rate = np.array([np.deg2rad(0.05) ** 2] * 3 + [0.003**2] * 3)
    floor = np.array([np.deg2rad(0.01) ** 2] * 3 + [0.002**2] * 3)
    mean = pair_place_mean(
        poses,
        times,
        times,
        positions,
        positions,
        rate_a=rate,
        rate_b=rate,
        clusters=candidate_clusters(times, times, gap_s=5.0),
        floor=floor,
        start=poses[0],
        fixed_axes=2,
    )
    drifted = pose_difference(make_pose(_rz(0.3 + np.deg2rad(0.5)), [0.0, 0.0, 0.0]), truth)[0]
    assert pose_difference(mean.a_from_b, truth)[0] < 0.5 * drifted
    # The gains say how each session's drift reaches the mean: the drift variance they
    # imply is part of the reported covariance.
    shared = np.minimum.outer(times, times)
    implied = sum(
        np.einsum("iak,k,ij,jbk->ab", g, rate, shared, g) for g in (mean.gains_a, mean.gains_b)
    )
    assert 0.0 < implied[2, 2] <= mean.covariance[2, 2] * (1 + 1e-9)
    assert np.all(np.diag(implied)[3:] <= np.diag(mean.covariance)[3:] * (1 + 1e-9))


def test_pair_place_mean_counts_a_shared_keyframe_once():
    # One query keyframe of b matched at eight places of a: its own pose error (a yaw
    # about the camera and a shift) is in all eight candidates alike, so averaging them
    # cannot shrink it; only the PnP's own errors average out.
    truth = make_pose(_rz(0.3), [1.0, 2.0, 0.0])
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    places = np.column_stack((9 * np.cos(angles), 9 * np.sin(angles), np.zeros(8)))
    camera = np.array([0.5, -0.5, 0.0])
    rate = np.array([1e-12] * 6)
    floor = np.array([np.deg2rad(0.01) ** 2] * 3 + [0.001**2] * 3)
    keyframe = np.array([np.deg2rad(0.3) ** 2] * 3 + [0.01**2] * 3)
    d2: dict[bool, list[float]] = {False: [], True: []}
    for seed in range(30):
        rng = np.random.default_rng(seed)
        yaw, shift = rng.normal(0, np.deg2rad(0.3)), rng.normal(0, 0.01, 3)
        poses = np.array(
            [_pivoted(truth, yaw + rng.normal(0, np.deg2rad(0.02)), camera, shift) for _ in places]
        )
        poses = np.array([_pivoted(p, 0.0, camera, rng.normal(0, 0.002, 3)) for p in poses])
        times_a = np.arange(len(places), dtype=np.float64) * 10.0
        times_b = np.full(len(places), 7.0)
        for modelled in (False, True):
            mean = pair_place_mean(
                poses,
                times_a,
                times_b,
                places,
                np.tile(camera, (len(places), 1)),
                rate_a=rate,
                rate_b=rate,
                clusters=np.arange(len(places)),
                floor=floor,
                start=poses[0],
                fixed_axes=2,
                keyframe_noise_b=keyframe if modelled else None,
            )
            residual = pose_residuals(mean.a_from_b[None], truth)[0][2:]
            d2[modelled].append(residual @ np.linalg.solve(mean.covariance[2:, 2:], residual))
            if modelled:
                # The keyframe's yaw is in the mean whole: never averaged down.
                assert mean.covariance[2, 2] > 0.9 * keyframe[2]
    # Counted eight times, the keyframe's error is claimed 8x smaller than it is.
    assert np.mean(d2[False]) > 20.0
    assert np.mean(d2[True]) < 9.0


def test_pair_place_mean_drops_a_candidate_beyond_its_modelled_error():
    truth = make_pose(_rz(0.3), [1.0, 2.0, 0.0])
    places = np.array([[9.0, 8.0, -1.0], [-6.0, 9.0, 0.5], [8.0, -7.0, 0.0], [-9.0, -5.0, -0.5]])
    rng = np.random.default_rng(11)
    poses, positions, times = _place_candidates(rng, truth, places, 6)
    # A wrong candidate that the consistency box keeps: 15 cm off at its camera, within
    # the 25 cm a yaw error at 10 m makes normal at Sb's origin.
    poses[7] = _pivoted(poses[7], 0.0, positions[7], np.array([0.15, -0.05, 0.0]))
    common = _without_drift(times, poses[0])
    kept = pair_place_mean(poses, times, times, positions, positions, **common)
    tested = pair_place_mean(
        poses, times, times, positions, positions, max_whitened_sq=18.5, **common
    )
    assert kept.inliers.all()
    assert tested.inliers.tolist() == [k != 7 for k in range(len(poses))]
    assert np.all(tested.gains_a[7] == 0) and np.all(tested.gains_b[7] == 0)
    error_kept = np.linalg.norm(kept.a_from_b[:3, 3] - truth[:3, 3])
    error_tested = np.linalg.norm(tested.a_from_b[:3, 3] - truth[:3, 3])
    assert error_tested < 0.5 * error_kept


def test_candidate_noise_splits_place_and_candidate_errors():
    rng = np.random.default_rng(5)
    # 40 places 30 s apart, 10 candidates each 1 s apart: a shared error per place
    # (2 cm) plus each candidate's own (1 cm).
    times = np.concatenate([30.0 * k + np.arange(10.0) * 0.5 for k in range(40)])
    clusters = candidate_clusters(times, times + 3.0, gap_s=5.0)
    assert len(np.unique(clusters)) == 40 and clusters.tolist()[:11] == [0] * 10 + [1]
    residuals = np.repeat(rng.normal(0, 0.02, (40, 6)), 10, axis=0)
    residuals += rng.normal(0, 0.01, (400, 6))
    independent, shared = candidate_noise(residuals, clusters, floor=np.full(6, 1e-8))
    assert np.allclose(np.sqrt(independent), 0.01, rtol=0.2)
    assert np.allclose(np.sqrt(shared), 0.02, rtol=0.35)
    few = candidate_noise(residuals[:2], clusters[:2], floor=np.full(6, 1e-6))
    assert np.allclose(few[0], 1e-4) and np.allclose(few[1], 1e-4)


def test_vocabulary_scores_the_same_wreck_above_another():
    cam = natural_scene.camera()
    rng = np.random.default_rng(1)
    same_wreck = [natural_scene.texture(11), natural_scene.texture(12)]
    other_wreck = [natural_scene.texture(13), natural_scene.texture(14)]
    views = []
    for textures, x, d in (
        (same_wreck, 0.0, 2.0),
        (same_wreck, 0.3, 2.3),
        (other_wreck, 0.0, 2.0),
    ):
        pose = natural_scene.look_at_wall(x, d, 0.05)
        image = natural_scene.render(cam, pose, (textures[0], textures[1]), rng)
        views.append(extract_features(image, 800)[1])
    vocabulary = build_vocabulary(views, words=200, sample=3000, seed=0)
    vectors = vocabulary.vectors([vocabulary.assign(d) for d in views])
    candidates = place_candidates(vectors[1:2], vectors[[0, 2]], per_query=2, min_score=0.0)
    assert candidates[0][1] == 0 and candidates[0][2] > candidates[1][2]
    with pytest.raises(ValueError, match="descriptors for"):
        build_vocabulary([views[0][:10]], words=200, sample=100, seed=0)
    assert place_candidates(vectors[:0], vectors, per_query=1, min_score=0.0) == []


def test_pair_place_mean_uses_each_candidates_measured_covariance():
    # Each candidate (a refined place) knows its structure's position to millimetres
    # but its yaw only to 0.5 deg, about the filmed structure 2.5 m ahead of the query
    # camera: its covariance says so. The scatter model pivots at the cameras instead.
    truth = make_pose(_rz(0.3), [1.0, 2.0, 0.0])
    cameras = np.array([[9.0, 8.0, -1.0], [-6.0, 9.0, 0.5], [8.0, -7.0, 0.0], [-9.0, -5.0, -0.5]])
    ahead = np.array([[0.0, 2.5, 0.0], [2.5, 0.0, 0.0], [0.0, -2.5, 0.0], [-2.5, 0.0, 0.0]])
    own = np.diag([1e-12, 1e-12, np.deg2rad(0.5) ** 2, 0.003**2, 0.003**2, 0.003**2])
    with_cov: list[tuple[float, float]] = []
    without: list[tuple[float, float]] = []
    d2 = []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        poses, positions, covariances = [], [], []
        for camera, offset in zip(cameras, ahead, strict=True):
            for _ in range(3):
                pivot = camera + offset + rng.normal(0, 0.3, 3)
                yaw = rng.normal(0, np.deg2rad(0.5))
                poses.append(_pivoted(truth, yaw, pivot, rng.normal(0, 0.003, 3)))
                positions.append(camera)
                J = pivot_jacobian(truth[:3, 3] - pivot)
                covariances.append(J @ own @ J.T)
        poses_a, positions_a = np.array(poses), np.array(positions)
        times = np.repeat(30.0 * np.arange(len(cameras)), 3)
        common = _without_drift(times, poses_a[0])
        mean = pair_place_mean(
            poses_a,
            times,
            times,
            positions_a,
            positions_a,
            covariances=np.array(covariances),
            **common,
        )
        plain = pair_place_mean(poses_a, times, times, positions_a, positions_a, **common)
        for out, result in ((with_cov, mean), (without, plain)):
            rotation, translation = pose_difference(result.a_from_b, truth)
            out.append((np.rad2deg(rotation), translation))
        turn = mean.a_from_b[:3, :3] @ truth[:3, :3].T
        yaw = np.arctan2(turn[1, 0], turn[0, 0])
        free = np.r_[yaw, mean.a_from_b[:3, 3] - truth[:3, 3]]
        d2.append(free @ np.linalg.solve(mean.covariance[2:, 2:], free))
    rms_with = np.sqrt(np.mean(np.square(with_cov), axis=0))
    rms_without = np.sqrt(np.mean(np.square(without), axis=0))
    # Places 15 m apart, each placed to millimetres: the yaw between them follows.
    assert rms_with[0] < 0.7 * rms_without[0] and rms_with[1] < 0.7 * rms_without[1]
    assert rms_with[0] < 0.1
    assert 1.5 < np.mean(d2) < 9.0


def test_with_tilt_prior_adds_gravity_once_and_moves_what_the_tilt_is_tied_to():
    # The places measured a relative roll of 0.4 deg (1 sigma 0.2 deg), tied to the
    # translation along y (correlation 0.8); gravity says 0 +- 0.2 deg.
    sigma_tilt, sigma_y = np.deg2rad(0.2), 0.01
    covariance = np.diag([sigma_tilt**2, sigma_tilt**2, np.deg2rad(0.3) ** 2, 1e-4, 1e-4, 1e-4])
    covariance[0, 4] = covariance[4, 0] = 0.8 * sigma_tilt * sigma_y
    measured = make_pose(so3_exp([np.deg2rad(0.4), 0.0, 0.0]) @ _rz(0.3), [1.0, 2.0, 0.0])
    pose, fused = with_tilt_prior(measured, covariance, sigma_tilt**2)
    roll = tilt_vector_rad(pose[:3, :3])[0]
    # Equal variances: half-way, and half the variance.
    assert np.rad2deg(roll) == pytest.approx(0.2, abs=1e-3)
    assert fused[0, 0] == pytest.approx(0.5 * sigma_tilt**2, rel=1e-6)
    # y follows the roll through their correlation: 0.8 * 1 cm per sigma of roll moved.
    assert pose[1, 3] - 2.0 == pytest.approx(-0.8 * sigma_y * 1.0, rel=1e-3)
    # The yaw and the other axes are untouched; pitch stays at zero.
    assert np.arctan2(pose[1, 0], pose[0, 0]) == pytest.approx(0.3, abs=1e-5)
    assert tilt_vector_rad(pose[:3, :3])[1] == pytest.approx(0.0, abs=1e-12)
    assert fused[2, 2] == pytest.approx(covariance[2, 2])
