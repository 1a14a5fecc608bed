"""`report.html` of a project: one self-contained page that opens offline.

Everything is inline: plots and renders as base64 PNG `data:` URIs, styles in `<style>`
blocks, the 3D viewer's three.js and script in `<script>` blocks (`viewer.py`), no
external reference. Sections, model first: the model in 3D (`viewer.py`), the coverage
for the next dive (`coverage_report.py`, which also writes `coverage/` in the run
folder), the stage runs (status, time, worker), per session the SLAM statistics, a top
view of the trajectory and the depth sync (numbers and its plot), the merge
(transforms, top and side views), the SfM statistics, the dense reconstruction (counts
and a rendered view of mesh.ply) and, when the project has a truth file, the errors
against truth (`evaluate`). Stages that have not run are listed as such.
"""

from __future__ import annotations

import base64
import datetime
import html
import io
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.errors import WreckmapError
from shared.folders import (
    DenseFolder,
    DepthFolder,
    HandoffFolder,
    MergeFolder,
    SfmFolder,
    SlamFolder,
)
from shared.fsutil import write_text_atomic

if TYPE_CHECKING:
    from shared.trajectory import Trajectory

log = logging.getLogger(__name__)

_STYLE = """
body{font-family:sans-serif;margin:2em;max-width:1100px;color:#222}
h1{font-size:1.6em}h2{border-bottom:1px solid #aaa;margin-top:1.6em}
table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;
text-align:left;font-size:0.9em}th{background:#eee}img{max-width:100%;border:1px solid #ddd}
.missing{color:#a00}.ok{color:#070}.small{font-size:0.85em;color:#555}
"""


def png_data_uri(png: bytes) -> str:
    """A PNG as a `data:` URI for an <img> (keeps the page self-contained)."""
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _img(png: bytes | None, alt: str) -> str:
    if not png:
        return f'<p class="missing">{html.escape(alt)}: not available</p>'
    return f'<p><img alt="{html.escape(alt)}" src="{png_data_uri(png)}"></p>'


def _file_png(path: Path) -> bytes | None:
    return path.read_bytes() if path.is_file() else None


def _figure_png(fig: Any) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buffer.getvalue()


def _table(rows: list[tuple[str, Any]]) -> str:
    cells = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>" for k, v in rows
    )
    return f"<table>{cells}</table>"


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict | list):
        return json.dumps(value)[:200]
    return str(value)


def _json(path: Path) -> dict[str, Any] | None:
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _shown(read: Callable[[], dict[str, Any]]) -> dict[str, Any] | None:
    """A folder's JSON file (`read`, one of its readers), None when it cannot be read."""
    try:
        return read()
    except WreckmapError:
        return None


def trajectory_png(read: Callable[[], Trajectory], title: str) -> bytes | None:
    """Top view (x, y) of a trajectory (`read`, a folder's reader), metres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        trajectory = read()
    except Exception as error:  # a report shows what it can
        log.warning("%s", error)
        return None
    p = trajectory.positions
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(p[:, 0], p[:, 1], lw=1)
    ax.plot(p[:1, 0], p[:1, 1], "go", ms=4)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    return _figure_png(fig)


def rasterise(
    points: np.ndarray,
    colours: np.ndarray,
    *,
    azimuth_deg: float,
    elevation_deg: float,
    size_px: tuple[int, int] = (640, 480),
) -> np.ndarray:
    """Orthographic z-buffer splat of coloured points (N,3 m; N,3 in 0..1): an RGB image.

    The view turns the world by `azimuth_deg` about z, then tilts it by `elevation_deg`
    (90: from above); nearer points overwrite farther ones (2x2 pixel splats, so a dense
    mesh's face centres cover the surface)."""
    a, e = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1.0]])
    # Rows: screen right, depth (away from the viewer), screen up; e = 90 looks down.
    tilt = np.array([[1.0, 0, 0], [0, np.cos(e), -np.sin(e)], [0, np.sin(e), np.cos(e)]])
    q = points @ (tilt @ turn).T
    width, height = size_px
    lo = np.percentile(q, 0.5, axis=0)
    hi = np.percentile(q, 99.5, axis=0)
    scale = 0.92 * min(width / max(hi[0] - lo[0], 1e-6), height / max(hi[2] - lo[2], 1e-6))
    u = np.rint((q[:, 0] - (lo[0] + hi[0]) / 2) * scale + width / 2).astype(np.int64)
    v = np.rint(height / 2 - (q[:, 2] - (lo[2] + hi[2]) / 2) * scale).astype(np.int64)
    order = np.argsort(-q[:, 1])  # far first, so the nearest is written last
    image = np.ones((height, width, 3))
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        uu, vv = u[order] + du, v[order] + dv
        inside = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height)
        image[vv[inside], uu[inside]] = colours[order][inside]
    return image


