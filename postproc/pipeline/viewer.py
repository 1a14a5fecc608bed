"""The 3D viewer at the top of report.html: the run's model in three.js, inline.

What it shows, read from the run folder (`runner.py` documents the layout): the mesh
(`dense/mesh.ply`, vertex colours), the fused points (`dense/fused.ply`), every session's
keyframe camera path and poses in the world frame (`sfm/sessions/<name>/
keyframes_world.tum`, else `merge/<name>/keyframes_merged.tum`, else the SLAM
`sessions/<name>/keyframes.tum` in its own frame) and the AprilGrid targets
(`merge/targets.json`, their size from the target YAMLs).

The page carries at most `MESH_TRIANGLE_BUDGET` triangles (200k) and `POINT_BUDGET`
points (300k): a larger mesh is vertex-clustered and a larger cloud subsampled
(`decimate.py`); the full files stay in `dense/`. Positions travel as uint16 over the
scene's bounding box (0.3 mm steps on a 20 m wreck), colours as uint8, indices as
uint32, base64 in a JSON block. three.js comes from `node_modules/.wreckmap/
three-bundle.js` (three pinned in package.json, bundled by `npm run build`, which
deploy/setup.sh runs) and is inlined with the viewer script (`web/viewer.js`), so the
page opens offline from the file alone: nothing is fetched.
"""

from __future__ import annotations

import base64
import html
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from postproc.pipeline.decimate import (
    MESH_TRIANGLE_BUDGET,
    POINT_BUDGET,
    decimate_mesh,
    subsample_points,
)
from shared.errors import InputError

if TYPE_CHECKING:
    from shared.trajectory import Trajectory

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
WEB_DIR = Path(__file__).resolve().parent / "web"
REPO = Path(__file__).resolve().parents[2]
THREE_BUNDLE = REPO / "node_modules" / ".wreckmap" / "three-bundle.js"
# One colour per session, as in the coverage plots (matplotlib's tab10).
SESSION_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                   "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")  # fmt: skip


@dataclass(kw_only=True)
class SessionPath:
    """A session's keyframe camera poses `T_W_C` (K,4,4, m), the file they came from and
    whether they are in the world frame (False: the session's own SLAM frame)."""

    name: str
    world_from_cam: FloatArray
    source: str
    in_world: bool


@dataclass(kw_only=True)
class TargetPlacement:
    """An AprilGrid target: pose `T_W_m` (4x4, m) and its tag area (width, height) m."""

    name: str
    world_from_target: FloatArray
    extent_m: tuple[float, float]


@dataclass(kw_only=True)
class ViewerScene:
    """Everything the viewer draws, in W (m); `notes` say what is missing and why."""

    mesh_vertices_m: FloatArray | None = None
    mesh_faces: npt.NDArray[np.int64] | None = None
    mesh_colours: npt.NDArray[np.uint8] | None = None
    mesh_full_triangles: int = 0
    mesh_cell_m: float = 0.0
    mesh_file: str = ""
    mesh_coverage: npt.NDArray[np.float64] | None = None
    points_m: FloatArray | None = None
    point_colours: npt.NDArray[np.uint8] | None = None
    points_full_count: int = 0
    points_file: str = ""
    sessions: list[SessionPath] = field(default_factory=list)
    targets: list[TargetPlacement] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def keyframe_sources(out: Path, name: str) -> list[tuple[Path, Callable[[], Trajectory], bool]]:
    """Where a session's keyframe poses may be, best first: the file, its reader and
    whether the poses are in the world frame."""
    from postproc.pipeline.stages import RunFolders

    folders = RunFolders(out)
    sfm, merge, slam = folders.sfm(), folders.merge(), folders.slam(name)
    return [
        (sfm.session_keyframes_world(name), partial(sfm.read_session_keyframes_world, name), True),
        (merge.merged_keyframes(name), partial(merge.read_merged_keyframes, name), True),
        (slam.keyframes_tum, slam.read_keyframes, False),
    ]


