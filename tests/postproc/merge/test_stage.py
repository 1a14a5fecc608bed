"""The merge stage end to end on small synthetic SLAM folders, and the CLI as a subprocess."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

from postproc.merge.stage import MergeOptions, pass_labels, run, session_names
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.kalibr import write_target_yaml
from shared.errors import InputError, OutputExistsError, StageError
from shared.formats.tum import read_tum, write_tum
from shared.geometry import invert_pose, make_pose, pose_difference
from shared.trajectory import Trajectory
from sim.targets import SurveyOptions, default_camera, default_targets, make_survey

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """Three dives: 1 and 2 film the bow and midship grids, 3 only a stern grid."""
    root = tmp_path_factory.mktemp("survey")
    targets = default_targets()
    stern = AprilGridTarget(
        tag_rows=2, tag_cols=4, tag_size_m=0.088, tag_spacing_ratio=0.3, tag_id_offset=28
    )
    targets["stern"] = (stern, make_pose(np.eye(3), [30.0, -2.0, -12.0]))
    options = SurveyOptions(
        sessions=3,
        targets=targets,
        passes_per_target=1,
        keyframes_per_pass=6,
        distance_m=(0.6, 1.0),
        camera=default_camera().scaled(0.5),
        outlier_fraction=0.1,
        skip_targets={0: ("stern",), 1: ("stern",), 2: ("bow", "midship")},
    )
    folders, target_paths, truth = make_survey(root, options, seed=3)
    return root, folders, target_paths, truth


def _copy(survey, tmp_path):
    _root, folders, target_paths, truth = survey
    new_folders = []
    for folder in folders:
        shutil.copytree(folder, tmp_path / folder.name)
        new_folders.append(tmp_path / folder.name)
    return new_folders, target_paths, truth


def _relative_truth(truth, a, b):
    return invert_pose(truth.world_from_session[a]) @ truth.world_from_session[b]


def test_stage_places_sessions_and_writes_every_output(survey, tmp_path):
    folders, target_paths, truth = _copy(survey, tmp_path)
    out = tmp_path / "merged"
    path = run(MergeOptions(), folders, target_paths, out)
    assert path == out / "transforms.json"
    document = json.loads(path.read_text())
    assert document["reference"] == "dive1"
    assert document["dof"] == 6 and document["depth_fused"] is False
    sessions = document["sessions"]
    assert sessions["dive1"]["placed"] and sessions["dive2"]["placed"]
    np.testing.assert_allclose(sessions["dive1"]["T_W_S"], np.eye(4))
    estimate = np.array(sessions["dive2"]["T_W_S"])
    rot, trans = pose_difference(estimate, _relative_truth(truth, "dive1", "dive2"))
    assert np.rad2deg(rot) < 0.5 and trans < 0.05
    covariance = np.array(sessions["dive2"]["covariance"])
    assert covariance.shape == (6, 6)
    np.testing.assert_allclose(covariance, covariance.T)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    assert sorted(sessions["dive2"]["targets_used"]) == ["bow", "midship"]
    # Dive 3 shares no target (and the synthetic views share no structure either):
    # reported with the evidence, not placed, no merged trajectory.
    assert sessions["dive3"]["placed"] is False
    assert "natural-feature" in sessions["dive3"]["reason"]
    pairs = {tuple(p["sessions"]): p for p in document["pairs"]}
    assert not pairs["dive1", "dive3"]["mergeable"] and not pairs["dive2", "dive3"]["mergeable"]
    assert document["estimator"] == "joint"
    assert {c["label"] for c in document["constraints"]} >= {"bow@dive1", "midship@dive2"}
    assert not (out / "dive3").exists()
    merged = read_tum(out / "dive2" / "keyframes_merged.tum")
    original = read_tum(folders[1] / "keyframes.tum")
    np.testing.assert_allclose(merged.poses, estimate @ original.poses, atol=1e-9)
    targets = json.loads((out / "targets.json").read_text())
    bow = targets["bow"]["sessions"]["dive1"]
    assert bow["observations"] == bow["used"] + bow["rejected"]
    assert bow["observations"] >= 4
    assert "T_W_m" in targets["bow"]
    # Only an unplaced session saw the stern grid: it has no pose in W.
    assert "T_W_m" not in targets["stern"] and "dive3" in targets["stern"]["sessions"]
    world_bow = np.array(targets["bow"]["T_W_m"])
    true_bow = invert_pose(truth.world_from_session["dive1"]) @ truth.world_from_target["bow"]
    assert pose_difference(world_bow, true_bow)[1] < 0.1
    for name in ("merge_top.png", "merge_side.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Done already: skipped (nothing rewritten) unless overwrite.
    stamp = path.stat().st_mtime_ns
    assert run(MergeOptions(), folders, target_paths, out) == path
    assert path.stat().st_mtime_ns == stamp
    run(MergeOptions(reference="dive2", plot=False), folders, target_paths, out, overwrite=True)
    assert json.loads(path.read_text())["reference"] == "dive2"


def test_paper_method_and_4dof(survey, tmp_path):
    folders, target_paths, truth = _copy(survey, tmp_path)
    expected = _relative_truth(truth, "dive1", "dive2")
    cases: tuple[tuple[Literal["ours", "paper"], Literal["auto", 4, 6]], ...] = (
        ("paper", "auto"),
        ("ours", 4),
    )
    for method, dof in cases:
        out = tmp_path / f"{method}_{dof}"
        document = json.loads(
            run(
                MergeOptions(method=method, dof=dof, natural_features=False, plot=False),
                folders[:2],
                target_paths,
                out,
            ).read_text()
        )
        assert document["method"] == method
        entry = document["sessions"]["dive2"]
        rot, trans = pose_difference(np.array(entry["T_W_S"]), expected)
        assert np.rad2deg(rot) < 3.0 and trans < 0.2
        if dof == 4:
            assert document["dof"] == 4
            assert "diagnostic_6dof" in entry
            assert entry["diagnostic_6dof"]["rotation_difference_deg"] < 1.0


def _add_depth(folder: Path, z_shift_m: float) -> None:
    """A depth stage output beside the folder: the body trajectory shifted to true depth."""
    keyframes = read_tum(folder / "keyframes.tum")
    write_tum(folder / "trajectory.tum", keyframes)
    shifted = make_pose(np.eye(3), [0.0, 0.0, z_shift_m]) @ keyframes.poses
    write_tum(folder / "depth" / "trajectory_world.tum", Trajectory(keyframes.stamps_ns, shifted))


def test_depth_fused_sessions_are_detected_and_aligned_in_4dof(survey, tmp_path):
    folders, target_paths, truth = _copy(survey, tmp_path)
    # The depth stage puts each session at its true depth: W's z of its frame origin.
    depth_z = {name: float(truth.world_from_session[name][2, 3]) for name in ("dive1", "dive2")}
    _add_depth(folders[0], depth_z["dive1"])
    _add_depth(folders[1], depth_z["dive2"])
    out = tmp_path / "merged"
    document = json.loads(run(MergeOptions(plot=False), folders[:2], target_paths, out).read_text())
    assert document["depth_fused"] is True and document["dof"] == 4
    shift = {name: make_pose(np.eye(3), [0, 0, z]) for name, z in depth_z.items()}
    expected = (
        shift["dive1"] @ _relative_truth(truth, "dive1", "dive2") @ invert_pose(shift["dive2"])
    )
    estimate = np.array(document["sessions"]["dive2"]["T_W_S"])
    rot, trans = pose_difference(estimate, expected)
    assert np.rad2deg(rot) < 0.5 and trans < 0.05
    # Only one session fused: both fall back to their SLAM frames (6 DoF).
    out2 = tmp_path / "mixed"
    mixed = json.loads(
        run(MergeOptions(plot=False), [folders[0], folders[2]], target_paths, out2).read_text()
    )
    assert mixed["depth_fused"] is False and mixed["dof"] == 6
    assert mixed["tilt_prior_sigma_deg"] is None
    # With the SLAM's tilt uncertainty, "auto" fits 6 DoF with a gravity prior instead.
    prior = json.loads(
        run(
            MergeOptions(plot=False, tilt_sigma_deg=0.05),
            folders[:2],
            target_paths,
            tmp_path / "prior",
        ).read_text()
    )
    assert prior["depth_fused"] is True and prior["dof"] == 6
    assert prior["tilt_prior_sigma_deg"] == pytest.approx(0.05)
    entry = prior["sessions"]["dive2"]
    assert entry["dof"] == 6 and "diagnostic_6dof" not in entry
    rot, trans = pose_difference(np.array(entry["T_W_S"]), expected)
    assert np.rad2deg(rot) < 0.5 and trans < 0.05
    # The posterior roll/pitch is never looser than the prior (sqrt(2) x 0.05 deg per axis).
    covariance = np.array(entry["covariance"])
    assert np.all(np.sqrt(np.diag(covariance)[:2]) <= np.deg2rad(0.05) * np.sqrt(2.0))
    explicit_4 = json.loads(
        run(
            MergeOptions(plot=False, dof=4, tilt_sigma_deg=0.05),
            folders[:2],
            target_paths,
            tmp_path / "four",
        ).read_text()
    )
    assert explicit_4["dof"] == 4 and explicit_4["tilt_prior_sigma_deg"] is None
    with pytest.raises(InputError, match="depth fusion requested"):
        run(MergeOptions(depth_fused=True), [folders[2]], target_paths, tmp_path / "x")


def test_session_names_are_made_unique():
    assert session_names([Path("a/dive1/slam"), Path("a/dive2/slam")]) == [
        "dive1_slam",
        "dive2_slam",
    ]
    assert session_names([Path("x/one"), Path("x/two")]) == ["one", "two"]
    with pytest.raises(InputError, match="twice"):
        session_names([Path("x/one"), Path("x/./one")])


def test_raise_paths(survey, tmp_path):
    folders, target_paths, _ = _copy(survey, tmp_path)
    out = tmp_path / "out"
    bad_options = [
        (MergeOptions(method="euler"), "unknown method"),  # type: ignore[arg-type]
        (MergeOptions(dof=5), "dof must be"),  # type: ignore[arg-type]
        (MergeOptions(rotation_mean="euler"), "rotation_mean"),  # type: ignore[arg-type]
        (MergeOptions(outlier_rule="sigma"), "outlier_rule"),  # type: ignore[arg-type]
        (MergeOptions(min_tags=0), "min_tags"),
        (MergeOptions(mad_threshold=-1.0), "mad_threshold"),
        (MergeOptions(drift_rate_rotation_deg_per_sqrt_s=0.0), "drift_rate_rotation"),
        (MergeOptions(drift_rate_translation_m_per_sqrt_s=np.nan), "drift_rate_translation"),
        (MergeOptions(tilt_sigma_deg=0.0), "tilt_sigma_deg"),
        (MergeOptions(tilt_sigma_deg=np.inf), "tilt_sigma_deg"),
        (MergeOptions(reference="dive9"), "reference 'dive9'"),
        (MergeOptions(depth_sigma_m=0.0), "depth_sigma_m"),
    ]
    for options, message in bad_options:
        with pytest.raises(StageError, match=message):
            run(options, folders, target_paths, out)
    with pytest.raises(StageError, match="no SLAM folder"):
        run(MergeOptions(), [], target_paths, out)
    # Without targets only natural-feature merging can work.
    for options in (MergeOptions(method="paper"), MergeOptions(natural_features=False)):
        with pytest.raises(StageError, match="no target YAML"):
            run(options, folders, [], out)
    with pytest.raises(InputError, match="not a folder"):
        run(MergeOptions(), [tmp_path / "missing"], target_paths, out)
    # Two grids claiming the same ids.
    clash = write_target_yaml(
        tmp_path / "clash.yaml",
        AprilGridTarget(tag_rows=1, tag_cols=2, tag_size_m=0.1, tag_spacing_ratio=0.3),
    )
    with pytest.raises(InputError, match="tagIdOffset"):
        run(MergeOptions(), folders, [target_paths[0], clash], out)
    same_name = tmp_path / "other"
    same_name.mkdir()
    shutil.copy(target_paths[0], same_name / target_paths[0].name)
    with pytest.raises(InputError, match="share a name"):
        run(MergeOptions(), folders, [target_paths[0], same_name / target_paths[0].name], out)
    with pytest.raises(InputError, match="camera 'cam7'"):
        run(MergeOptions(camera="cam7"), folders, target_paths, out)
    broken = folders[0]
    (broken / "calib" / "camchain.yaml").unlink()
    with pytest.raises(InputError, match=r"camchain\.yaml"):
        run(MergeOptions(), [broken], target_paths, out)
    for image in (folders[1] / "keyframes").iterdir():
        image.unlink()
    with pytest.raises(InputError, match="no keyframe images"):
        run(MergeOptions(), [folders[1]], target_paths, out)
    unreadable = folders[2] / "keyframes" / sorted((folders[2] / "keyframes").iterdir())[0].name
    unreadable.write_bytes(b"not a png")
    # Read in a thread pool: the error still names the file.
    with pytest.raises(InputError, match=rf"{unreadable.name}: cannot read the keyframe image"):
        run(MergeOptions(), [folders[2]], target_paths, out)
    assert not out.exists()


def test_outputs_are_not_clobbered(survey, tmp_path):
    folders, target_paths, _ = _copy(survey, tmp_path)
    out = tmp_path / "out"
    (out / "dive1").mkdir(parents=True)
    (out / "dive1" / "keyframes_merged.tum").write_text("precious\n")
    with pytest.raises(OutputExistsError):
        run(MergeOptions(plot=False), folders[:2], target_paths, out)
    assert (out / "dive1" / "keyframes_merged.tum").read_text() == "precious\n"


def test_cli_subprocess(survey, tmp_path):
    folders, target_paths, _ = _copy(survey, tmp_path)
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    command = [sys.executable, "-m", "postproc.cli", "merge", str(folders[0]), str(folders[1])]
    command += ["--targets", *map(str, target_paths), "--out", str(tmp_path / "out"), "--no-plot"]
    command += ["--tilt-sigma-deg", "0.05"]
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert Path(done.stdout.strip()) == tmp_path / "out" / "transforms.json"
    document = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert document["sessions"]["dive2"]["placed"]
    assert document["tilt_prior_sigma_deg"] == 0.05
    failed = subprocess.run(
        [*command, "--reference", "nope", "--overwrite"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert failed.returncode == 1
    assert failed.stderr.strip().splitlines()[-1].startswith("wreckmap-post: error: merge:")


def test_pass_labels_split_on_time_gaps():
    second = 1_000_000_000
    stamps = [0, 1 * second, 30 * second, 2 * second, 31 * second, 90 * second]
    np.testing.assert_array_equal(pass_labels(stamps, gap_s=5.0), [0, 0, 1, 0, 1, 2])
    assert pass_labels([], gap_s=5.0).shape == (0,)


def test_depth_trajectory_must_overlap_the_keyframes(survey, tmp_path):
    folders, target_paths, _ = _copy(survey, tmp_path)
    keyframes = read_tum(folders[0] / "keyframes.tum")
    later = Trajectory(keyframes.stamps_ns + 10**12, keyframes.poses)
    write_tum(folders[0] / "trajectory.tum", later)
    write_tum(folders[0] / "depth" / "trajectory_world_fused.tum", later)
    with pytest.raises(InputError, match="no overlap"):
        run(MergeOptions(plot=False), folders[:1], target_paths, tmp_path / "out")


def test_session_anchor_is_the_first_slam_pose(tmp_path, caplog):
    from postproc.merge.stage import _anchor_ns

    keyframes = Trajectory(np.array([5_000, 9_000], dtype=np.int64), np.stack([np.eye(4)] * 2))
    assert _anchor_ns(tmp_path, keyframes) == 5_000
    write_tum(
        tmp_path / "trajectory.tum",
        Trajectory(np.array([1_000, 5_000], dtype=np.int64), np.stack([np.eye(4)] * 2)),
    )
    assert _anchor_ns(tmp_path, keyframes) == 1_000
    (tmp_path / "trajectory.tum").write_text("1 2 3\n")
    assert _anchor_ns(tmp_path, keyframes) == 5_000
    assert "unreadable" in caplog.text


def test_drift_weighting_leans_on_the_first_pass(tmp_path, caplog):
    """Passes a minute apart in sessions that drift as a random walk from their first pose."""
    from sim.targets import apply_slam_error

    options = SurveyOptions(
        sessions=2,
        passes_per_target=2,
        keyframes_per_pass=4,
        pass_gap_s=60.0,
        distance_m=(0.6, 1.0),
        camera=default_camera().scaled(0.5),
        drift_rotation_deg=0.0,
        drift_translation_m=0.0,
        jitter_rotation_deg=0.05,
        jitter_translation_m=0.003,
        outlier_fraction=0.0,
    )
    folders, target_paths, truth = make_survey(tmp_path / "survey", options, seed=8)
    rng = np.random.default_rng(8)
    for folder in folders:
        keyframes = read_tum(folder / "keyframes.tum")
        seconds = (keyframes.stamps_ns - keyframes.stamps_ns[0]) / 1e9
        steps = (
            rng.normal(0.0, 0.01, (len(seconds), 3))
            * np.sqrt(np.diff(seconds, prepend=0.0))[:, None]
        )
        walk = np.cumsum(steps, axis=0)
        drifted = np.array(
            [
                apply_slam_error(pose, make_pose(np.eye(3), w))
                for pose, w in zip(keyframes.poses, walk, strict=True)
            ]
        )
        (folder / "keyframes.tum").unlink()
        write_tum(folder / "keyframes.tum", Trajectory(keyframes.stamps_ns, drifted))
    expected = _relative_truth(truth, "dive1", "dive2")
    errors, sigmas, rejected = {}, {}, {}
    for weighting in (True, False):
        out = tmp_path / f"merged_{weighting}"
        with caplog.at_level("INFO", logger="postproc.merge.stage"):
            document = json.loads(
                run(
                    MergeOptions(drift_weighting=weighting, dof=4, plot=False),
                    folders,
                    target_paths,
                    out,
                ).read_text()
            )
        entry = document["sessions"]["dive2"]
        errors[weighting] = pose_difference(np.array(entry["T_W_S"]), expected)[1]
        sigmas[weighting] = entry["sigma_translation_m"]
        targets = json.loads((out / "targets.json").read_text())
        rejected[weighting] = sum(
            seen["rejected"] for target in targets.values() for seen in target["sessions"].values()
        )
        # Measured drift: the targets of one session share it, so the joint estimate
        # places the sessions (with a residual per target); else one by one.
        assert ("estimator" in document) == weighting
        if weighting:
            assert {c["kind"] for c in document["constraints"]} == {"target"}
            assert "from 2 pass pairs" in caplog.text
            # Two pairs of passes measure the rate poorly: the model says so.
            model = entry["drift_model"]
            assert model["pass_pairs"] == 2
            assert min(model["variance_calibration"]) >= 1.0
            assert min(model["variance_calibration"][3:]) > 1.2
            assert 0.005 < np.mean(model["drift_sigma_per_sqrt_s"][3:]) < 0.02
    assert errors[True] < 0.5 * errors[False]
    # No gross error was planted: measured against the drift model every sighting stays
    # (the robust mean's rule alone cuts one of a drifted pass).
    assert rejected[True] == 0 and rejected[False] >= 1
    assert errors[True] < 0.03
    # The covariance includes the drift of the first passes: the same size as the error.
    assert 0.3 < errors[True] / sigmas[True] < 3.0
    # Equal passes: each target's covariance grows by its local frame's drift from the
    # session's mean frame, in proportion to the drift rate (here shrunk toward the prior).
    spread = {}
    for rate in (0.003, 0.3):
        out = tmp_path / f"overlay_{rate}"
        run(
            MergeOptions(
                drift_weighting=False, drift_rate_translation_m_per_sqrt_s=rate, plot=False
            ),
            folders,
            target_paths,
            out,
        )
        targets = json.loads((out / "targets.json").read_text())
        spread[rate] = [
            np.trace(np.array(targets[m]["sessions"]["dive2"]["covariance"])[3:, 3:])
            for m in targets
        ]
    assert all(big > 100 * small for big, small in zip(spread[0.3], spread[0.003], strict=True))
