"""The quick look (`wreckmap-post run --quick`) on a real GoPro file: karma.mp4 (HERO5 on
a Karma drone, 12 s at 30 fps, no dive log).

Measured (2-core machine, the test suite running beside it): import 0.8 s, quick SLAM
10.8 s on 120 of the 361 images (10 Hz, 480 px wide), 12 keyframes, a 34.1 m path
against 48.9 m for the full SLAM on the same import (361 images, 25 keyframes) and
about 77 m in the drone's own telemetry; the quick map kept no landmark (the full one
163: the scene is far, and with a keyframe a second few landmarks pass the map's
tests), so the page has the path but no coverage map, and says why.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from postproc.pipeline.project import load_project
from postproc.pipeline.quick import run_quick
from shared.folders import SessionFolder, SlamFolder


@pytest.mark.slow(seconds=60)
@pytest.mark.timeout(1200)
def test_karma_quick_look_runs_and_shares_the_import(shared_data: Path, tmp_path: Path) -> None:
    video = shared_data / "gopro" / "karma.mp4"
    project_file = tmp_path / "project.yaml"
    project_file.write_text(
        f"name: karma-quick\noutput: out\nsessions:\n  - name: karma\n    gopro: [{video}]\n"
    )
    project = load_project(project_file)
    result, page = run_quick(project)
    assert result.ok, [(o.key, o.status, o.message) for o in result.outcomes]
    assert {o.stage for o in result.outcomes} == {"import", "slam"}  # no dive log: no depth
    # The import is where the full run puts it; SLAM under quick/.
    assert SessionFolder(project.output / "imports" / "karma").is_complete()
    slam = SlamFolder(project.output / "quick" / "sessions" / "karma")
    stats = json.loads(slam.stats.read_text())
    assert stats["frontend_width_px"] == 480
    # 10 of the 30 images a second (the IMU starts one image late).
    assert 115 <= stats["frames"] <= 125, stats["frames"]
    assert stats["path_length_m"] > 10.0
    text = page.read_text(encoding="utf-8")
    assert text.count("<img") >= 1 and "depth not synced" in text
    assert "http://" not in text and "https://" not in text
