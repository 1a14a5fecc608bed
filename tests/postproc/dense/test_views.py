"""Neighbour choice (overlap, triangulation angle, sideways motion) and the choice of
reference views."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from postproc.dense.views import (
    NeighbourOptions,
    ViewSelectionOptions,
    pair_score,
    select_neighbours,
    select_reference_views,
    view_overlap,
)

K = np.array([[200.0, 0.0, 160.0], [0.0, 200.0, 120.0], [0.0, 0.0, 1.0]])
SIZE = (320, 240)


def cam_from_world_at(
    x: float, *, y: float = 0.0, z: float = 0.0, yaw_deg: float = 0.0
) -> np.ndarray:
    """A camera at (x, y, z) looking along +z (turned by yaw about the y axis)."""
    a = np.radians(yaw_deg)
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    world_from_cam[:3, 3] = (x, y, z)
    return np.linalg.inv(world_from_cam)


def test_overlap_of_shifted_views() -> None:
    ref = cam_from_world_at(0.0)
    assert view_overlap(K, SIZE, np.linalg.inv(ref), 3.0, K, SIZE, ref) == pytest.approx(1.0)
    # Shifted by half the footprint (3 m * 320/200 = 4.8 m wide): about half overlaps.
    half = view_overlap(K, SIZE, np.linalg.inv(ref), 3.0, K, SIZE, cam_from_world_at(2.4))
    assert 0.35 < half < 0.65
    away = cam_from_world_at(0.0, yaw_deg=180.0)
    assert view_overlap(K, SIZE, np.linalg.inv(ref), 3.0, K, SIZE, away) == 0.0


def test_row_of_cameras_prefers_the_best_angle() -> None:
    # Cameras every 0.1 m along x, scene 3 m away: 10 degrees is about 0.52 m of baseline.
    poses = [cam_from_world_at(0.1 * k) for k in range(21)]
    options = NeighbourOptions(max_neighbours=4)
    chosen = select_neighbours([K] * 21, [SIZE] * 21, poses, [3.0] * 21, options)
    assert len(chosen[10]) == 4
    baselines = [abs(j - 10) * 0.1 for j in chosen[10]]
    assert baselines[0] == pytest.approx(0.5, abs=0.11)
    # 2 degrees at 3 m is 0.105 m: the immediate neighbours are too close.
    assert 9 not in chosen[10] and 11 not in chosen[10]
    assert all(j != 10 for j in chosen[10])


def test_forward_motion_and_tiny_baselines_are_rejected() -> None:
    options = NeighbourOptions()
    common: dict[str, Any] = {"centre_ref_m": np.zeros(3), "axis_ref": np.array([0.0, 0.0, 1.0]),
              "depth_ref_m": 3.0, "overlap": 1.0, "options": options}  # fmt: skip
    assert pair_score(centre_src_m=np.array([0.0, 0.0, 0.5]), **common) == 0.0  # forward
    assert pair_score(centre_src_m=np.array([0.05, 0.0, 0.0]), **common) == 0.0  # < 2 deg
    assert pair_score(centre_src_m=np.array([3.0, 0.0, 0.0]), **common) == 0.0  # > 30 deg
    sideways = pair_score(centre_src_m=np.array([0.5, 0.0, 0.0]), **common)
    assert 0.9 < sideways <= 1.0
    low_overlap = dict(common, overlap=0.1)
    assert pair_score(centre_src_m=np.array([0.5, 0.0, 0.0]), **low_overlap) == 0.0


def test_no_neighbours_for_a_lonely_camera() -> None:
    poses = [cam_from_world_at(0.0), cam_from_world_at(50.0)]
    assert select_neighbours([K, K], [SIZE, SIZE], poses, [3.0, 3.0]) == [[], []]


def test_far_partners_have_longer_baselines() -> None:
    # Scene 3 m away at the median, 9 m at the far end: the far partners are chosen for a
    # good angle at 9 m (10 degrees is about 1.6 m), beyond the near ones.
    poses = [cam_from_world_at(0.1 * k) for k in range(41)]
    options = NeighbourOptions(max_neighbours=2, far_neighbours=2, max_angle_deg=40.0)
    near_only = select_neighbours([K] * 41, [SIZE] * 41, poses, [3.0] * 41, options)
    both = select_neighbours(
        [K] * 41, [SIZE] * 41, poses, [3.0] * 41, options, far_depths_m=[9.0] * 41
    )
    assert both[20][:2] == near_only[20] and len(both[20]) == 4
    near_baselines = [abs(j - 20) * 0.1 for j in both[20][:2]]
    far_baselines = [abs(j - 20) * 0.1 for j in both[20][2:]]
    assert min(far_baselines) > max(near_baselines)
    assert len(set(both[20])) == 4 and 20 not in both[20]
    none = NeighbourOptions(max_neighbours=2, far_neighbours=0, max_angle_deg=40.0)
    assert (
        select_neighbours([K] * 41, [SIZE] * 41, poses, [3.0] * 41, none, far_depths_m=[9.0] * 41)
        == near_only
    )


def test_references_follow_the_baseline_not_the_keyframe_count() -> None:
    # A row of keyframes every 0.1 m, scene 3 m away: 0.3 x 3 m = 0.9 m between references.
    poses = [cam_from_world_at(0.1 * k) for k in range(31)]
    options = ViewSelectionOptions(min_baseline_rel=0.3, min_rotation_deg=20.0)
    chosen = select_reference_views(poses, [3.0] * 31, options)
    assert chosen == [0, 9, 18, 27]
    # Ten times the keyframes over the same path: the same references' spacing.
    dense = [cam_from_world_at(0.01 * k) for k in range(301)]
    assert select_reference_views(dense, [3.0] * 301, options) == [0, 90, 180, 270]
    # Twice the scene depth, twice the spacing.
    assert select_reference_views(poses, [6.0] * 31, options) == [0, 18]
    # Disabled: every keyframe.
    assert select_reference_views(poses, [3.0] * 31, ViewSelectionOptions(enabled=False)) == (
        list(range(31))
    )
    assert select_reference_views([], [], options) == []


def test_swimming_back_adds_no_references() -> None:
    # Along a wall and back over the same path: the way back is already covered.
    there = [cam_from_world_at(0.1 * k) for k in range(31)]
    back = [cam_from_world_at(0.1 * k + 0.05) for k in range(30, -1, -1)]
    chosen = select_reference_views(there + back, [3.0] * 62, ViewSelectionOptions())
    assert chosen == select_reference_views(there, [3.0] * 31, ViewSelectionOptions())
    # In a given order (the way back first), the references come from the way back.
    order = list(range(31, 62)) + list(range(31))
    from_back = select_reference_views(there + back, [3.0] * 62, order=order)
    # (as many, give or take the one that the grid's rounding moves to either end)
    assert all(k >= 31 for k in from_back) and abs(len(from_back) - len(chosen)) <= 1


def test_turning_on_the_spot_gives_new_references() -> None:
    # Turning in place, 7 degrees a keyframe: no baseline, but every 21 degrees (beyond the
    # 20 asked) the view turned far enough from the last reference.
    poses = [cam_from_world_at(0.0, yaw_deg=7.0 * k) for k in range(19)]
    options = ViewSelectionOptions(min_baseline_rel=0.3, min_rotation_deg=20.0)
    assert select_reference_views(poses, [3.0] * 19, options) == [0, 3, 6, 9, 12, 15, 18]


def test_keyframes_without_depth_are_kept() -> None:
    poses = [cam_from_world_at(0.01 * k) for k in range(4)]
    depths = [3.0, float("nan"), 0.0, 3.0]
    assert select_reference_views(poses, depths) == [0, 1, 2]
