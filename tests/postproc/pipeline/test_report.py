"""report.html is self-contained (inline PNGs, no external reference) and the errors
against truth are right on synthetic outputs with known errors."""

from __future__ import annotations

import base64
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from postproc.pipeline.evaluate import evaluate_project, read_truth
from postproc.pipeline.project import load_project
from postproc.pipeline.report import render_mesh_png, write_report
from shared.errors import InputError
from shared.formats.ply import write_ply

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report_fixture import build, cube  # type: ignore[import-not-found]  # on the sys.path above


def test_errors_against_truth(tmp_path: Path) -> None:
    path, known = build(tmp_path, rng=np.random.default_rng(3))
    evaluation = evaluate_project(load_project(path))
    s1 = evaluation["sessions"]["s1"]
    # ATE after a rigid fit is at most the added noise, and close to it.
    assert 0.8 * known["noise_rms"] < s1["slam_ate_m"] <= known["noise_rms"] + 1e-9
    assert s1["slam_poses"] >= 199
    assert s1["depth_time_offset_error_s"] == pytest.approx(0.3, abs=1e-6)
    assert s1["depth_offset_error_m"] == pytest.approx(-0.2, abs=1e-9)
    assert s1["depth_z_rms_m"] == pytest.approx(0.2, abs=1e-9)
    assert evaluation["merge"]["rms_m"] == pytest.approx(0.0, abs=1e-6)
    assert "sfm" not in evaluation  # no refined keyframes written
    dense = evaluation["dense"]
    assert dense["file"] == "mesh.ply" and dense["median_distance_m"] < 1e-5
    assert all(s["accuracy"] == 1.0 for s in dense["scores"])


def test_report_is_self_contained(tmp_path: Path) -> None:
    path, _ = build(tmp_path, rng=np.random.default_rng(4))
    report = write_report(load_project(path))
    text = report.read_text()
    # No URL at all (the viewer test checks in Chromium that nothing is requested).
    assert "http://" not in text and "https://" not in text and "://" not in text
    assert "<link" not in text and "url(" not in text
    assert not re.search(r"<script[^>]*\ssrc=", text)
    # The viewer comes first: the model, then coverage, then the tables.
    assert text.index("id='wm-viewer'") < text.index("Coverage for the next dive")
    assert text.index("Coverage for the next dive") < text.index("Stage runs")
    sources = re.findall(r'src="([^"]*)"', text)
    # trajectory, depth sync, merge top, mesh render (merge side is reported as missing;
    # no coverage map: this run has no camera model)
    assert len(sources) == 4
    for src in sources:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert "merge side view: not available" in text
    assert "s1: left out (camera model" in text
    assert "Errors against truth" in text and "SLAM ATE" in text
    assert json.loads((tmp_path / "out" / "evaluation.json").read_text())["sessions"]["s1"]
    assert "Stage runs" in text and "not run" in text  # no stamps: listed as not run


def test_mesh_render_and_unreadable_mesh(tmp_path: Path) -> None:
    write_ply(tmp_path / "m.ply", cube())
    png = render_mesh_png(tmp_path / "m.ply")
    assert png is not None
    assert png[:4] == b"\x89PNG"
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    assert render_mesh_png(tmp_path / "bad.ply") is None


def test_truth_file_errors(tmp_path: Path) -> None:
    (tmp_path / "t.json").write_text('{"format": "other"}')
    with pytest.raises(InputError, match=r"t.json: not a simulator truth file"):
        read_truth(tmp_path / "t.json")
    with pytest.raises(InputError, match=r"none.json: cannot read the truth file"):
        read_truth(tmp_path / "none.json")


def test_rasterise_keeps_the_nearest_point() -> None:
    from postproc.pipeline.report import rasterise

    # A low red point under a high blue one, plus two corners to set the extent.
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -1.0, 0.0], [1.0, 1.0, 0.0]])
    colours = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0], [0, 1.0, 0]])
    top = rasterise(points, colours, azimuth_deg=0.0, elevation_deg=90.0, size_px=(64, 64))
    side = rasterise(points, colours, azimuth_deg=0.0, elevation_deg=0.0, size_px=(64, 64))
    blue = np.all(top == [0, 0, 1.0], axis=2)
    red = np.all(top == [1.0, 0, 0], axis=2)
    assert blue.any() and not red.any()  # seen from above, the high point hides the low one
    assert np.all(side == [1.0, 0, 0], axis=2).any()  # from the side, both show
    assert np.all(side == [0, 0, 1.0], axis=2).any()
