"""Coverage maps of a run for the next dive: PNGs, JSON and the report's section.

I/O around `coverage.py`: reads the run folder (the mesh, else the fused points; each
session's world keyframes and its camera model from `sessions/<name>/calib/
camchain.yaml`; the targets), computes the coverage per session and for all sessions
together, draws a top and two side views each (cells coloured by the score, gaps
outlined and numbered, targets marked) and writes into `<run>/coverage/`:

- `coverage_<session>.png`, `coverage_merged.png`: the maps;
- `coverage.json`: options, per map the cell size and the gaps (centre in W, area, part
  with no surface, mean score, nearest target and the offset from it).

The surface is the mesh cut to `COVERAGE_TRIANGLES` by vertex clustering (the test is
per face centre and keyframe; the z-buffer that decides occlusion uses the same mesh).
"""

from __future__ import annotations

import html
import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from postproc.pipeline.coverage import (
    VIEWS,
    CoverageMap,
    CoverageOptions,
    Gap,
    KeyframeViews,
    SurfaceSamples,
    aggregate,
    auto_cell_m,
    coverage_map,
    nearest_target,
    sightings,
    surface_from_mesh,
    surface_from_points,
)
from postproc.pipeline.viewer import SESSION_COLOURS
from shared.fsutil import write_bytes_atomic, write_text_atomic

log = logging.getLogger(__name__)

COVERAGE_TRIANGLES = 30_000
COVERAGE_POINTS = 60_000
LISTED_GAPS = 8
VIEW_TITLES = {
    "top": "top (from above)",
    "side_pos": "side (from +b)",
    "side_neg": "side (from -b)",
}


@dataclass(kw_only=True)
class RunCoverage:
    """The maps of one run: per label (a session's name, or "merged") the maps of the
    three views; the targets (name -> `T_W_m`); what was left out and why; the surface
    samples and their score from all sessions (for the viewer's coverage colouring)."""

    maps: dict[str, dict[str, CoverageMap]] = field(default_factory=dict)
    keyframes: dict[str, int] = field(default_factory=dict)
    targets: dict[str, np.ndarray] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    surface_source: str = ""
    options: CoverageOptions = field(default_factory=CoverageOptions)
    surface: SurfaceSamples | None = None
    merged_score: np.ndarray | None = None
    camera_paths_m: dict[str, np.ndarray] = field(default_factory=dict)


def _surface(out: Path) -> tuple[SurfaceSamples, tuple[Any, Any] | None, str] | None:
    from postproc.pipeline.decimate import decimate_mesh, subsample_points
    from postproc.pipeline.stages import RunFolders
    from shared.formats.ply import read_ply

    dense = RunFolders(out).dense()
    mesh_path, fused_path = dense.mesh, dense.fused
    if mesh_path.is_file():
        ply = read_ply(mesh_path)
        if ply.faces is not None and len(ply.faces):
            small = decimate_mesh(ply.vertices, ply.faces, None, max_triangles=COVERAGE_TRIANGLES)
            surface = surface_from_mesh(small.vertices_m, small.faces)
            return surface, (small.vertices_m, small.faces), _relative(mesh_path, out)
    if fused_path.is_file():
        ply = read_ply(fused_path)
        keep = subsample_points(len(ply.vertices), max_points=COVERAGE_POINTS)
        points = ply.vertices[keep]
        normals = None if ply.normals is None else ply.normals[keep]
        surface = surface_from_points(points, normals)
        return surface, None, _relative(fused_path, out)
    return None


def _relative(path: Path, out: Path) -> str:
    return path.relative_to(out).as_posix()


