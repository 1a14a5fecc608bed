"""Merging without targets: through the structure two dives share, and never without it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from postproc.merge.natural import match_sessions
from postproc.merge.places import PlaceOptions
from postproc.merge.stage import MergeOptions, _load_sessions, run
from shared.errors import InputError
from shared.geometry import invert_pose, make_pose, pose_difference, so3_exp
from tests.postproc.merge import natural_scene

REPO = Path(__file__).resolve().parents[3]
# Session frames in the world: gravity-aligned (yaw and an offset), as VI-SLAM defines them.
WORLD_FROM = {
    "a": make_pose(so3_exp([0.0, 0.0, 0.3]), [-3.0, 2.0, -1.5]),
    "b": make_pose(so3_exp([0.0, 0.0, -1.1]), [2.0, 2.5, -1.5]),
    "c": make_pose(so3_exp([0.0, 0.0, 2.0]), [1.0, 2.0, -1.5]),
}


@pytest.fixture(scope="module")
def dives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """a and b film the same wreck (textures 1, 2) from different routes; c another one."""
    root = tmp_path_factory.mktemp("natural")
    return {
        "a": natural_scene.write_session(
            root / "a",
            texture_seeds=(1, 2),
            xs_m=np.linspace(-3, 3, 10),
            distance_m=2.0,
            world_from_session=WORLD_FROM["a"],
            seed=1,
        ),
        "b": natural_scene.write_session(
            root / "b",
            texture_seeds=(1, 2),
            xs_m=np.linspace(2, -2, 9),
            distance_m=2.4,
            world_from_session=WORLD_FROM["b"],
            seed=2,
        ),
        "c": natural_scene.write_session(
            root / "c",
            texture_seeds=(7, 8),
            xs_m=np.linspace(-3, 3, 10),
            distance_m=2.0,
            world_from_session=WORLD_FROM["c"],
            seed=3,
        ),
    }


def _options() -> MergeOptions:
    return MergeOptions(plot=False, places=PlaceOptions(vocabulary_words=500))


def test_sessions_sharing_structure_merge_and_others_are_refused(dives, tmp_path):
    out = tmp_path / "out"
    document = json.loads(run(_options(), list(dives.values()), [], out).read_text())
    assert document["estimator"] == "joint"
    b = document["sessions"]["b"]
    assert b["placed"] and b["via"] == ["a"]
    expected = invert_pose(WORLD_FROM["a"]) @ WORLD_FROM["b"]
    rotation, translation = pose_difference(np.array(b["T_W_S"]), expected)
    assert np.rad2deg(rotation) < 0.5 and translation < 0.04
    # The reported uncertainty is of the size of the error, not far below it.
    assert np.rad2deg(rotation) < 4 * b["sigma_rotation_deg"]
    assert translation < 4 * b["sigma_translation_m"]
    pairs = {tuple(p["sessions"]): p for p in document["pairs"]}
    assert pairs["a", "b"]["mergeable"] and pairs["a", "b"]["consistent"] >= 3
    # c filmed another wreck: candidates come up (some word overlap always does), none
    # survives verification, so it is reported, not merged.
    for pair in (("a", "c"), ("b", "c")):
        evidence = pairs[pair]
        assert evidence["candidates"] > 0 and not evidence["mergeable"]
        assert evidence["consistent"] < 3 and "needed" in evidence["reason"]
    c = document["sessions"]["c"]
    assert c["placed"] is False and "evidence" in c["reason"]
    assert not (out / "c").exists()
    [constraint] = document["constraints"]
    assert constraint["kind"] == "features" and constraint["label"] == "a-b"
    assert constraint["weight"] == 1.0 and constraint["whitened_norm"] < 4.1


def test_cli_merges_without_targets(dives, tmp_path):
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    command = [sys.executable, "-m", "postproc.cli", "merge", str(dives["a"]), str(dives["b"])]
    command += ["--out", str(tmp_path / "out"), "--no-plot"]
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    document = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert document["sessions"]["b"]["placed"]
    refused = subprocess.run(
        [*command[:-3], "--out", str(tmp_path / "x"), "--no-natural-features"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert refused.returncode == 1 and "no target YAML" in refused.stderr


def _dives(tmp_path, specs, **noise):
    """Two sessions of one wreck (textures 1, 2): (name, xs, distance, seed, T_W_S) each."""
    return [
        natural_scene.write_session(
            tmp_path / name,
            texture_seeds=(1, 2),
            xs_m=xs,
            distance_m=distance,
            world_from_session=world_from_session,
            seed=seed,
            **noise,
        )
        for name, xs, distance, seed, world_from_session in specs
    ]


def _pair_refined_and_not(folders, *, tilt_variance_rad2):
    """The a-b pair's evidence without (False) and with (True) `refine_places`."""
    options = _options()
    sessions = _load_sessions(options, folders)
    out = {}
    for refine in (False, True):
        [pair] = match_sessions(
            replace(options.places, refine_places=refine),
            sessions,
            drift_rates={"a": np.full(6, 1e-10), "b": np.full(6, 1e-10)},
            tilt_variance_rad2=tilt_variance_rad2,
        )
        assert pair.mergeable and pair.poses is not None and pair.a_from_b is not None, pair.reason
        out[refine] = pair
    return out