def read_session_paths(out: Path, names: list[str]) -> tuple[list[SessionPath], list[str]]:
    """Each session's best keyframe poses (see `keyframe_sources`), and notes."""
    paths, notes = [], []
    for name in names:
        for path, read, in_world in keyframe_sources(out, name):
            if not path.is_file():
                continue
            try:
                trajectory = read()
            except Exception as error:  # a report shows what it can
                notes.append(f"{name}: {path.name} unreadable ({error})")
                continue
            paths.append(
                SessionPath(
                    name=name,
                    world_from_cam=np.asarray(trajectory.poses, dtype=np.float64),
                    source=str(path.relative_to(out)),
                    in_world=in_world,
                )
            )
            if not in_world:
                notes.append(f"{name}: keyframes in the session's own frame (not merged)")
            break
        else:
            notes.append(f"{name}: no keyframe poses yet")
    return paths, notes


def read_targets(out: Path) -> list[TargetPlacement]:
    """The targets placed by the merge (`merge/targets.json`); extents from their YAMLs
    (0.5 m square when a YAML cannot be read)."""
    from postproc.pipeline.stages import RunFolders
    from shared.calibration.kalibr import read_target_yaml

    try:
        document = RunFolders(out).merge().read_targets()
    except InputError:
        return []
    targets = []
    for name, entry in sorted(document.items()):
        if not isinstance(entry, dict) or "T_W_m" not in entry:
            continue
        extent = (0.5, 0.5)
        try:
            extent = read_target_yaml(Path(entry["file"])).extent_m
        except Exception as error:  # the pose is still worth drawing
            log.info("%s: target size unknown (%s)", entry.get("file"), error)
        targets.append(
            TargetPlacement(
                name=str(name),
                world_from_target=np.asarray(entry["T_W_m"], dtype=np.float64),
                extent_m=(float(extent[0]), float(extent[1])),
            )
        )
    return targets


def load_scene(
    out: Path,
    session_names: list[str],
    *,
    max_triangles: int = MESH_TRIANGLE_BUDGET,
    max_points: int = POINT_BUDGET,
    coverage: Any = None,
) -> ViewerScene:
    """The viewer's scene from a run folder, decimated to the budgets; with `coverage`
    (a `coverage_report.RunCoverage`) each mesh vertex also gets the score of the
    nearest coverage sample (all sessions), for the "colour by coverage" toggle."""
    from shared.formats.ply import read_ply

    scene = ViewerScene()
    from postproc.pipeline.stages import RunFolders

    dense = RunFolders(out).dense()
    mesh_path, fused_path = dense.mesh, dense.fused
    if mesh_path.is_file():
        try:
            ply = read_ply(mesh_path)
            if ply.faces is None or len(ply.faces) == 0:
                raise InputError(f"{mesh_path}: no faces")
            small = decimate_mesh(ply.vertices, ply.faces, ply.colors, max_triangles=max_triangles)
            scene.mesh_vertices_m = small.vertices_m
            scene.mesh_faces = small.faces
            scene.mesh_colours = small.colours
            scene.mesh_full_triangles = len(ply.faces)
            scene.mesh_cell_m = small.cell_m
            scene.mesh_file = str(mesh_path.relative_to(out))
            if coverage is not None and coverage.merged_score is not None:
                from scipy.spatial import cKDTree

                tree = cKDTree(coverage.surface.points_m)
                _, nearest = tree.query(small.vertices_m)
                scene.mesh_coverage = np.asarray(coverage.merged_score)[nearest]
        except Exception as error:  # a report shows what it can
            scene.notes.append(f"mesh: {error}")
    else:
        scene.notes.append("mesh: dense/mesh.ply not there (dense stage not run)")
    if fused_path.is_file():
        try:
            ply = read_ply(fused_path)
            keep = subsample_points(len(ply.vertices), max_points=max_points)
            scene.points_m = ply.vertices[keep]
            scene.point_colours = None if ply.colors is None else ply.colors[keep]
            scene.points_full_count = len(ply.vertices)
            scene.points_file = str(fused_path.relative_to(out))
        except Exception as error:  # a report shows what it can
            scene.notes.append(f"points: {error}")
    scene.sessions, notes = read_session_paths(out, session_names)
    scene.notes += notes
    scene.targets = read_targets(out)
    return scene


def _b64(array: npt.NDArray[Any]) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


def _quantised(points_m: FloatArray, lo: FloatArray, step: FloatArray) -> dict[str, Any]:
    q = np.clip(np.rint((points_m - lo) / step), 0, 65535).astype("<u2")
    return {"count": len(points_m), "data": _b64(q)}