def compute_run_coverage(
    out: Path, session_names: list[str], options: CoverageOptions | None = None
) -> RunCoverage:
    """Coverage of the run in `out` per session and merged (empty maps with notes when
    the dense stage or the keyframes are not there)."""
    from postproc.pipeline.stages import RunFolders
    from postproc.pipeline.viewer import read_session_paths, read_targets

    options = options or CoverageOptions()
    result = RunCoverage(options=options)
    result.targets = {t.name: t.world_from_target for t in read_targets(out)}
    found = _surface(out)
    if found is None:
        dense = RunFolders(out).dense()
        result.notes.append(
            f"no {_relative(dense.mesh, out)} or {_relative(dense.fused, out)} "
            "(dense stage not run)"
        )
        return result
    surface, occluder, result.surface_source = found
    paths, notes = read_session_paths(out, session_names)
    result.notes += notes
    sessions: list[KeyframeViews] = []
    for path in paths:
        if not path.in_world:
            result.notes.append(f"{path.name}: left out (keyframes not in the world frame)")
            continue
        try:
            camera = RunFolders(out).slam(path.name).read_camchain()[0].camera
        except Exception as error:  # a report shows what it can
            result.notes.append(f"{path.name}: left out (camera model: {error})")
            continue
        sessions.append(
            KeyframeViews(name=path.name, world_from_cam=path.world_from_cam, camera=camera)
        )
        result.keyframes[path.name] = len(path.world_from_cam)
        result.camera_paths_m[path.name] = path.world_from_cam[:, :3, 3]
    if not sessions:
        result.notes.append("no session with world keyframes and a camera model")
        return result
    cell = options.cell_m or auto_cell_m(surface)
    groups = [(s.name, [s]) for s in sessions] if len(sessions) > 1 else []
    groups.append(("merged", sessions))
    # Each session's sightings once; a group (one session, or all) aggregates them.
    seen_by = {s.name: sightings(surface, s, options, occluder=occluder) for s in sessions}
    for label, group in groups:
        seen = aggregate(len(surface.points_m), [seen_by[s.name] for s in group], options)
        if label == "merged":
            result.surface, result.merged_score = surface, seen.score
        result.maps[label] = {
            view: coverage_map(surface, seen, view, options, cell_m=cell) for view in VIEWS
        }
    return result


def gap_rows(coverage: RunCoverage, label: str = "merged") -> list[dict[str, Any]]:
    """The largest gaps of one label's maps (all views, largest first), each with its
    position relative to the nearest target."""
    gaps: list[Gap] = [g for m in coverage.maps.get(label, {}).values() for g in m.gaps]
    gaps.sort(key=lambda g: -g.area_m2)
    rows = []
    for gap in gaps[:LISTED_GAPS]:
        near = nearest_target(gap.centre_m, coverage.targets)
        rows.append(
            {
                "view": gap.view,
                "centre_m": [round(float(v), 3) for v in gap.centre_m],
                "depth_m": round(float(-gap.centre_m[2]), 2),
                "area_m2": round(gap.area_m2, 3),
                "no_surface_m2": round(gap.no_surface_m2, 3),
                "mean_score": round(gap.mean_score, 3),
                "median_views": gap.median_views,
                "median_spread_deg": round(gap.median_spread_deg, 1),
                "median_range_m": None
                if not np.isfinite(gap.median_range_m)
                else round(gap.median_range_m, 2),
                "limited_by": gap.limited_by,
                "nearest_target": None if near is None else near.target,
                "offset_from_target_m": None
                if near is None
                else [round(float(v), 2) for v in near.offset_m],
                "distance_to_target_m": None if near is None else round(near.distance_m, 2),
            }
        )
    return rows


