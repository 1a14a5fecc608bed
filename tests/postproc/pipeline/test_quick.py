"""The quick look (`wreckmap-post run --quick`): what it plans, where it puts it, and the
page it draws from a SLAM and depth result with a known answer."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from postproc.pipeline.project import load_project
from postproc.pipeline.quick import (
    QUICK_FOLDER,
    QUICK_MAX_FEATURES,
    QUICK_POSE_GRAPH_SCALE,
    QUICK_WINDOW_KEYFRAMES,
    QUICK_WINDOW_STEP,
    quick_project,
    quick_stages,
    read_quick_session,
    session_coverage,
    write_quick_page,
)
from postproc.pipeline.runner import plan, run_project
from shared.calibration.cameras import PinholeRadtan
from shared.calibration.kalibr import CameraCalibration, write_camchain
from shared.folders import SlamFolder
from shared.formats.ply import PlyData, ply_bytes
from shared.formats.tum import write_tum
from shared.geometry import look_at
from shared.trajectory import Trajectory

DEPTH_OF_ORIGIN_M = 12.0


def test_plan_keeps_session_stages_and_shares_imports_with_the_full_run(
    project_file: Path,
) -> None:
    project = load_project(project_file)
    full_width = project.options_for("slam").frontend.width_px
    quick = quick_project(project, width_px=320)
    assert quick.output == project.output / QUICK_FOLDER
    slam = quick.options_for("slam")
    assert slam.frontend.width_px == 320 and slam.max_rate_hz == 10.0
    assert slam.estimator.keyframes.max_interval_s == 1.0 and not slam.estimator.backend.final_batch
    assert not slam.keyframe_images  # the page draws none
    assert slam.estimator.backend.window_keyframes == QUICK_WINDOW_KEYFRAMES < 150
    assert slam.frontend.max_features == QUICK_MAX_FEATURES < 400
    assert slam.estimator.backend.window_step_keyframes == QUICK_WINDOW_STEP < 100
    # Every third image: the seeded flow keeps the unseeded window.
    assert slam.frontend.klt_window_px == slam.frontend.klt_window_unseeded_px == 15
    # The full project keeps its own options.
    full = project.options_for("slam")
    for name in ("pose_graph_rotation_sigma_rad", "pose_graph_translation_sigma_m"):
        loose, own = getattr(slam.estimator.backend, name), getattr(full.estimator.backend, name)
        assert loose == pytest.approx(QUICK_POSE_GRAPH_SCALE * own) and QUICK_POSE_GRAPH_SCALE > 1
    assert full.frontend.width_px == full_width == 960 and full.max_rate_hz is None
    assert full.estimator.keyframes.max_interval_s == 0.5 and full.estimator.backend.final_batch
    assert full.keyframe_images
    assert full.estimator.backend.window_keyframes == 150
    assert full.frontend.max_features == 400
    assert full.frontend.klt_window_px == 11
    registry = quick_stages(project)
    assert list(registry) == ["calibrate", "import", "slam", "depth"]
    # Imports and calibration go where the full run puts them; slam and depth to quick/.
    assert registry["import"].place(quick.output, "s1") == project.output / "imports" / "s1"
    assert registry["calibrate"].place(quick.output, None) == project.output / "calibration"
    tasks, _ = plan(quick, registry)
    assert {t.stage for t in tasks} == {"slam", "depth"}  # EuRoC sessions: no import
    for task in tasks:
        assert task.out.is_relative_to(quick.output / "sessions"), task.out


def test_never_widens_the_project_s_own_width(project_file: Path) -> None:
    project = load_project(project_file)
    project.options_for("slam").frontend.width_px = 400
    project.options_for("slam").estimator.backend.window_keyframes = 40
    project.options_for("slam").frontend.max_features = 150
    quick = quick_project(project, width_px=480).options_for("slam")
    assert quick.frontend.width_px == 400
    assert quick.frontend.max_features == 150
    assert quick.estimator.backend.window_keyframes == 40
    # A project that keeps every keyframe still gets the quick look's window.
    project.options_for("slam").estimator.backend.window_keyframes = 0
    quick = quick_project(project).options_for("slam")
    assert quick.estimator.backend.window_keyframes == QUICK_WINDOW_KEYFRAMES


def test_quick_run_on_fake_stages_reruns_nothing_the_second_time(
    project_file: Path, fake_stages: dict[str, Any]
) -> None:
    project = load_project(project_file)
    quick = quick_project(project)
    first = run_project(quick, stages=quick_stages(project, fake_stages))
    assert first.ok and {o.status for o in first.outcomes} == {"done"}
    again = run_project(quick, stages=quick_stages(project, fake_stages))
    assert {o.status for o in again.outcomes} == {"skipped"}
    # Nothing of the full run's own stage folders was written.
    assert not (project.output / "sessions").exists()
    assert not (project.output / "merge").exists()


def _wall_session(folder: SlamFolder, *, with_depth: bool) -> np.ndarray:
    """A swim along a wall (the plane y = 0, x 0..8 m, z -2..0 in S) at y = -3 m,
    looking at it; returns the landmarks (S)."""
    rng = np.random.default_rng(3)
    stamps = (np.arange(0, 40 * 10) * 100_000_000 + 1_000_000_000).astype(np.int64)
    t = (stamps - stamps[0]) * 1e-9
    x = 8.0 * t / t[-1]
    eye = np.stack([x, np.full_like(x, -3.0), np.full_like(x, -1.0)], axis=1)
    poses = look_at(eye, eye + np.array([0.0, 3.0, 0.0]))
    write_tum(folder.trajectory, Trajectory(stamps, poses))
    write_tum(folder.keyframes_tum, Trajectory(stamps[::10], poses[::10]))
    landmarks = np.stack(
        [rng.uniform(0, 8, 3000), np.zeros(3000), rng.uniform(-2, 0, 3000)], axis=1
    )
    folder.calib.mkdir()
    write_camchain(
        folder.camchain,
        [CameraCalibration(camera=PinholeRadtan(480, 270, 300.0, 300.0, 240.0, 135.0))],
    )
    folder.map_ply.write_bytes(ply_bytes(PlyData(vertices=landmarks)))
    folder.stats.write_text(
        json.dumps({"frames": len(stamps), "run_time_s": 10.0, "real_time_factor": 4.0})
    )
    if with_depth:
        depth = folder.depth
        depth.path.mkdir()
        world = poses.copy()
        world[:, 2, 3] -= DEPTH_OF_ORIGIN_M
        write_tum(depth.trajectory_world, Trajectory(stamps, world))
        depth.sync.write_text(json.dumps({"time_offset_s": -7.5, "residual_rms_m": 0.04}))
    return landmarks


def test_page_puts_the_map_at_depth_and_finds_the_unfilmed_side(project_file: Path) -> None:
    project = load_project(project_file)
    quick = quick_project(project)
    landmarks = _wall_session(SlamFolder(quick.output / "sessions" / "s1"), with_depth=True)
    _wall_session(SlamFolder(quick.output / "sessions" / "s2"), with_depth=False)

    s1 = read_quick_session(quick.output, "s1")
    assert s1 is not None and s1.at_depth
    np.testing.assert_allclose(s1.landmarks_m[:, 2], landmarks[:, 2] - DEPTH_OF_ORIGIN_M)
    np.testing.assert_allclose(s1.path_m[:, 2], -1.0 - DEPTH_OF_ORIGIN_M)
    np.testing.assert_allclose(s1.world_from_cam[:, 2, 3], -1.0 - DEPTH_OF_ORIGIN_M)
    s2 = read_quick_session(quick.output, "s2")
    assert s2 is not None and not s2.at_depth and "depth not synced" in s2.notes[0]
    assert read_quick_session(quick.output, "s3") is None

    coverage = session_coverage(s1)
    assert coverage is not None
    maps = coverage.maps["s1"]
    # The wall faces -y: one side view sees it well, the other has no surface at all.
    sides = [maps["side_pos"], maps["side_neg"]]
    filmed = [int(np.sum(m.surface)) for m in sides]
    assert min(filmed) == 0 and max(filmed) > 50, filmed
    seen = sides[int(np.argmax(filmed))]
    well = np.nan_to_num(seen.score)[seen.surface] >= coverage.options.gap_score
    assert well.mean() > 0.8, well.mean()

    page = write_quick_page(quick)
    assert page == quick.output / "quick.html"
    text = page.read_text(encoding="utf-8")
    assert "quick look" in text and "http://" not in text and "https://" not in text
    assert text.count("<img") >= 3  # two paths, one coverage map (s2 has no depth: still drawn)
    assert "depth not synced" in text
    # A session whose map is empty says why it has no coverage map.
    empty = SlamFolder(quick.output / "sessions" / "s2")
    empty.map_ply.write_bytes(ply_bytes(PlyData(vertices=np.zeros((0, 3)))))
    text = write_quick_page(quick).read_text(encoding="utf-8")
    assert "no coverage map: 0 landmarks, 40 keyframes" in text
    assert (quick.output / "coverage" / "coverage_s1.png").is_file()


def test_cli_refuses_a_tiny_width(project_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from postproc.cli import main

    assert main(["run", str(project_file), "--quick", "--quick-width", "10"]) == 1
    assert "--quick-width 10: expected at least 64 px" in capsys.readouterr().err
