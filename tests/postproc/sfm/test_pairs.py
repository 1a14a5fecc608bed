"""Pair selection from prior poses: sequential, spatial (z included), loops, bridging."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from postproc.sfm.inputs import SessionInput, read_place_links
from postproc.sfm.pairs import (
    BRIDGING,
    LOOP,
    PLACE,
    SEQUENTIAL,
    SPATIAL,
    PairOptions,
    bridging_pairs,
    place_pairs,
    select_pairs,
    sequential_pairs,
    spatial_pairs,
)
from shared.folders import MergeFolder
from shared.geometry import make_pose
from shared.trajectory import Trajectory


def looking_along_y(positions: np.ndarray) -> np.ndarray:
    """Camera poses T_W_C at `positions` whose optical axis (z_C) is world +y, x_C = +x."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return make_pose(np.broadcast_to(R, (len(positions), 3, 3)), positions)


def track(n: int, *, z: float = 0.0, x0: float = 0.0, step: float = 0.2) -> np.ndarray:
    return np.column_stack((x0 + step * np.arange(n), np.zeros(n), np.full(n, z)))


def test_sequential_pairs_use_offsets_one_to_n_within_each_session() -> None:
    session = np.array([0] * 10 + [1] * 7)
    stamps = np.r_[np.arange(10), np.arange(7)].astype(np.int64) * 500_000_000
    pairs = sequential_pairs(session, stamps, 3)
    offsets = pairs.pairs[:, 1] - pairs.pairs[:, 0]
    assert set(offsets.tolist()) == {1, 2, 3}
    assert np.all(session[pairs.pairs[:, 0]] == session[pairs.pairs[:, 1]])
    # (n - 1) + (n - 2) + (n - 3) pairs per session: no quadratic offsets (4, 8, ...).
    assert len(pairs) == (9 + 8 + 7) + (6 + 5 + 4)
    assert np.all(pairs.kind == SEQUENTIAL)


def test_sequential_pairs_follow_time_not_list_order() -> None:
    session = np.zeros(4, dtype=np.int64)
    stamps = np.array([30, 10, 40, 20], dtype=np.int64)
    pairs = sequential_pairs(session, stamps, 1)
    assert {tuple(p) for p in pairs.pairs.tolist()} == {(1, 3), (0, 3), (0, 2)}


def test_spatial_pairs_join_sessions_that_view_the_same_place() -> None:
    a = looking_along_y(track(20))
    b = looking_along_y(track(20, z=0.1))  # the same stretch, 10 cm higher
    poses = np.concatenate((a, b))
    session = np.r_[np.zeros(20), np.ones(20)].astype(np.int64)
    stamps = np.r_[np.arange(20), np.arange(20)].astype(np.int64)
    pairs = select_pairs(poses, session, stamps, np.ones(40, bool), PairOptions())
    spatial = pairs.pairs[pairs.kind == SPATIAL]
    assert len(spatial) > 0
    assert np.all(session[spatial[:, 0]] != session[spatial[:, 1]])
    assert np.all(np.abs(spatial[:, 0] - (spatial[:, 1] - 20)) <= 8)


def test_spatial_pairs_respect_z() -> None:
    # Same x and y, 5 m apart in depth: COLMAP's default spatial matcher (x, y only) would
    # pair them; they see different parts of the wreck.
    a = looking_along_y(track(20))
    b = looking_along_y(track(20, z=-5.0))
    poses = np.concatenate((a, b))
    session = np.r_[np.zeros(20), np.ones(20)].astype(np.int64)
    stamps = np.r_[np.arange(20), np.arange(20)].astype(np.int64)
    pairs = select_pairs(poses, session, stamps, np.ones(40, bool), PairOptions())
    assert pairs.counts()["spatial"] == 0