def coverage_png(coverage: RunCoverage, label: str) -> bytes:
    """One label's three views side by side, as PNG."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    maps = coverage.maps[label]
    fig, axes = plt.subplots(
        1, 3, figsize=(16, 5.0), gridspec_kw={"width_ratios": [1.2, 1, 1]}, layout="constrained"
    )
    image = None
    for ax, view in zip(axes, VIEWS, strict=True):
        cmap = maps[view]
        extent = cmap.extent_m
        ax.imshow(
            np.where(cmap.holes, 1.0, np.nan), origin="lower", extent=extent,
            cmap=ListedColormap(["#555555"]), vmin=0, vmax=1, interpolation="nearest",
        )  # fmt: skip
        image = ax.imshow(
            cmap.score, origin="lower", extent=extent, cmap="RdYlGn", vmin=0.0, vmax=1.0,
            interpolation="nearest",
        )  # fmt: skip
        if cmap.gaps:
            u = cmap.origin_u_m + (np.arange(cmap.score.shape[1]) + 0.5) * cmap.cell_m
            v = cmap.origin_v_m + (np.arange(cmap.score.shape[0]) + 0.5) * cmap.cell_m
            ax.contour(u, v, (cmap.gap_labels > 0).astype(float), levels=[0.5],
                       colors="k", linewidths=1.0)  # fmt: skip
            for number, gap in enumerate(cmap.gaps[:LISTED_GAPS], start=1):
                cu, cv = gap.centre_m @ cmap.axis_u, gap.centre_m @ cmap.axis_v
                ax.text(
                    cu, cv, str(number), ha="center", va="center", fontsize=8,
                    fontweight="bold", color="k",
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "alpha": 0.7},
                )  # fmt: skip
        # The keyframe paths over the map (the session's colour, as in the viewer).
        for k, (name, path) in enumerate(coverage.camera_paths_m.items()):
            if label != "merged" and name != label:
                continue
            ax.plot(path @ cmap.axis_u, path @ cmap.axis_v, "-", lw=0.7, alpha=0.8,
                    color=SESSION_COLOURS[k % len(SESSION_COLOURS)], label=name)  # fmt: skip
        for name, pose in coverage.targets.items():
            p = pose[:3, 3]
            ax.plot(p @ cmap.axis_u, p @ cmap.axis_v, "s", color="#1f3fff", ms=6, mec="w")
            ax.annotate(name, (p @ cmap.axis_u, p @ cmap.axis_v), textcoords="offset points",
                        xytext=(4, 4), fontsize=7, color="#1f3fff")  # fmt: skip
        ax.set_aspect("equal")
        ax.set_title(VIEW_TITLES[view], fontsize=10)
        # The map's extent, not the paths', sets the limits.
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        if view == "top":
            if coverage.camera_paths_m:
                ax.legend(loc="lower left", fontsize=7, title="keyframe paths",
                          title_fontsize=7)  # fmt: skip
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
        else:
            ax.set_xlabel("along the wreck's long axis (m)")
            ax.set_ylabel("z (m, 0 = surface)")
    if image is not None:
        bar = fig.colorbar(image, ax=axes, fraction=0.02, pad=0.01)
        bar.set_label("coverage score (views x angles x range)")
    what = "all sessions" if label == "merged" else f"session {label}"
    count = sum(coverage.keyframes.values()) if label == "merged" else coverage.keyframes[label]
    fig.suptitle(
        f"Coverage, {what} ({count} keyframes; cell {maps['top'].cell_m:g} m): grey = no "
        "surface inside the outline, black outlines = gaps (numbered by size per view)",
        fontsize=10,
    )
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def write_coverage(out: Path, coverage: RunCoverage) -> dict[str, Path]:
    """`coverage/` in the run folder (see the module docstring): label -> PNG path."""
    folder = out / "coverage"
    written: dict[str, Path] = {}
    for label in coverage.maps:
        path = folder / f"coverage_{label}.png"
        write_bytes_atomic(path, coverage_png(coverage, label), overwrite=True)
        written[label] = path
    document = {
        "options": asdict(coverage.options),
        "surface": coverage.surface_source,
        "keyframes": coverage.keyframes,
        "notes": coverage.notes,
        "maps": {
            label: {
                view: {
                    "cell_m": m.cell_m,
                    "gaps": len(m.gaps),
                    "well_seen_fraction": _well_seen(m, coverage.options),
                }
                for view, m in maps.items()
            }
            for label, maps in coverage.maps.items()
        },
        "largest_gaps": {label: gap_rows(coverage, label) for label in coverage.maps},
    }
    write_text_atomic(folder / "coverage.json", json.dumps(document, indent=2) + "\n",
                      overwrite=True)  # fmt: skip
    return written


def _why_text(row: dict[str, Any]) -> str:
    """What a gap fell short of, with the medians of its samples."""
    if row["limited_by"] == "no surface":
        return "no surface"
    reach = "unseen" if row["median_range_m"] is None else f"{row['median_range_m']:.1f} m"
    return (
        f"{row['limited_by']} ({row['median_views']:g} views, "
        f"{row['median_spread_deg']:.0f} deg, {reach})"
    )


def _well_seen(cmap: CoverageMap, options: CoverageOptions) -> float:
    """Fraction of the outline's cells (surface or hole) scoring at least gap_score."""
    total = int(cmap.surface.sum() + cmap.holes.sum())
    good = int(np.sum(cmap.surface & (np.nan_to_num(cmap.score) >= options.gap_score)))
    return round(good / total, 4) if total else 0.0


