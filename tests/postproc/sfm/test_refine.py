"""Refinement helpers: session placement fit, gap filling, option checks, the mapper choice."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from postproc.sfm.database import KeyframeSet
from postproc.sfm.features import FeatureOptions
from postproc.sfm.refine import (
    RefineOptions,
    fit_world_from_session,
    function_tolerance,
    refine,
    shape_moves_m,
)
from postproc.sfm.stage import SfmOptions, _fill_missing, run
from shared.errors import StageError
from shared.formats.tum import read_tum
from shared.geometry import make_pose, so3_exp
from shared.trajectory import ate
from sim.slam_like import SlamLikeSession, write_merge_like


def test_fit_world_from_session_recovers_a_rigid_transform() -> None:
    rng = np.random.default_rng(2)
    local = make_pose(so3_exp(rng.normal(size=(20, 3))), rng.normal(scale=3.0, size=(20, 3)))
    truth = make_pose(so3_exp([0.0, 0.0, 1.2]), [4.0, -2.0, -11.0])
    world = truth @ local
    world[:, :3, 3] += rng.normal(scale=0.01, size=(20, 3))
    estimate, rms = fit_world_from_session(local, world)
    np.testing.assert_allclose(estimate, truth, atol=0.02)
    assert 0.005 < rms < 0.03


def test_shape_moves_ignore_a_common_similarity() -> None:
    rng = np.random.default_rng(3)
    before = make_pose(so3_exp(rng.normal(size=(30, 3))), rng.normal(scale=4.0, size=(30, 3)))
    similarity = make_pose(so3_exp([0.1, -0.2, 0.3]), [2.0, -1.0, 0.5])
    after = similarity @ before
    after[:, :3, 3] *= 1.1  # and a scale about the origin
    names = [f"k{i:02d}" for i in range(30)]  # in sorted order
    moved = dict(zip(names, after, strict=True))
    np.testing.assert_allclose(
        shape_moves_m(dict(zip(names, before, strict=True)), moved), 0.0, atol=1e-9
    )
    moved["k07"] = moved["k07"].copy()
    moved["k07"][:3, 3] += [0.0, 0.0, 0.3]  # one camera bends the path
    shape = shape_moves_m(dict(zip(names, before, strict=True)), moved)
    assert np.argmax(shape) == 7 and 0.2 < shape[7] < 0.3


def test_function_tolerance_is_a_chi2_change_per_residual() -> None:
    # 1000 observations are 2000 residuals: a chi-square change of 10 is 10 / 2000 of the cost.
    assert function_tolerance(0.0, 10.0, 1000) == pytest.approx(0.005)
    # Twice the observations, half the relative change: the same change of chi-square.
    assert function_tolerance(0.0, 10.0, 2000) == pytest.approx(0.0025)
    assert function_tolerance(1e-2, 10.0, 1000) == pytest.approx(1e-2)  # never below the floor
    assert function_tolerance(1e-6, None, 1000) == 1e-6  # off: the floor alone
    assert function_tolerance(0.0, 10.0, 0) == 0.0  # nothing to adjust


def test_fill_missing_carries_the_nearest_correction() -> None:
    prior = make_pose(np.broadcast_to(np.eye(3), (4, 3, 3)), np.arange(12.0).reshape(4, 3))
    keyframes = KeyframeSet(
        names=["a/1.png", "a/2.png", "a/3.png", "b/1.png"],
        sources=[Path("x")] * 4,
        session=np.array([0, 0, 0, 1]),
        camera=np.zeros(4, dtype=np.int64),
        stamps_ns=np.array([1, 2, 3, 1]),
        world_from_cam=prior,
        placed=np.ones(4, bool),
        prior_sigma_m=np.ones(4),
    )
    shift = make_pose(np.eye(3), [0.0, 0.0, 0.5])
    refined = {"a/1.png": shift @ prior[0], "a/2.png": shift @ prior[1]}
    out, in_model = _fill_missing(keyframes, refined, prior)
    np.testing.assert_array_equal(in_model, [True, True, False, False])
    np.testing.assert_allclose(out[2], shift @ prior[2])  # corrected like its neighbour
    np.testing.assert_allclose(out[3], prior[3])  # nothing in its session: the prior


@pytest.mark.parametrize(
    "kwargs",
    [
        {"mapper": "magic"},
        {"max_rounds": 0},
        {"triangulation_max_angle_deg": 0.0},
        {"rebuilt_max_angle_deg": -1.0},
        {"rebuilt_merge_max_reproj_error_px": 0.0},
        {"first_pass_converged_change_m": 0.0},
        {"ba_max_direct_sparse_images": -1},
        {"ba_max_track_length": 2},
        {"ba_trust_region": "newton"},
        {"ba_chi2_tolerance": 0.0},
        {"ba_chi2_tolerance": -1.0},
        {"first_pass_ba_chi2_tolerance": 0.0},
    ],
)
def test_refine_options_reject_bad_values(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        RefineOptions(**kwargs)  # type: ignore[arg-type]


def test_refine_needs_a_placed_session(tmp_path: Path) -> None:
    keyframes = KeyframeSet(
        names=["a/1.png"],
        sources=[Path("x")],
        session=np.zeros(1, dtype=np.int64),
        camera=np.zeros(1, dtype=np.int64),
        stamps_ns=np.ones(1, dtype=np.int64),
        world_from_cam=np.eye(4)[None],
        placed=np.zeros(1, bool),
        prior_sigma_m=np.ones(1),
    )
    with pytest.raises(StageError, match="no session has a world pose"):
        refine(tmp_path / "db", tmp_path, tmp_path, keyframes, RefineOptions())


@pytest.mark.slow
def test_incremental_mapper_with_priors_keeps_the_world_frame(
    slam_survey: list[SlamLikeSession], tmp_path: Path
) -> None:
    merge = write_merge_like(tmp_path / "merge", slam_survey, placed=[True, True])
    options = SfmOptions(
        features=FeatureOptions(max_num_features=512, num_threads=2),
        refine=RefineOptions(mapper="incremental", num_threads=2),
    )
    run(options, [merge], tmp_path / "sfm")
    stats = json.loads((tmp_path / "sfm" / "stats.json").read_text())
    assert stats["mapper"] == "incremental"
    for session in slam_survey:
        refined = read_tum(tmp_path / "sfm" / "sessions" / session.folder.name / "keyframes.tum")
        prior = session.estimate.transformed(session.world_from_session)
        # Metric and in the world frame: no alignment needed to beat the priors' shape.
        assert (
            ate(refined, session.truth_world_from_cam, align="se3").rmse_m
            < ate(prior, session.truth_world_from_cam, align="se3").rmse_m
        )
