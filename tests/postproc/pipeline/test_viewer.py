"""The report's 3D viewer in headless Chromium (SwiftShader WebGL, offline): it draws,
its layer toggles change what is drawn, two clicks on the mesh measure a known
distance, nothing is fetched; and the decimation that keeps the page small."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from postproc.pipeline.browser import HeadlessChromium
from postproc.pipeline.decimate import cluster_vertices, decimate_mesh, subsample_points
from postproc.pipeline.project import load_project
from postproc.pipeline.report import write_report
from postproc.pipeline.viewer import load_scene, scene_document
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.cameras import PinholeRadtan
from shared.calibration.kalibr import CameraCalibration, write_camchain, write_target_yaml
from shared.formats.ply import PlyData, write_ply
from shared.geometry import make_pose, so3_exp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report_fixture import build  # type: ignore[import-not-found]  # on the sys.path above

# The fixture's mesh: a 2 m cube centred at (0, 0, -10) moved by H (see report_fixture).
H = make_pose(so3_exp([0.0, 0.0, -0.4]), [1.0, 1.0, 0.0])
BACKGROUND = np.array([0x30, 0x26, 0x1D])  # BGR of the viewer's clear colour #1d2630


def world(p: list[float]) -> list[float]:
    moved: list[float] = (H[:3, :3] @ np.asarray(p, float) + H[:3, 3]).tolist()
    return moved


def fine_cube(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A 2 m cube centred at the origin, each face an n x n grid of squares (two
    triangles each, wound outwards)."""
    t = np.linspace(-1.0, 1.0, n + 1)
    a, b = np.meshgrid(t, t, indexing="ij")
    vertices: list[np.ndarray] = []
    faces: list[list[int]] = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            grid = np.zeros((n + 1, n + 1, 3))
            u, v = (axis + 1) % 3, (axis + 2) % 3
            grid[..., axis], grid[..., u], grid[..., v] = sign, a, b
            base = sum(len(x) for x in vertices)
            vertices.append(grid.reshape(-1, 3))
            for i in range(n):
                for j in range(n):
                    k = base + i * (n + 1) + j
                    quad = [k, k + n + 1, k + n + 2, k + 1]
                    tri = [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
                    faces += tri if sign > 0 else [t_[::-1] for t_ in tri]
    return np.vstack(vertices), np.array(faces)


def viewer_run(root: Path) -> Path:
    """The report fixture plus what the viewer draws: vertex colours, fused points, a
    target, a camera model (so that coverage runs too)."""
    project: Path
    project, _ = build(root, rng=np.random.default_rng(5))
    out = root / "out"
    # The same cube as the fixture's, each face a 16 x 16 grid (coverage needs samples).
    vertices, faces = fine_cube(16)
    vertices = (vertices + np.array([0.0, 0.0, -10.0])) @ H[:3, :3].T + H[:3, 3]
    colours = np.tile(np.array([[60, 200, 60]], np.uint8), (len(vertices), 1))
    write_ply(out / "dense" / "mesh.ply", PlyData(vertices=vertices, faces=faces,
                                                  colors=colours), overwrite=True)  # fmt: skip
    rng = np.random.default_rng(1)
    points = rng.uniform(-1, 1, (5000, 3))
    points[np.arange(5000), rng.integers(0, 3, 5000)] = rng.choice([-1.0, 1.0], 5000)
    points = (points + np.array([0.0, 0.0, -10.0])) @ H[:3, :3].T + H[:3, 3]
    colours = np.tile(np.array([[230, 60, 60]], np.uint8), (5000, 1))
    write_ply(out / "dense" / "fused.ply", PlyData(vertices=points, colors=colours))
    grid = root / "targets" / "grid_a.yaml"
    write_target_yaml(grid, AprilGridTarget(tag_rows=2, tag_cols=3, tag_size_m=0.1,
                                            tag_spacing_ratio=0.3))  # fmt: skip
    pose = make_pose(np.eye(3), world([-1.0, -1.0, -8.999]))
    (out / "merge" / "targets.json").write_text(
        json.dumps({"grid_a": {"file": str(grid), "T_W_m": pose.tolist(), "sessions": {}}})
    )
    camera = PinholeRadtan(width=320, height=180, fx=250.0, fy=250.0, cx=159.5, cy=89.5)
    write_camchain(out / "sessions" / "s1" / "calib" / "camchain.yaml",
                   [CameraCalibration(camera=camera)])  # fmt: skip
    return project


def canvas_image(browser: HeadlessChromium) -> np.ndarray:
    """The viewer's canvas (BGR) from a screenshot, the panel's corner blanked."""
    rect = browser.evaluate(
        "(() => { const r = document.getElementById('wm-canvas').getBoundingClientRect();"
        " const p = document.getElementById('wm-panel').getBoundingClientRect();"
        " return [r.x, r.y, r.width, r.height, p.right - r.x, p.bottom - r.y]; })()"
    )
    x, y, w, h, panel_w, panel_h = (round(v) for v in rect)
    png = browser.screenshot()
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    canvas = image[y : y + h, x : x + w].copy()
    canvas[: panel_h + 2, : panel_w + 2] = BACKGROUND
    return canvas


def drawn_fraction(canvas: np.ndarray) -> float:
    """Share of canvas pixels that differ from the clear colour."""
    return float(np.mean(np.abs(canvas.astype(int) - BACKGROUND).max(axis=2) > 24))


def green(canvas: np.ndarray) -> np.ndarray:
    """Pixels of the test mesh's colour (RGB 60, 200, 60 shaded; BGR images)."""
    b, g, r = (canvas[:, :, k].astype(int) for k in range(3))
    return (g > r + 40) & (g > b + 40)


def open_viewer(browser: HeadlessChromium, url: str) -> int:
    """Load the page afresh (a change of hash alone would not reload it)."""
    browser.open("about:blank")
    browser.wait_for("location.href === 'about:blank'")
    browser.open(url)
    browser.wait_for(
        "window.wreckmapViewer && (window.wreckmapViewer.ready || window.wreckmapViewer.error)"
    )
    assert browser.evaluate("window.wreckmapViewer.error") is None, browser.console
    return int(browser.evaluate("window.wreckmapViewer.frames"))


@pytest.mark.timeout(240)
def test_viewer_draws_toggles_measures_offline(tmp_path: Path) -> None:
    report = write_report(load_project(viewer_run(tmp_path)))
    url = report.resolve().as_uri()
    with HeadlessChromium(width_px=1000, height_px=800, profile_dir=tmp_path / "profile") as b:
        assert open_viewer(b, url) >= 1
        # With a mesh the fused points start hidden (they would cover it).
        assert b.evaluate("document.getElementById('wm-layer-points').checked") is False
        full = canvas_image(b)
        assert drawn_fraction(full) > 0.05  # not blank: the cube fills part of the view
        # The mesh's colour (green, shaded) is on screen.
        assert green(full).mean() > 0.02
        labels = b.evaluate(
            "[...document.querySelectorAll('#wm-panel input')].map(i => i.id).join(',')"
        )
        for layer in ("mesh", "points", "session_s1", "targets", "keyframes"):
            assert f"wm-layer-{layer}" in labels

        # A URL hash hides the mesh at load: the fused points (red) show through.
        open_viewer(b, url + "#hide=mesh")
        hidden = canvas_image(b)
        changed = np.abs(full.astype(int) - hidden.astype(int)).max(axis=2) > 24
        assert changed.mean() > 0.02
        assert not green(hidden).any()
        b_, g_, r_ = (hidden[:, :, k].astype(int) for k in range(3))
        assert ((r_ > g_ + 50) & (r_ > b_ + 40)).mean() > 0.002
        # The mesh coloured by its coverage score: other colours than the photo's green.
        open_viewer(b, url + "#colour=coverage")
        assert b.evaluate("document.getElementById('wm-coverage').checked") is True
        by_coverage = canvas_image(b)
        assert green(by_coverage).mean() < 0.2 * green(full).mean()
        assert drawn_fraction(by_coverage) > 0.05
        # Unticking the box by a real click (every layer on: "hide=" names none) draws the
        # same picture as the hash.
        open_viewer(b, url + "#hide=")
        assert b.evaluate("document.getElementById('wm-layer-points').checked") is True
        frames = b.evaluate("window.wreckmapViewer.frames")
        box = b.evaluate(
            "(() => { const r = document.getElementById('wm-layer-mesh')"
            ".getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; })()"
        )
        b.click(*box)
        b.wait_for(f"window.wreckmapViewer.frames > {frames}")
        clicked = canvas_image(b)
        assert np.mean(np.abs(clicked.astype(int) - hidden.astype(int)).max(axis=2) > 24) < 0.005

        # Measuring: two clicks on the cube's top face, 1.2 m and 1.1 m apart along its
        # edges (positions travel quantised: the answer is within a centimetre).
        open_viewer(b, url)
        b.evaluate("document.getElementById('wm-measure').click()")
        a, c = world([-0.6, -0.6, -9.0]), world([0.6, 0.5, -9.0])
        for point in (a, c):
            x, y = b.evaluate(f"window.wreckmapViewer.toScreen({json.dumps(point)})")
            b.click(x, y)
        measured = b.wait_for("window.wreckmapViewer.lastMeasure_m")
        assert measured == pytest.approx(np.hypot(1.2, 1.1), abs=0.01)
        assert f"{measured:.3f} m" in b.evaluate(
            "document.getElementById('wm-measure-result').textContent"
        )
        scale = b.evaluate("document.querySelector('#wm-scalebar span').textContent")
        assert scale.endswith(" m") or scale.endswith(" cm")
        # Offline: the page asked for nothing but itself and its inline data.
        assert b.requests
        assert all(r.startswith(("file:", "data:")) for r in b.requests), b.requests
    assert (tmp_path / "out" / "coverage" / "coverage_merged.png").is_file()
    assert "Largest gaps" in report.read_text() or "no gap found" in report.read_text()


def sphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 1 m (rows x 2 rows triangles a band)."""
    rows, cols = subdivisions, 2 * subdivisions
    theta = np.linspace(0, np.pi, rows + 1)
    phi = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = np.column_stack(
        [(np.sin(t) * np.cos(p)).ravel(), (np.sin(t) * np.sin(p)).ravel(), np.cos(t).ravel()]
    )
    faces = []
    for r in range(rows):
        for c in range(cols):
            a, b = r * cols + c, r * cols + (c + 1) % cols
            d, e = a + cols, b + cols
            faces += [[a, b, e], [a, e, d]]
    return vertices, np.array(faces)


def test_decimation_meets_the_budget_and_keeps_the_shape() -> None:
    vertices, faces = sphere(120)  # 57,600 triangles
    colours = np.tile(np.array([[10, 200, 30]], np.uint8), (len(vertices), 1))
    small = decimate_mesh(vertices, faces, colours, max_triangles=4000)
    assert 3000 < len(small.faces) <= 4000  # the smallest cell that fits, not far below
    radius = np.linalg.norm(small.vertices_m, axis=1)
    assert np.all(np.abs(radius - 1.0) < small.cell_m)  # within one cell of the surface
    assert small.colours is not None and np.all(small.colours == [10, 200, 30])
    assert small.faces.max() < len(small.vertices_m)
    same = decimate_mesh(vertices, faces, None, max_triangles=len(faces))
    assert same.cell_m == 0.0 and len(same.faces) == len(faces)
    with pytest.raises(ValueError, match="cell_m must be positive"):
        cluster_vertices(vertices, faces, None, cell_m=0.0)
    picked = subsample_points(1000, max_points=300, seed=2)
    assert len(picked) == 300 and len(np.unique(picked)) == 300
    assert np.array_equal(subsample_points(10, max_points=300), np.arange(10))


def test_scene_document_positions_round_trip(tmp_path: Path) -> None:
    viewer_run(tmp_path)
    scene = load_scene(tmp_path / "out", ["s1"], max_triangles=500, max_points=1000)
    document = scene_document(scene)
    assert document["mesh"]["full_triangles"] == 6 * 16 * 16 * 2
    assert 100 < document["mesh"]["triangles"] <= 500
    assert document["points"]["full_count"] == 5000
    assert len(document["points"]["colours"]) > 0
    import base64

    q = np.frombuffer(base64.b64decode(document["points"]["positions"]["data"]), "<u2")
    decoded = np.asarray(document["min_m"]) + q.reshape(-1, 3) * np.asarray(document["step_m"])
    assert np.max(np.abs(decoded - scene.points_m)) <= max(document["step_m"]) * 0.51
    assert [s["name"] for s in document["sessions"]] == ["s1"]
    assert document["sessions"][0]["source"] == "merge/s1/keyframes_merged.tum"
    assert document["targets"][0]["name"] == "grid_a"
    assert document["targets"][0]["extent_m"] == pytest.approx([0.36, 0.23])


def test_missing_library_is_named_and_the_report_still_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import postproc.pipeline.viewer as viewer
    from shared.errors import InputError

    monkeypatch.setattr(viewer, "THREE_BUNDLE", tmp_path / "none" / "three-bundle.js")
    with pytest.raises(InputError, match=r"three-bundle.js: three.js bundle missing .*npm ci"):
        viewer.three_bundle()
    page = viewer.viewer_html(viewer.ViewerScene())
    assert "3D viewer not available" in page and "<script" not in page


def test_run_coverage_from_the_mesh_or_else_the_points(tmp_path: Path) -> None:
    from postproc.pipeline.coverage_report import compute_run_coverage, gap_rows, write_coverage

    viewer_run(tmp_path)
    out = tmp_path / "out"
    coverage = compute_run_coverage(out, ["s1"])
    assert coverage.surface_source == "dense/mesh.ply" and coverage.keyframes == {"s1": 20}
    assert set(coverage.maps) == {"merged"}  # one session: its map is the merged one
    assert set(coverage.maps["merged"]) == {"top", "side_pos", "side_neg"}
    rows = gap_rows(coverage)
    assert rows and all(r["nearest_target"] == "grid_a" for r in rows)
    target = np.asarray(json.loads((out / "merge" / "targets.json").read_text())["grid_a"]["T_W_m"])
    for row in rows:
        offset = np.asarray(row["centre_m"]) - target[:3, 3]
        assert row["offset_from_target_m"] == pytest.approx(offset, abs=0.01)
    written = write_coverage(out, coverage)
    assert written["merged"].read_bytes()[:4] == b"\x89PNG"
    document = json.loads((out / "coverage" / "coverage.json").read_text())
    assert document["largest_gaps"]["merged"] == rows
    (out / "dense" / "mesh.ply").unlink()
    from_points = compute_run_coverage(out, ["s1"])
    assert from_points.surface_source == "dense/fused.ply" and from_points.maps
    (out / "dense" / "fused.ply").unlink()
    nothing = compute_run_coverage(out, ["s1"])
    assert not nothing.maps and "dense stage not run" in nothing.notes[0]


def test_browser_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from postproc.pipeline import browser

    with HeadlessChromium(profile_dir=tmp_path / "profile") as b:
        b.open("about:blank")
        with pytest.raises(browser.BrowserError, match=r"'window.neverTrue' still false"):
            b.wait_for("window.neverTrue", timeout_s=0.5)
        with pytest.raises(browser.BrowserError, match=r"page: throw"):
            b.evaluate("throw new Error('x')")
    monkeypatch.setattr(shutil, "which", lambda name: None)  # the module browser uses
    with pytest.raises(browser.BrowserError, match="chromium is not installed"):
        HeadlessChromium()