def render_mesh_png(path: Path) -> bytes | None:
    """An oblique and a top view of a PLY mesh (or point cloud), shaded, as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from shared.formats.ply import read_ply

    try:
        ply = read_ply(path)
    except Exception as error:  # a report shows what it can
        log.warning("%s: %s", path, error)
        return None
    v = ply.vertices
    if len(v) == 0:
        return None
    if ply.faces is not None and len(ply.faces):
        tri = v[ply.faces]
        points = tri.mean(axis=1)
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        base = (
            ply.colors[ply.faces].mean(axis=1) / 255.0
            if ply.colors is not None
            else np.full((len(points), 3), 0.8)
        )
        shade = 0.35 + 0.65 * np.abs(normals @ np.array([0.3, -0.4, 0.87]))
    else:
        points = v
        base = ply.colors / 255.0 if ply.colors is not None else np.full((len(v), 3), 0.5)
        shade = np.ones(len(v))
    colours = np.clip(base * shade[:, None], 0.0, 1.0)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, (azimuth, elevation, label) in zip(
        axes, ((-60.0, 30.0, "oblique"), (0.0, 90.0, "top (x right, y up)")), strict=True
    ):
        ax.imshow(rasterise(points, colours, azimuth_deg=azimuth, elevation_deg=elevation))
        ax.set_title(label)
        ax.axis("off")
    kind = f"{len(ply.faces)} triangles" if ply.faces is not None and len(ply.faces) else "points"
    fig.suptitle(f"{path.name}: {len(v)} vertices, {kind}")
    return _figure_png(fig)


def _status_rows(project: Any, result: Any) -> str:
    from postproc.pipeline.runner import STAMP_NAME, plan

    rows = [
        "<tr><th>stage</th><th>session</th><th>status</th><th>time (s)</th>"
        "<th>worker / note</th></tr>"
    ]
    if result is not None:
        for o in result.outcomes:
            cls = "ok" if o.status in ("done", "skipped") else "missing"
            rows.append(
                f"<tr><td>{o.stage}</td><td>{o.session or '-'}</td>"
                f"<td class='{cls}'>{o.status}</td>"
                f"<td>{o.seconds:.1f}</td><td>{html.escape(o.worker or o.message)}</td></tr>"
            )
    else:
        tasks, _ = plan(project)
        for task in tasks:
            stamp = _json(task.out / STAMP_NAME)
            status = "done" if stamp else "not run"
            seconds = float(stamp.get("seconds", 0.0)) if stamp else 0.0
            worker = str(stamp.get("worker", "")) if stamp else ""
            cls = "ok" if stamp else "missing"
            rows.append(
                f"<tr><td>{task.stage}</td><td>{task.session or '-'}</td><td class='{cls}'>{status}"
                f"</td><td>{seconds:.1f}</td><td>{html.escape(worker)}</td></tr>"
            )
    return "<table>" + "".join(rows) + "</table>"


def _evaluation_html(evaluation: dict[str, Any]) -> str:
    if not evaluation:
        return ""
    if "error" in evaluation:
        return (
            "<h2>Errors against truth</h2><p class='missing'>evaluation failed: "
            f"{html.escape(evaluation['error'])}</p>"
        )
    parts = [
        "<h2>Errors against truth</h2>",
        f"<p class='small'>truth: {html.escape(evaluation['truth'])}</p>",
    ]
    rows = []
    for name, e in evaluation.get("sessions", {}).items():
        rows += [
            (f"{name}: SLAM ATE (m)", e.get("slam_ate_m", "n/a")),
            (f"{name}: depth clock offset error (s)", e.get("depth_time_offset_error_s", "n/a")),
            (f"{name}: depth offset error (m)", e.get("depth_offset_error_m", "n/a")),
            (f"{name}: depth z RMS (m)", e.get("depth_z_rms_m", "n/a")),
        ]
    for stage in ("merge", "sfm"):
        if stage in evaluation:
            rows.append(
                (
                    f"{stage}: keyframe position RMS after one rigid alignment (m)",
                    evaluation[stage]["rms_m"],
                )
            )
    dense = evaluation.get("dense")
    if dense:
        rows.append(
            (f"dense ({dense['file']}): median distance to truth (m)", dense["median_distance_m"])
        )
        if "completeness_basis" in dense:
            rows.append(("dense: completeness is measured on the", dense["completeness_basis"]))
        for s in dense["scores"]:
            d = s["threshold_m"]
            rows.append(
                (
                    f"dense: accuracy / completeness at {d:.2f} m",
                    f"{s['accuracy']:.3f} / {s['completeness']:.3f}",
                )
            )
    parts.append(_table(rows))
    return "".join(parts)


def _slam_section(folder: SlamFolder, session: Any) -> list[str]:
    stats = _shown(folder.read_stats)
    if stats is None:
        return ["<p class='missing'>SLAM: not run</p>"]
    keys = ("frames", "keyframes", "run_time_s", "sequence_duration_s", "real_time_factor",
            "loop_closures", "tracking_failures")  # fmt: skip
    return [
        "<h3>SLAM</h3>" + _table([(k, stats[k]) for k in keys if k in stats]),
        _img(
            trajectory_png(folder.read_trajectory, f"{session.name}: trajectory (top)"),
            "trajectory",
        ),
    ]


def _depth_section(folder: DepthFolder, session: Any) -> list[str]:
    sync = _shown(folder.read_sync)
    if sync is None:
        return ["<p class='missing'>Depth: not run</p>"] if session.dive is not None else []
    keys = ("time_offset_s", "time_offset_sigma_s", "drift_ppm", "depth_offset_m",
            "depth_offset_sigma_m", "depth_scale", "residual_rms_m", "samples_used")  # fmt: skip
    return [
        "<h3>Depth sync</h3>" + _table([(k, sync[k]) for k in keys if k in sync]),
        _img(_file_png(folder.plot), "depth sync plot"),
    ]


def _merge_section(folder: MergeFolder, session: Any) -> list[str]:
    body = ["<h2>Merge</h2>"]
    transforms = _shown(folder.read_transforms)
    if transforms is None:
        return [*body, "<p class='missing'>not run</p>"]
    rows = []
    for name, entry in transforms.get("sessions", {}).items():
        if entry.get("placed"):
            rows.append(
                (
                    name,
                    f"placed via {entry.get('via')}, sigma "
                    f"{entry.get('sigma_translation_m', float('nan')):.3f} m",
                )
            )
        else:
            rows.append((name, "not placed: " + str(entry.get("reason", ""))))
    body.append(
        _table([("reference", transforms.get("reference")), ("dof", transforms.get("dof")), *rows])
    )
    body.append(_img(_file_png(folder.top_plot), "merge top view"))
    body.append(_img(_file_png(folder.side_plot), "merge side view"))
    return body


def _sfm_section(folder: SfmFolder, session: Any) -> list[str]:
    body = ["<h2>Structure from motion</h2>"]
    sfm = _shown(folder.read_stats)
    if sfm is None:
        return [*body, "<p class='missing'>not run</p>"]
    keys = ("keyframes", "registered_images", "points3D", "mean_track_length",
            "mean_reprojection_error_px", "pairs", "seconds")  # fmt: skip
    return [*body, _table([(k, sfm[k]) for k in keys if k in sfm])]


def _dense_section(folder: DenseFolder, session: Any) -> list[str]:
    body = ["<h2>Dense reconstruction</h2>"]
    dense = _shown(folder.read_report)
    if dense is None:
        return [*body, "<p class='missing'>not run</p>"]
    keys = ("backend", "images", "fused_points", "mesh", "timings")
    body.append(_table([(k, dense[k]) for k in keys if k in dense]))
    target = folder.mesh if folder.mesh.is_file() else folder.fused
    body.append(_img(render_mesh_png(target) if target.is_file() else None, "mesh render"))
    return body


# The report's section of each folder kind a stage writes (a kind without one, like the
# calibration or an imported session, has no section). Sections follow the registry's
# order: per session those of the session stages, then those of the project stages.
SECTIONS: dict[type[HandoffFolder], Callable[[Any, Any], list[str]]] = {
    SlamFolder: _slam_section,
    DepthFolder: _depth_section,
    MergeFolder: _merge_section,
    SfmFolder: _sfm_section,
    DenseFolder: _dense_section,
}


def build_report(
    project: Any, *, result: Any = None, evaluation: dict[str, Any] | None = None
) -> str:
    """The report page of `project` as one HTML string (no external references)."""
    from postproc.pipeline.stages import STAGES

    out = project.output
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    from postproc.pipeline.coverage_report import coverage_html, safe_run_coverage
    from postproc.pipeline.viewer import load_scene, viewer_html

    names = [session.name for session in project.sessions]
    coverage = safe_run_coverage(out, names)
    body = [
        f"<h1>{html.escape(project.name)}</h1>",
        f"<p class='small'>project {html.escape(str(project.path))}; "
        f"output {html.escape(str(out))}; {now}</p>",
        "<h2>Model</h2>",
        viewer_html(load_scene(out, names, coverage=coverage)),
        "<h2>Coverage for the next dive</h2>",
        coverage_html(out, coverage),
        "<h2>Stage runs</h2>",
        _status_rows(project, result),
    ]
    sectioned = [stage for stage in STAGES.values() if stage.writes in SECTIONS]
    for session in project.sessions:
        body.append(f"<h2>Session {html.escape(session.name)}</h2>")
        body.append(
            f"<p class='small'>{session.source}: "
            f"{html.escape(', '.join(str(p) for p in session.paths))}</p>"
        )
        for stage in (s for s in sectioned if s.per_session):
            folder = stage.writes(stage.place(out, session.name))
            body += SECTIONS[stage.writes](folder, session)
    for stage in (s for s in sectioned if not s.per_session):
        body += SECTIONS[stage.writes](stage.writes(stage.place(out, None)), None)
    if evaluation:
        body.append(_evaluation_html(evaluation))
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>{html.escape(project.name)}: wreckmap report</title><style>{_STYLE}</style>"
        "</head><body>" + "\n".join(body) + "</body></html>\n"
    )


def write_report(project: Any, *, result: Any = None, out_path: Path | None = None) -> Path:
    """Evaluate against truth (when known; also writes evaluation.json) and write report.html."""
    evaluation: dict[str, Any] = {}
    if project.truth is not None:
        from postproc.pipeline.evaluate import evaluate_project

        try:
            evaluation = evaluate_project(project)
        except (WreckmapError, ValueError, KeyError, TypeError, OSError) as error:
            # The report still shows the outputs; the evaluation says why it is missing.
            log.warning("evaluation against %s failed: %s", project.truth, error)
            evaluation = {"truth": str(project.truth), "error": f"{type(error).__name__}: {error}"}
        write_text_atomic(
            project.output / "evaluation.json",
            json.dumps(evaluation, indent=2) + "\n",
            overwrite=True,
        )
    path = out_path or project.output / "report.html"
    write_text_atomic(
        path, build_report(project, result=result, evaluation=evaluation), overwrite=True
    )
    return path