def scene_document(scene: ViewerScene) -> dict[str, Any]:
    """The scene as the JSON the viewer script reads (see `web/viewer.js`).

    Positions: uint16 triples, world = `min_m` + q * `step_m`; colours: uint8 triples;
    faces: uint32 triples; poses: 16 floats row-major. Everything in W, metres."""
    clouds = [a for a in (scene.mesh_vertices_m, scene.points_m) if a is not None and len(a)]
    clouds += [s.world_from_cam[:, :3, 3] for s in scene.sessions if len(s.world_from_cam)]
    clouds += [t.world_from_target[None, :3, 3] for t in scene.targets]
    if clouds:
        every = np.vstack(clouds)
        lo, hi = every.min(axis=0), every.max(axis=0)
    else:
        lo, hi = np.zeros(3), np.ones(3)
    step = np.maximum(hi - lo, 1e-6) / 65535.0
    document: dict[str, Any] = {
        "min_m": lo.tolist(),
        "step_m": step.tolist(),
        "mesh": None,
        "points": None,
        "sessions": [],
        "targets": [],
        "notes": scene.notes,
    }
    if scene.mesh_vertices_m is not None and scene.mesh_faces is not None:
        document["mesh"] = {
            "positions": _quantised(scene.mesh_vertices_m, lo, step),
            "colours": None if scene.mesh_colours is None else _b64(scene.mesh_colours),
            "faces": _b64(scene.mesh_faces.astype("<u4")),
            "triangles": len(scene.mesh_faces),
            "full_triangles": scene.mesh_full_triangles,
            "cell_m": scene.mesh_cell_m,
            "file": scene.mesh_file,
            # Coverage score per vertex, 0..255 (None: not computed).
            "coverage": None
            if scene.mesh_coverage is None
            else _b64(np.clip(np.rint(scene.mesh_coverage * 255), 0, 255).astype(np.uint8)),
        }
    if scene.points_m is not None:
        document["points"] = {
            "positions": _quantised(scene.points_m, lo, step),
            "colours": None if scene.point_colours is None else _b64(scene.point_colours),
            "full_count": scene.points_full_count,
            "file": scene.points_file,
        }
    for k, session in enumerate(scene.sessions):
        document["sessions"].append(
            {
                "name": session.name,
                "colour": SESSION_COLOURS[k % len(SESSION_COLOURS)],
                "poses": np.round(session.world_from_cam.reshape(-1, 16), 5).tolist(),
                "source": session.source,
                "in_world": session.in_world,
            }
        )
    for target in scene.targets:
        document["targets"].append(
            {
                "name": target.name,
                "pose": np.round(target.world_from_target.reshape(16), 6).tolist(),
                "extent_m": list(target.extent_m),
            }
        )
    return document


def three_bundle() -> str:
    """The bundled three.js (a classic script defining `THREE`); InputError when the npm
    install step has not run."""
    try:
        text = THREE_BUNDLE.read_text(encoding="utf-8")
    except OSError as error:
        raise InputError(
            f"{THREE_BUNDLE}: three.js bundle missing (expected `npm ci && npm run build` "
            "at the repository top, which deploy/setup.sh runs)"
        ) from error
    # "://" occurs only inside string literals (the XHTML namespace name); with its
    # slashes escaped it means the same to JavaScript and the page holds no URL-like text.
    return text.replace("://", ":\\/\\/")


def _script(text: str) -> str:
    # Inline scripts end at the first "</script": none may appear inside.
    return "<script>" + text.replace("</script", "<\\/script") + "</script>"


def viewer_html(scene: ViewerScene) -> str:
    """The viewer's HTML: container, controls, the scene JSON, three.js and the viewer
    script, all inline. Without the three.js bundle: a line saying how to get it."""
    try:
        library = three_bundle()
    except InputError as error:
        return f"<p class='missing'>3D viewer not available: {html.escape(str(error))}</p>"
    scene_json = json.dumps(scene_document(scene), separators=(",", ":"))
    viewer_js = (WEB_DIR / "viewer.js").read_text(encoding="utf-8")
    style = (WEB_DIR / "viewer.css").read_text(encoding="utf-8")
    return (
        f"<style>{style}</style>"
        "<div id='wm-viewer'><canvas id='wm-canvas'></canvas>"
        "<div id='wm-panel'></div><div id='wm-scalebar'><div></div><span></span></div>"
        "<div id='wm-labels'></div></div>"
        "<p class='small' id='wm-info'></p>"
        "<script type='application/json' id='wm-scene'>"
        + scene_json.replace("</", "<\\/")
        + "</script>"
        + _script(library)
        + _script(viewer_js)
    )