def test_spatial_pairs_reject_opposite_view_directions() -> None:
    a = looking_along_y(track(10))
    b = looking_along_y(track(10))
    flip = make_pose(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))
    b = b @ flip  # same centres, looking along -y
    options = PairOptions(
        view_distance_m=0.0,
        spatial_radius_m=2.0,
        max_view_angle_deg=60.0,
        loop_min_separation_s=0.0,
    )
    poses = np.concatenate((a, b))
    session = np.r_[np.zeros(10), np.ones(10)].astype(np.int64)
    stamps = np.r_[np.arange(10), np.arange(10)].astype(np.int64)
    pairs = spatial_pairs(poses, session, stamps, options)
    assert len(pairs) > 0  # loops within each session, same direction
    assert np.all(session[pairs.pairs[:, 0]] == session[pairs.pairs[:, 1]])


def test_loop_candidates_found_when_a_session_returns() -> None:
    out = track(30)
    back = out[::-1] + np.array([0.0, 0.05, 0.0])
    poses = looking_along_y(np.concatenate((out, back)))
    session = np.zeros(60, dtype=np.int64)
    stamps = np.arange(60, dtype=np.int64) * 500_000_000  # 2 Hz keyframes
    options = PairOptions(sequential_neighbours=4, loop_min_separation_s=5.0)
    pairs = select_pairs(poses, session, stamps, np.ones(60, bool), options)
    loops = pairs.pairs[pairs.kind == LOOP]
    assert len(loops) > 20
    assert np.all(np.abs(loops[:, 1] - loops[:, 0]) > options.sequential_neighbours)
    assert np.all(np.abs(loops[:, 1] - loops[:, 0]) >= 10)  # 5 s at 2 Hz


def test_pair_count_grows_linearly() -> None:
    rng = np.random.default_rng(3)
    counts = []
    for n in (800, 3200):
        # A zigzag survey over the same area, 4x denser the second time.
        t = np.linspace(0.0, 1.0, n)
        positions = np.column_stack((10 * np.sin(2 * np.pi * 4 * t), 10 * t, -10 + 0 * t))
        positions += rng.normal(scale=0.02, size=positions.shape)
        poses = looking_along_y(positions)
        session = (np.arange(n) >= n // 2).astype(np.int64)
        stamps = np.arange(n, dtype=np.int64) * round(600e9 / n)  # a 10 min survey
        options = PairOptions()
        pairs = select_pairs(poses, session, stamps, np.ones(n, bool), options)
        assert len(pairs) <= n * (options.sequential_neighbours + options.spatial_neighbours)
        counts.append(len(pairs))
    assert counts[1] / counts[0] < 4.4  # 4x the keyframes, about 4x the pairs


def test_bridging_pairs_stay_within_budget_and_span_both_sets() -> None:
    unplaced = np.arange(100, 160)
    placed = np.arange(0, 100)
    pairs = bridging_pairs(unplaced, placed, 150)
    assert 0 < len(pairs) <= 150
    assert np.all(pairs.kind == BRIDGING)
    assert set(pairs.pairs[:, 1].tolist()) <= set(unplaced.tolist())
    assert set(pairs.pairs[:, 0].tolist()) <= set(placed.tolist())
    # Spread over the whole unplaced session, not just its start.
    assert pairs.pairs[:, 1].max() - pairs.pairs[:, 1].min() > 50


def test_unplaced_sessions_get_bridging_but_no_spatial_pairs() -> None:
    a = looking_along_y(track(20))
    b = looking_along_y(track(20))  # would overlap, but its frame is unknown
    poses = np.concatenate((a, b))
    session = np.r_[np.zeros(20), np.ones(20)].astype(np.int64)
    stamps = np.r_[np.arange(20), np.arange(20)].astype(np.int64)
    placed = session == 0
    pairs = select_pairs(poses, session, stamps, placed, PairOptions(max_bridging_pairs=50))
    counts = pairs.counts()
    assert counts["spatial"] == 0
    assert 0 < counts["bridging"] <= 50


def test_merge_place_pairs_are_matched_where_the_priors_see_no_overlap(tmp_path) -> None:
    # The merge verified keyframes 3 and 15 of dive1 against 10 and 2 of dive2; the
    # priors put the dives 50 m apart, so no spatial pair would join them.
    transforms = {
        "sessions": {},
        "pairs": [
            {
                "sessions": ["dive1", "dive2"],
                "mergeable": True,
                "consistent_stamps_ns": [[10, 3], [2, 15], [99, 4]],
            },
            {"sessions": ["dive1", "dive3"], "mergeable": False, "consistent_stamps_ns": [[1, 1]]},
        ],
    }
    merge = MergeFolder(tmp_path / "merge")
    merge.path.mkdir()
    merge.transforms.write_text(json.dumps(transforms))
    links = merge.read_place_pairs()
    assert links == [
        ("dive1", 3, "dive2", 10),
        ("dive1", 15, "dive2", 2),
        ("dive1", 4, "dive2", 99),
    ]
    poses = np.concatenate((looking_along_y(track(20)), looking_along_y(track(20, x0=50.0))))
    session = np.r_[np.zeros(20), np.ones(20)].astype(np.int64)
    stamps = np.r_[np.arange(20), np.arange(20)].astype(np.int64)
    places = place_pairs(session, stamps, ["dive1", "dive2"], links)
    # Stamp 99 is no keyframe of dive2: skipped.
    assert places.pairs.tolist() == [[3, 30], [15, 22]] and np.all(places.kind == PLACE)
    placed = np.ones(40, dtype=bool)
    without = select_pairs(poses, session, stamps, placed, PairOptions())
    assert without.counts()["spatial"] == 0 and without.counts()["place"] == 0
    pairs = select_pairs(poses, session, stamps, placed, PairOptions(), places=places)
    assert pairs.counts()["place"] == 2 and len(pairs) == len(without) + 2
    # The SfM stage's session names may differ from the merge's (folder names).
    inputs = [
        SessionInput(
            name=name,
            folder=tmp_path / folder,
            keyframes=Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4))),
            images=[],
            camera=None,  # type: ignore[arg-type]
        )
        for name, folder in (("a_dive1", "dive1"), ("b_dive2", "dive2"))
    ]
    assert read_place_links([tmp_path / "dive1", merge.path], inputs) == [
        ("a_dive1", a, "b_dive2", b) for _, a, _, b in links
    ]
    assert read_place_links([tmp_path / "dive1"], inputs) == []
    transforms["pairs"] = []
    merge.transforms.write_text(json.dumps(transforms))
    assert merge.read_place_pairs() == []