def safe_run_coverage(out: Path, session_names: list[str]) -> RunCoverage:
    """`compute_run_coverage`, or an empty result whose note says why it failed."""
    try:
        return compute_run_coverage(out, session_names)
    except Exception as error:  # a report shows what it can
        log.warning("coverage failed: %s", error)
        return RunCoverage(notes=[f"coverage failed: {type(error).__name__}: {error}"])


def coverage_html(out: Path, coverage: RunCoverage) -> str:
    """The report's coverage section: maps per session and merged, the largest gaps
    (also writes `coverage/` in the run folder)."""
    from postproc.pipeline.report import png_data_uri

    if not coverage.maps:
        return (
            "<p class='missing'>not available: " + html.escape("; ".join(coverage.notes)) + "</p>"
        )
    written = write_coverage(out, coverage)
    o = coverage.options
    parts = [
        "<p class='small'>Surface "
        + html.escape(coverage.surface_source)
        + f"; a keyframe counts within {o.max_range_m:g} m, at most {o.max_incidence_deg:g} deg "
        f"incidence, unoccluded. Full marks: {o.min_views} keyframes, rays {o.min_spread_deg:g} "
        f"deg apart, nearest within {o.good_range_m:g} m; gaps score below {o.gap_score:g} "
        "or have no surface. Also in coverage/ (PNG, JSON).</p>"
    ]
    rows = gap_rows(coverage)
    if rows:
        head = ("<tr><th>#</th><th>view</th><th>area (m²)</th><th>no surface (m²)</th>"
                "<th>score</th><th>short of (views, spread, range)</th>"
                "<th>centre x, y, z (m)</th><th>depth (m)</th>"
                "<th>from target (dx, dy, dz m)</th><th>distance (m)</th></tr>")  # fmt: skip
        body = []
        for k, row in enumerate(rows, start=1):
            target = row["nearest_target"]
            offset = row["offset_from_target_m"]
            where = (
                "-"
                if target is None
                else f"{html.escape(target)}: {offset[0]:+.2f}, {offset[1]:+.2f}, {offset[2]:+.2f}"
            )
            centre = ", ".join(f"{v:.2f}" for v in row["centre_m"])
            distance = "-" if target is None else f"{row['distance_to_target_m']:.2f}"
            body.append(
                f"<tr><td>{k}</td><td>{row['view']}</td><td>{row['area_m2']:.2f}</td>"
                f"<td>{row['no_surface_m2']:.2f}</td><td>{row['mean_score']:.2f}</td>"
                f"<td>{html.escape(_why_text(row))}</td><td>{centre}</td><td>{row['depth_m']:.1f}</td><td>{where}</td>"
                f"<td>{distance}</td></tr>"
            )
        parts.append("<h3>Largest gaps, all sessions</h3><table id='coverage-gaps'>" + head
                     + "".join(body) + "</table>")  # fmt: skip
    else:
        parts.append("<p class='ok'>no gap found in the merged coverage</p>")
    for label in ["merged", *[k for k in coverage.maps if k != "merged"]]:
        if label in written:
            title = "all sessions" if label == "merged" else f"session {label}"
            uri = png_data_uri(written[label].read_bytes())
            parts.append(f'<p><img alt="coverage {html.escape(title)}" src="{uri}"></p>')
    if coverage.notes:
        parts.append("<p class='small'>" + html.escape("; ".join(coverage.notes)) + "</p>")
    return "".join(parts)
