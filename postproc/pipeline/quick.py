"""The quick look for the boat: `wreckmap-post run PROJECT --quick`.

Between two dives there is about an hour on the surface; the full run of a long dive
does not fit, but what the divers need to plan the next dive does: where the camera
went, at what depth, the sparse structure it saw, and which parts of it were seen
badly or not at all. The quick look runs the session stages that give that
(calibrate, import, slam, depth) with a lighter SLAM (half the width, 10 images a
second, a keyframe a second, a shorter smoother window, no final batch, no keyframe
images, a looser pose graph chain: `quick_project`), then draws one page from their folders.

Layout, inside the project's output folder::

    imports/<session>/ calibration/   shared with the full run (same place, same digest:
                                       the full run finds them done and keeps them)
    quick/sessions/<session>/         SLAM at `width_px` (SlamFolder) and its depth/
    quick/quick.html                  the page (opens offline)
    quick/coverage/                   coverage_<session>.png, coverage.json

Coverage comes from the SLAM landmarks (the sparse map): each landmark stands for an
equal share of the surface and faces its nearest keyframe camera (`facing_normals`),
so the maps say where the dive looked from how far and how often, not where the
final mesh will have holes (the full run's report gives that from the mesh).

Frames: each session in its own frame S (gravity-aligned, z up) shifted in z to the
true depth with the depth stage's per-frame correction (x, y and yaw kept: sessions are
not merged, so each gets its own maps). A session whose depth did not sync stays in S
(the page says so).
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import html
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.pipeline.project import Project
from postproc.pipeline.stages import STAGES, RunFolders, Stage
from shared.fsutil import write_text_atomic

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

QUICK_STAGES = ("calibrate", "import", "slam", "depth")
# Stages whose folders stay where the full run puts them (their options are the
# full run's, so the full run reuses them).
SHARED_STAGES = ("calibrate", "import")
QUICK_FOLDER = "quick"
QUICK_WIDTH_PX = 480
# The quick look's SLAM, besides the width: images at most this rate, a keyframe at
# least this often (the full run: 0.5 s), no final batch adjustment of the window.
QUICK_RATE_HZ = 10.0
QUICK_KEYFRAME_INTERVAL_S = 1.0
# And a shorter smoother window (the full run: 150 keyframes, retired 100 at a time).
# On bench_pipeline.py's 10-minute dive the quick look's SLAM took 117.7 s with it
# against 124.4-135.2 s (ATE 3.3 against 2.9 cm), and its 3-minute prefix, 188
# keyframes, now fills the window too, so the 45-minute projection no longer counts
# the window filling up as growth (k 0.95 against 1.12-1.23). 60 / 40: 115.3 s, 6.7 cm.
QUICK_WINDOW_KEYFRAMES = 100
QUICK_WINDOW_STEP = 50
# And fewer features (the full run: 400 at 960 px, four times the quick look's image
# area). bench_pipeline.py's 10-minute dive and its 3-minute prefix, both from the H.264
# session, one run each in one sitting (quick SLAM seconds at 10 / 3 minutes, ATE at 10 /
# 3): 400 features 117.5 / 32.7 s, 2.7 / 1.6 cm; 300: 86.6 / 23.6 s, 3.6 / 1.9 cm; 250:
# 80.3 / 23.6 s, 3.9 / 2.0 cm. The smoother's cost grows faster than the landmarks
# (estimator CPU 73.6 s at 400, 45.2 s at 300).
QUICK_MAX_FEATURES = 300
# And a global pose graph whose chain of consecutive keyframes is this many times less
# certain than the project's (the full run: 1 cm and 0.003 rad per link). Its keyframes
# are a second apart and tracked at half the width, so a link can be off by several
# centimetres; with the full run's sigmas the chain outweighed the loops that should have
# corrected such a stretch (their Cauchy loss set them aside). bench_pipeline.py's
# 10-minute dive, the same online run each time: ATE 15.9 cm with x1, 5.7 with x2,
# 5.5 with x3, 7.1 with x5.
QUICK_POSE_GRAPH_SCALE = 3.0
# The quick pass tracks every third image of a 30 fps video, so a gyro seed spans three
# images of motion it does not predict (the translation): it keeps the unseeded KLT
# window (15 px) instead of the full run's seeded 11 px. On the real karma.mp4 the quick
# path was 7.16 % of the drone's own log at 11 px against 3.79 % at 15 (the same at bias
# lags 8-60; docs/benchmarks.md, SLAM, stop 51); tracking a third of the images, the
# larger window costs the quick look little.
QUICK_PAGE = "quick.html"


def quick_project(project: Project, *, width_px: int = QUICK_WIDTH_PX) -> Project:
    """`project` for the quick look: output in `<output>/quick`; SLAM with frontend
    images shrunk to `width_px`, at most `QUICK_RATE_HZ` images a second, a keyframe at
    least every `QUICK_KEYFRAME_INTERVAL_S`, a smoother window of at most
    `QUICK_WINDOW_KEYFRAMES`, at most `QUICK_MAX_FEATURES` tracked features, no final
    batch and no keyframe images (the page draws none; never more work than the
    project's own settings ask), a pose graph chain `QUICK_POSE_GRAPH_SCALE` times
    looser than the project's, and the project's unseeded KLT window for seeded flow
    too (its images are three steps apart)."""
    stage_options = dict(project.stage_options)
    slam = copy.deepcopy(project.options_for("slam"))
    current = int(slam.frontend.width_px)
    slam.frontend.width_px = width_px if current <= 0 else min(width_px, current)
    slam.frontend.max_features = min(slam.frontend.max_features, QUICK_MAX_FEATURES)
    slam.frontend.klt_window_px = max(
        slam.frontend.klt_window_px, slam.frontend.klt_window_unseeded_px
    )
    rate = slam.max_rate_hz
    slam.max_rate_hz = QUICK_RATE_HZ if rate is None else min(rate, QUICK_RATE_HZ)
    keyframes = slam.estimator.keyframes
    keyframes.max_interval_s = max(keyframes.max_interval_s, QUICK_KEYFRAME_INTERVAL_S)
    slam.estimator.backend.final_batch = False
    slam.keyframe_images = False
    backend = slam.estimator.backend
    window = backend.window_keyframes
    backend.window_keyframes = (
        QUICK_WINDOW_KEYFRAMES if window <= 0 else min(window, QUICK_WINDOW_KEYFRAMES)
    )
    backend.window_step_keyframes = min(backend.window_step_keyframes, QUICK_WINDOW_STEP)
    backend.pose_graph_rotation_sigma_rad *= QUICK_POSE_GRAPH_SCALE
    backend.pose_graph_translation_sigma_m *= QUICK_POSE_GRAPH_SCALE
    stage_options["slam"] = slam
    return dataclasses.replace(
        project, output=project.output / QUICK_FOLDER, stage_options=stage_options
    )


def quick_stages(project: Project, stages: Mapping[str, Stage] | None = None) -> dict[str, Stage]:
    """The registry entries of the quick look; the shared ones placed in the full run's
    output folder (`project` is the full project)."""
    registry = STAGES if stages is None else stages
    chosen: dict[str, Stage] = {}
    for name in QUICK_STAGES:
        if name not in registry:
            continue
        stage = registry[name]
        if name in SHARED_STAGES:
            stage = dataclasses.replace(stage, place=_in_full_run(stage.place, project.output))
        chosen[name] = stage
    return chosen


def _in_full_run(
    place: Callable[[Path, str | None], Path], output: Path
) -> Callable[[Path, str | None], Path]:
    def placed(_quick_output: Path, session: str | None) -> Path:
        return place(output, session)

    return placed


def run_quick(
    project: Project,
    *,
    backend: Any | None = None,
    width_px: int = QUICK_WIDTH_PX,
    force: bool = False,
    echo: Callable[[str], None] | None = None,
) -> tuple[Any, Path]:
    """Run the quick look of `project` (the full project) and write its page; returns
    the run's result (`runner.RunResult`) and the page's path."""
    from postproc.pipeline.runner import run_project

    quick = quick_project(project, width_px=width_px)
    result = run_project(
        quick, backend=backend, stages=quick_stages(project), force=force, echo=echo
    )
    page = write_quick_page(quick, result=result)
    return result, page


# ------------------------------------------------------------------------------ reading


@dataclass(kw_only=True)
class QuickSession:
    """What the quick look has of one session, in its depth-corrected frame (see the
    module docstring): landmarks (N,3 m), keyframe poses `T_W_C` (K,4,4), the body path
    (M,3 m) with its stamps (ns), the camera model and notes."""

    name: str
    landmarks_m: FloatArray
    world_from_cam: FloatArray
    path_m: FloatArray
    path_stamps_ns: npt.NDArray[np.int64]
    camera: Any = None
    at_depth: bool = False
    stats: dict[str, Any] = field(default_factory=dict)
    sync: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def read_quick_session(out: Path, name: str) -> QuickSession | None:
    """The session `name` of the quick run in `out` (None: no complete SLAM folder)."""
    from shared.formats.ply import read_ply

    slam = RunFolders(out).slam(name)
    if not slam.is_complete():
        return None
    trajectory = slam.read_trajectory()
    keyframes = slam.read_keyframes()
    landmarks = np.asarray(read_ply(slam.map_ply).vertices, dtype=np.float64).reshape(-1, 3)
    session = QuickSession(
        name=name,
        landmarks_m=landmarks.copy(),
        world_from_cam=np.asarray(keyframes.poses, dtype=np.float64).copy(),
        path_m=np.asarray(trajectory.positions, dtype=np.float64).copy(),
        path_stamps_ns=np.asarray(trajectory.stamps_ns, dtype=np.int64),
        stats=slam.read_stats(),
    )
    try:
        session.camera = slam.read_camchain()[0].camera
    except Exception as error:  # a page shows what it can
        session.notes.append(f"camera model unreadable ({error}): no coverage")
    depth = slam.depth
    if not depth.is_complete():
        session.notes.append("depth not synced: the session's own frame (z = 0 at the start)")
        return session
    world = depth.read_world()
    session.sync = depth.read_sync()
    # The depth stage keeps x, y and the stamps and moves z: the move per frame,
    # applied to the keyframes at their stamps and to the map by its median.
    stamps = np.asarray(world.stamps_ns, dtype=np.int64)
    if len(stamps) != len(trajectory.stamps_ns) or np.any(stamps != trajectory.stamps_ns):
        session.notes.append("depth trajectory does not match the SLAM stamps: not applied")
        return session
    shift = np.asarray(world.positions, dtype=np.float64)[:, 2] - session.path_m[:, 2]
    t = (stamps - stamps[0]).astype(np.float64)
    kf_t = (np.asarray(keyframes.stamps_ns, dtype=np.int64) - stamps[0]).astype(np.float64)
    session.world_from_cam[:, 2, 3] += np.interp(kf_t, t, shift)
    session.landmarks_m[:, 2] += float(np.median(shift))
    session.path_m[:, 2] += shift
    session.at_depth = True
    return session


# ------------------------------------------------------------------------------ drawing


def session_coverage(session: QuickSession) -> Any:
    """The coverage maps of one session from its landmarks (`coverage_report.RunCoverage`
    labelled with the session's name), or None when it has no camera or no map."""
    from postproc.pipeline.coverage import (
        VIEWS,
        CoverageOptions,
        KeyframeViews,
        aggregate,
        auto_cell_m,
        coverage_map,
        sightings,
        surface_from_points,
    )
    from postproc.pipeline.coverage_report import RunCoverage

    if session.camera is None or len(session.landmarks_m) < 10 or not len(session.world_from_cam):
        return None
    points = session.landmarks_m
    surface = surface_from_points(points, facing_normals(points, session.world_from_cam))
    options = CoverageOptions()
    views = KeyframeViews(
        name=session.name, world_from_cam=session.world_from_cam, camera=session.camera
    )
    seen = aggregate(len(points), [sightings(surface, views, options)], options)
    cell = auto_cell_m(surface)
    coverage = RunCoverage(options=options)
    coverage.surface_source = f"sessions/{session.name} SLAM landmarks ({len(points)})"
    coverage.maps[session.name] = {
        view: coverage_map(surface, seen, view, options, cell_m=cell) for view in VIEWS
    }
    coverage.keyframes[session.name] = len(session.world_from_cam)
    coverage.camera_paths_m[session.name] = session.world_from_cam[:, :3, 3]
    coverage.surface, coverage.merged_score = surface, seen.score
    return coverage


def facing_normals(points_m: FloatArray, world_from_cam: FloatArray) -> FloatArray:
    """A stand-in normal per landmark: the unit vector towards the nearest keyframe
    camera (a landmark was seen, so the surface there faces some camera; the nearest
    is the likeliest). Enough to tell the two sides of a wreck apart in the maps; the
    incidence test is then optimistic for that camera."""
    from scipy.spatial import cKDTree

    centres = world_from_cam[:, :3, 3]
    _, nearest = cKDTree(centres).query(points_m)
    towards = centres[nearest] - points_m
    norm = np.linalg.norm(towards, axis=1, keepdims=True)
    return np.asarray(towards / np.maximum(norm, 1e-9), dtype=np.float64)


def path_png(session: QuickSession) -> bytes:
    """Top view and depth profile of the body path, the landmarks behind it."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, profile) = plt.subplots(
        1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [1, 1.4]}, layout="constrained"
    )
    land = session.landmarks_m
    if len(land):
        top.plot(land[:, 0], land[:, 1], ".", ms=1, color="#999999", label="landmarks")
    top.plot(session.path_m[:, 0], session.path_m[:, 1], "-", lw=1.0, color="#d62728",
             label="camera path")  # fmt: skip
    top.plot(session.path_m[:1, 0], session.path_m[:1, 1], "o", color="#d62728", ms=5)
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.legend(loc="best", fontsize=7)
    top.set_title("from above (start: dot)", fontsize=10)
    minutes = (session.path_stamps_ns - session.path_stamps_ns[0]) / 60e9
    z = session.path_m[:, 2]
    profile.plot(minutes, -z if session.at_depth else z, "-", lw=1.0, color="#1f77b4")
    if session.at_depth:
        profile.invert_yaxis()
        profile.set_ylabel("depth (m)")
        profile.set_title("depth along the dive (dive computer synced)", fontsize=10)
    else:
        profile.set_ylabel("z (m, session frame)")
        profile.set_title("height along the dive (not synced to the dive computer)", fontsize=10)
    profile.set_xlabel("minutes into the recording")
    profile.grid(alpha=0.3)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def _summary_rows(session: QuickSession) -> list[tuple[str, Any]]:
    stats, sync = session.stats, session.sync
    rows: list[tuple[str, Any]] = [
        ("frames", stats.get("frames")),
        ("frontend width (px)", stats.get("frontend_width_px")),
        ("keyframes", len(session.world_from_cam)),
        ("landmarks", len(session.landmarks_m)),
        ("recording (s)", stats.get("sequence_duration_s")),
        ("SLAM (s)", stats.get("run_time_s")),
        ("real-time factor", stats.get("real_time_factor")),
        ("path length (m)", stats.get("path_length_m")),
    ]
    if session.at_depth:
        depth = -session.path_m[:, 2]
        rows += [
            ("dive clock offset (s)", sync.get("time_offset_s")),
            ("depth range (m)", f"{float(depth.min()):.1f} to {float(depth.max()):.1f}"),
            ("depth residual RMS (m)", sync.get("residual_rms_m")),
        ]
    return rows


def build_quick_page(quick: Project, *, result: Any = None) -> str:
    """The quick look's page for the quick project `quick` (see `quick_project`)."""
    from postproc.pipeline.coverage_report import coverage_png, gap_rows, write_coverage
    from postproc.pipeline.report import _STYLE, _status_rows, _table, png_data_uri
    from postproc.pipeline.viewer import SessionPath, ViewerScene, viewer_html

    out = quick.output
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    slam = quick.options_for("slam")
    head = [
        f"<h1>{html.escape(quick.name)}: quick look</h1>",
        f"<p class='small'>output {html.escape(str(out))}; {now}. SLAM at "
        f"{slam.frontend.width_px} px wide, at most {slam.max_rate_hz:g} images a second "
        f"and {slam.frontend.max_features} features, a keyframe at least every "
        f"{slam.estimator.keyframes.max_interval_s:g} s; depth "
        "from the dive computer, coverage from the SLAM landmarks; no merge, SfM or mesh "
        "(the full `wreckmap-post run` gives those).</p>",
    ]
    body = ["<h2>Stage runs</h2>", _status_rows(quick, result)]
    scene = ViewerScene()
    clouds: list[FloatArray] = []
    for spec in quick.sessions:
        body.append(f"<h2>Session {html.escape(spec.name)}</h2>")
        try:
            session = read_quick_session(out, spec.name)
        except Exception as error:  # a page shows what it can
            body.append(f"<p class='missing'>unreadable: {html.escape(str(error))}</p>")
            continue
        if session is None:
            body.append("<p class='missing'>no SLAM result (see the stage runs)</p>")
            continue
        body.append(_table(_summary_rows(session)))
        body.append(
            f'<p><img alt="path {html.escape(spec.name)}" '
            f'src="{png_data_uri(path_png(session))}"></p>'
        )
        coverage = None
        try:
            coverage = session_coverage(session)
            if coverage is None:
                session.notes.append(
                    f"no coverage map: {len(session.landmarks_m)} landmarks, "
                    f"{len(session.world_from_cam)} keyframes"
                    + ("" if session.camera is not None else ", no camera model")
                )
        except Exception as error:  # a page shows what it can
            session.notes.append(f"coverage failed: {error}")
        if coverage is not None:
            write_coverage(out, coverage)
            rows = gap_rows(coverage, spec.name)
            body.append("<h3>Coverage</h3>")
            uri = png_data_uri(coverage_png(coverage, spec.name))
            body.append(f'<p><img alt="coverage {html.escape(spec.name)}" src="{uri}"></p>')
            if rows:
                body.append(
                    "<p class='small'>largest gaps (view, centre x y z m, depth m, area m², "
                    "short of): "
                    + "; ".join(
                        f"{r['view']} ({', '.join(f'{v:.1f}' for v in r['centre_m'])}), "
                        f"{r['depth_m']:.1f} m, {r['area_m2']:.2f} m², {r['limited_by']}"
                        for r in rows[:5]
                    )
                    + "</p>"
                )
        if session.notes:
            body.append("<p class='small'>" + html.escape("; ".join(session.notes)) + "</p>")
        scene.sessions.append(
            SessionPath(
                name=spec.name,
                world_from_cam=session.world_from_cam,
                source=f"{QUICK_FOLDER}/sessions/{spec.name}",
                in_world=session.at_depth,
            )
        )
        clouds.append(session.landmarks_m)
    if clouds and len(quick.sessions) == 1:
        scene.points_m = np.vstack(clouds)
        scene.points_full_count = len(scene.points_m)
        scene.points_file = "SLAM landmarks"
        head += ["<h2>Sparse map</h2>", viewer_html(scene)]
    elif len(quick.sessions) > 1:
        body.append(
            "<p class='small'>Each session is drawn in its own frame: the quick look does "
            "not merge sessions (the full run does).</p>"
        )
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>{html.escape(quick.name)}: wreckmap quick look</title><style>{_STYLE}</style>"
        "</head><body>" + "\n".join(head + body) + "</body></html>\n"
    )


def write_quick_page(quick: Project, *, result: Any = None) -> Path:
    """`quick/quick.html` of the quick project `quick`."""
    path = quick.output / QUICK_PAGE
    write_text_atomic(path, build_quick_page(quick, result=result), overwrite=True)
    return path


__all__ = [
    "QUICK_STAGES",
    "QuickSession",
    "build_quick_page",
    "quick_project",
    "quick_stages",
    "read_quick_session",
    "run_quick",
    "session_coverage",
    "write_quick_page",
]