@pytest.mark.parametrize(
    "kwargs",
    [
        {"sequential_neighbours": -1},
        {"spatial_radius_m": 0.0},
        {"max_view_angle_deg": 0.0},
        {"max_bridging_pairs": -5},
        {"loop_min_separation_s": -1.0},
    ],
)
def test_pair_options_reject_bad_values(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        PairOptions(**kwargs)  # type: ignore[arg-type]


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(min_value=2, max_value=60),
    sessions=st.integers(min_value=1, max_value=3),
    seed=st.integers(min_value=0, max_value=10_000),
)
def test_pairs_are_unique_ordered_and_bounded(n: int, sessions: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    positions = np.cumsum(rng.normal(scale=0.3, size=(n, 3)), axis=0)
    poses = looking_along_y(positions)
    session = rng.integers(0, sessions, size=n).astype(np.int64)
    stamps = np.arange(n, dtype=np.int64)
    placed = rng.random(n) < 0.8
    placed[session == session[0]] = True
    options = PairOptions(max_bridging_pairs=20)
    pairs = select_pairs(poses, session, stamps, placed, options)
    assert np.all(pairs.pairs[:, 0] < pairs.pairs[:, 1])
    assert len({tuple(p) for p in pairs.pairs.tolist()}) == len(pairs)
    assert set(pairs.kind.tolist()) <= {SEQUENTIAL, SPATIAL, LOOP, BRIDGING, PLACE}
    bound = n * (options.sequential_neighbours + 2 * options.spatial_neighbours)
    assert len(pairs) <= bound + sessions * options.max_bridging_pairs