def test_refined_places_take_the_keyframes_own_errors_out(tmp_path):
    # Two dives of one wreck whose SLAM poses carry 0.3 deg and 1 cm of error per
    # keyframe: a map triangulated from two of them is warped, and the query's own
    # error enters its PnP whole. The adjustment of both neighbourhoods removes most.
    folders = _dives(
        tmp_path,
        (
            ("a", np.linspace(-3, 3, 13), 2.0, 11, WORLD_FROM["a"]),
            ("b", np.linspace(2, -2, 11), 2.4, 12, WORLD_FROM["b"]),
        ),
        jitter_rotation_deg=0.3,
        jitter_translation_m=0.01,
    )
    expected = invert_pose(WORLD_FROM["a"]) @ WORLD_FROM["b"]
    errors = {}
    for refine, pair in _pair_refined_and_not(
        folders, tilt_variance_rad2=np.deg2rad(0.1) ** 2
    ).items():
        yaws = [
            np.rad2deg(np.arctan2(*(p[:3, :3] @ expected[:3, :3].T)[[1, 0], 0])) for p in pair.poses
        ]
        errors[refine] = float(np.sqrt(np.mean(np.square(yaws))))
    assert errors[True] < 0.6 * errors[False], errors


def test_refined_places_measure_the_relative_tilt_gravity_left(tmp_path):
    # b's gravity alignment is off by 0.5 deg of roll and pitch: the adjustments see it
    # in the images where the fit with the tilt held at zero cannot.
    tilted = WORLD_FROM["b"] @ make_pose(
        so3_exp([np.deg2rad(0.5), np.deg2rad(-0.5), 0.0]), [0, 0, 0]
    )
    folders = _dives(
        tmp_path,
        (
            ("a", np.linspace(-3, 3, 10), 2.0, 1, WORLD_FROM["a"]),
            ("b", np.linspace(2, -2, 9), 2.4, 2, tilted),
        ),
    )
    expected = invert_pose(WORLD_FROM["a"]) @ tilted
    errors = {
        refine: np.rad2deg(pose_difference(pair.a_from_b, expected)[0])
        for refine, pair in _pair_refined_and_not(folders, tilt_variance_rad2=1.0).items()
    }
    assert errors[False] > 0.5
    assert errors[True] < 0.2


def test_an_unreadable_keyframe_is_refused_naming_its_file(dives, tmp_path):
    # Feature extraction runs over a thread pool: the worker's error still reaches the
    # caller, with the file's name.
    broken = tmp_path / "a"
    shutil.copytree(dives["a"], broken)
    image = sorted((broken / "keyframes").glob("*.png"))[3]
    image.write_bytes(b"not a PNG")
    with pytest.raises(InputError, match=f"{image.name}: cannot read the keyframe image"):
        run(_options(), [broken, dives["b"]], [], tmp_path / "out")
