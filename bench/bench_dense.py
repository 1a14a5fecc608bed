"""Dense reconstruction accuracy on the simulated wreck, against its truth mesh.

    .venv/bin/python bench/bench_dense.py [--duration 30] [--width 640 --height 360]
        [--keyframe-step 0.25] [--max-image-size 960] [--backend auto] [--keep DIR]
        [--no-view-selection] [--min-baseline-rel 0.3] [--min-rotation-deg 20]
        [--project-keyframes 5000] [--max-neighbours 4] [--far-neighbours 2]
        [--single-image-neighbours 0 --single-image-radius 0.05] [--single-image-min-pairs 4]
        [--single-image-near-min-pairs 2 --single-image-near-range 6]
        [--support-tolerance 0.02]

Simulates session 0 of the survey (`sim.survey`: diver route along the starboard
hull, underwater image model with noise), picks keyframes every `--keyframe-step` metres
or 10 degrees on the true trajectory, writes an SfM folder with the TRUE poses (so the
figures measure the dense stage alone, not SfM drift) and sparse points, runs
`postproc.dense.stage.run`, and prints ETH3D-style accuracy and completeness at 2, 5 and
10 cm for the fused points and the mesh. Completeness counts only truth-surface samples
seen by three or more keyframes (projection inside the undistorted image and the true
depth agrees); a second row counts only those seen by three keyframes from within
`--near-range` metres (what the water lets a camera resolve), and completeness is also
broken down by range band (the range within which a sample is seen by three keyframes:
0-2, 2-4, 4-6, 6+ m). Goal: accuracy >= 90 % and completeness >= 70 % at 5 cm.

With `--keep DIR`, an SfM folder already in DIR is reused (no rendering) and the truth
visibility is cached in DIR/seen.npz; `--dense-name` names the dense output folder so
variants can be compared on the same images.

The stage computes depth maps for reference views only (`ViewSelectionOptions`); the
bench prints how many of the keyframes were chosen and projects the depth-map time of a
dive with `--project-keyframes` keyframes (5000: a 45-minute dive) from the measured
time per reference image and the measured fraction chosen. `--no-view-selection` gives
every keyframe a depth map (the figures before the selection).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from postproc.dense.colmap_io import (
    DenseWorkspace,
    PinholeView,
    read_pinhole_views,
    write_known_pose_model,
)
from postproc.dense.evaluate import distance_to_mesh, evaluate, sample_surface, visibility
from postproc.dense.fusion import FusionOptions
from postproc.dense.stage import DenseOptions, run
from postproc.dense.stereo_cpu import CpuStereoOptions
from postproc.dense.views import NeighbourOptions, ViewSelectionOptions
from shared.calibration.cameras import PinholeRadtan
from shared.folders import DenseFolder, SfmFolder
from shared.formats.ply import read_ply
from sim.mesh import scene_mesh
from sim.render import Renderer
from sim.survey import SurveyOptions, SurveySimulator


def pick_keyframes(poses: np.ndarray, step_m: float, step_deg: float = 10.0) -> list[int]:
    """Indices of frames where the camera moved `step_m` or turned `step_deg` since the last."""
    chosen = [0]
    for i in range(1, len(poses)):
        last = poses[chosen[-1]]
        moved = np.linalg.norm(poses[i][:3, 3] - last[:3, 3])
        cos = (np.trace(last[:3, :3].T @ poses[i][:3, :3]) - 1.0) / 2.0
        turned = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        if moved >= step_m or turned >= step_deg:
            chosen.append(i)
    return chosen


def sparse_points(
    camera: PinholeRadtan, poses: list[np.ndarray], depths: list[np.ndarray], step_px: int = 24
) -> tuple[np.ndarray, list[list[tuple[int, float, float]]]]:
    """A pixel grid of each keyframe back-projected at its true depth, observed in every
    keyframe where the true depth confirms it is visible (what SfM would triangulate)."""
    points = []
    for pose, depth in zip(poses, depths, strict=True):
        vv, uu = np.mgrid[4 : camera.height - 4 : step_px, 4 : camera.width - 4 : step_px]
        z = depth[vv, uu]
        ok = np.isfinite(z)
        rays = camera.unproject(np.column_stack((uu[ok], vv[ok])).astype(float))
        cam_points = rays / rays[:, 2:3] * z[ok, None]
        points.append(cam_points @ pose[:3, :3].T + pose[:3, 3])
    all_points = np.concatenate(points)
    observations = []
    for pose, depth in zip(poses, depths, strict=True):
        cam_from_world = np.linalg.inv(pose)
        pc = all_points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        idx = np.flatnonzero(pc[:, 2] > 0.1)
        uv = camera.project(pc[idx])
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width - 1)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height - 1)
        )
        idx, uv = idx[inside], uv[inside]
        true_z = depth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
        seen = np.isfinite(true_z) & (np.abs(true_z - pc[idx, 2]) < 0.01 * pc[idx, 2])
        observations.append(
            [(int(p), float(u), float(v)) for p, (u, v) in zip(idx[seen], uv[seen], strict=True)]
        )
    return all_points, observations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=30.0, help="filmed seconds")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--keyframe-step", type=float, default=0.25, metavar="METRES")
    parser.add_argument("--max-image-size", type=int, default=960)
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "patchmatch"))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--near-range", type=float, default=4.0, metavar="METRES",
        help="second completeness row: seen by 3 keyframes within this range",
    )  # fmt: skip
    parser.add_argument("--keep", type=Path, help="work folder to keep (default: temporary)")
    parser.add_argument("--dense-name", default="dense", help="dense folder inside the work one")
    parser.add_argument("--no-mesh", action="store_true", help="skip Poisson meshing")
    parser.add_argument("--no-view-selection", action="store_true",
                        help="a depth map for every keyframe")  # fmt: skip
    parser.add_argument("--min-baseline-rel", type=float,
                        default=ViewSelectionOptions().min_baseline_rel,
                        help="view selection: baseline over scene depth")  # fmt: skip
    parser.add_argument("--min-rotation-deg", type=float,
                        default=ViewSelectionOptions().min_rotation_deg,
                        help="view selection: turn between optical axes, degrees")  # fmt: skip
    parser.add_argument("--max-neighbours", type=int, default=NeighbourOptions().max_neighbours,
                        help="stereo partners per reference at its median depth")  # fmt: skip
    parser.add_argument("--far-neighbours", type=int, default=NeighbourOptions().far_neighbours,
                        help="extra stereo partners at its far depth")  # fmt: skip
    parser.add_argument("--project-keyframes", type=int, default=5000,
                        help="keyframes of the dive to project the depth-map time to")  # fmt: skip
    parser.add_argument("--min-num-pixels", type=int, default=FusionOptions().min_num_pixels,
                        help="fusion: images agreeing on a point")  # fmt: skip
    parser.add_argument("--max-depth-error", type=float,
                        default=FusionOptions().max_depth_error_rel,
                        help="fusion: depth agreement (fraction of the depth)")  # fmt: skip
    parser.add_argument("--single-image-neighbours", type=int,
                        default=DenseOptions().mesh_single_image_neighbours,
                        help="mesh: keep a point of one depth map with this many fused "
                             "points near it (0: leave them out)")  # fmt: skip
    parser.add_argument("--single-image-radius", type=float,
                        default=DenseOptions().mesh_single_image_radius_m,
                        help="mesh: radius of that neighbour count, metres")  # fmt: skip
    parser.add_argument("--support-tolerance", type=float,
                        default=CpuStereoOptions().support_tolerance_m,
                        help="stereo: pair agreement that supports a depth, m")  # fmt: skip
    parser.add_argument("--single-image-min-pairs", type=int,
                        default=DenseOptions().mesh_single_image_min_pairs,
                        help="mesh: keep a point of one depth map where this many of its "
                             "stereo pairs agreed (0: off)")  # fmt: skip
    parser.add_argument("--single-image-near-min-pairs", type=int,
                        default=DenseOptions().mesh_single_image_near_min_pairs,
                        help="mesh: the same within the near range (0: off)")  # fmt: skip
    parser.add_argument("--single-image-near-range", type=float,
                        default=DenseOptions().mesh_single_image_near_range_m,
                        help="mesh: range of that rule, metres from the map's camera")  # fmt: skip
    args = parser.parse_args()

    sim = SurveySimulator(
        SurveyOptions(sessions=1, duration_s=args.duration, width=args.width,
                      height=args.height, seed=args.seed, video=False)
    )  # fmt: skip
    camera = sim.camera
    stamps = sim.sessions[0].frame_stamps_cam_ns
    all_poses = sim.world_from_cam(0, stamps)
    keys = pick_keyframes(all_poses, args.keyframe_step)
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench_dense."))
    sfm_dir, out_dir = work / "sfm", work / args.dense_name
    sfm, dense = SfmFolder(sfm_dir), DenseFolder(out_dir)  # the model as the SfM stage puts it
    print(f"work folder: {work}")

    start = time.perf_counter()
    _ = sim.scene
    poses = [all_poses[i] for i in keys]
    names = [f"{int(stamps[i])}.png" for i in keys]
    reuse = sfm.model.exists() and all((sfm.images / n).is_file() for n in names)
    sfm.images.mkdir(parents=True, exist_ok=True)
    if not reuse:
        depths = []
        for i, name in zip(keys, names, strict=True):
            frame = sim.render_frame(0, int(stamps[i]), frame_index=int(i))
            cv2.imwrite(str(sfm.images / name), frame.image_rgb[..., ::-1])
            depths.append(frame.depth_m)
        points, observations = sparse_points(camera, poses, depths)
        write_known_pose_model(
            sfm.model, camera_model="OPENCV",
            camera_params=[camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2,
                           camera.p1, camera.p2],
            size=(camera.width, camera.height), image_names=names,
            cams_from_world=[np.linalg.inv(p) for p in poses], points_m=points,
            observations=observations,
        )  # fmt: skip
    render_s = time.perf_counter() - start
    print(f"{len(keys)} keyframes of {len(stamps)} frames ({args.width}x{args.height}); "
          f"{'reused' if reuse else 'rendered in'} {render_s:.1f} s")  # fmt: skip

    start = time.perf_counter()
    load_before = os.getloadavg()[0]
    options = DenseOptions(
        max_image_size_px=args.max_image_size, backend=args.backend, make_mesh=not args.no_mesh,
        mesh_single_image_neighbours=args.single_image_neighbours,
        mesh_single_image_radius_m=args.single_image_radius,
        mesh_single_image_min_pairs=args.single_image_min_pairs,
        mesh_single_image_near_min_pairs=args.single_image_near_min_pairs,
        mesh_single_image_near_range_m=args.single_image_near_range,
    )  # fmt: skip
    options.fusion = FusionOptions(
        min_num_pixels=args.min_num_pixels, max_depth_error_rel=args.max_depth_error
    )
    options.stereo.support_tolerance_m = args.support_tolerance
    options.neighbours = NeighbourOptions(
        max_neighbours=args.max_neighbours, far_neighbours=args.far_neighbours
    )
    options.view_selection = ViewSelectionOptions(
        enabled=not args.no_view_selection,
        min_baseline_rel=args.min_baseline_rel,
        min_rotation_deg=args.min_rotation_deg,
    )
    run(options, sfm_dir, out_dir)
    dense_s = time.perf_counter() - start
    load_after = os.getloadavg()[0]
    report = dense.read_report()

    # Truth: the scene mesh; completeness samples seen by >= 3 keyframes in the undistorted
    # cameras (true depth rendered through the workspace's pinhole camera).
    start = time.perf_counter()
    truth = scene_mesh(sim.scene)
    views = read_pinhole_views(DenseWorkspace(dense.workspace).sparse_dir)
    by_name = {v.name: v for v in views}
    K = views[0].K
    pinhole = PinholeRadtan(
        width=views[0].width, height=views[0].height, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2],
        cy=K[1, 2], k1=0.0, k2=0.0, p1=0.0, p2=0.0,
    )  # fmt: skip
    cache = work / "seen.npz"
    if cache.is_file():
        cached = np.load(cache)
        samples, counts, ranges = cached["samples"], cached["counts"], cached["ranges"]
    else:
        renderer = Renderer(sim.scene, pinhole, sim.options.water)
        centres = np.array([p[:3, 3] for p in poses])
        tri_centres = truth.vertices[truth.triangles].mean(axis=1)
        reach = 8.0  # m: far beyond what the water lets the cameras resolve
        near = np.min(
            np.linalg.norm(tri_centres[:, None, :] - centres[None, ::5, :], axis=2), axis=1
        )
        samples, _ = sample_surface(truth.vertices, truth.triangles[near < reach + 1.0], 0.02,
                                    seed=1)  # fmt: skip
        true_depths = [renderer.render(p).depth_m for p in poses]
        counts, ranges = visibility(
            samples, [by_name[n].K for n in names], [by_name[n].cam_from_world for n in names],
            true_depths, nearest=3,
        )  # fmt: skip
        np.savez(cache, samples=samples, counts=counts, ranges=ranges)
    v, t = truth.vertices, truth.triangles.astype(np.int64)
    seen_mask = counts >= 3
    seen = samples[seen_mask]
    third = ranges[seen_mask, 2]  # the range within which three keyframes see the sample
    seen_near = seen[third <= args.near_range]
    fused = read_ply(dense.fused)
    thresholds = (0.02, 0.05, 0.10)
    rows = [("fused points", evaluate(fused.vertices, v, t, seen, thresholds_m=thresholds))]
    near_label = f"fused, seen <= {args.near_range:g} m"
    rows.append((near_label, evaluate(fused.vertices, v, t, seen_near, thresholds_m=thresholds)))
    bands = [(0.0, 2.0), (2.0, 4.0), (4.0, 6.0), (6.0, np.inf)]
    band_rows = []
    for lo, hi in bands:
        in_band = seen[(third >= lo) & (third < hi)]
        label = f"fused, band {lo:g}-{hi:g} m" if np.isfinite(hi) else f"fused, band {lo:g}+ m"
        scores = evaluate(fused.vertices, v, t, in_band, thresholds_m=thresholds)
        band_rows.append((f"{label} ({100 * len(in_band) / max(len(seen), 1):.0f} %)", scores))
    mesh_path = dense.mesh
    if mesh_path.is_file():
        mesh = read_ply(mesh_path)
        assert mesh.faces is not None, f"{mesh_path}: no faces"
        mesh_samples, _ = sample_surface(mesh.vertices, mesh.faces, 0.02, seed=2)
        rows.append(
            ("mesh (2 cm samples)", evaluate(mesh_samples, v, t, seen, thresholds_m=thresholds))
        )
        near_label = f"mesh, seen <= {args.near_range:g} m"
        rows.append((near_label, evaluate(mesh_samples, v, t, seen_near, thresholds_m=thresholds)))
    rows.extend(band_rows)
    errors = distance_to_mesh(fused.vertices, v, t)
    support_rows = one_map_support(dense, fused.vertices, views, errors, options.mesh_min_images)
    eval_s = time.perf_counter() - start

    depth_report = report["depth_maps"]
    per_image = depth_report.get("seconds_per_image")
    print(f"\nbackend {report['backend']}, {report['images']} images, "
          f"{report['fused_points']} fused points, mesh {report.get('mesh', {})}")  # fmt: skip
    print(f"truth samples seen by >= 3 keyframes: {len(seen)} of {len(samples)} (2 cm spacing), "
          f"{len(seen_near)} of them within {args.near_range:g} m")  # fmt: skip
    print(f"fused point error: median {100 * np.median(errors):.2f} cm, "
          f"90th percentile {100 * np.percentile(errors, 90):.2f} cm")  # fmt: skip
    print()
    print(f"{'':32s}" + "".join(f"{f'{100 * d:.0f} cm acc/comp/F1':>24s}" for d in thresholds))
    for label, scores in rows:
        cells = "".join(
            f"{f'{100 * s.accuracy:.1f} / {100 * s.completeness:.1f} / {100 * s.f1:.1f}':>24s}"
            for s in scores
        )
        print(f"{label:32s}{cells}")
    print()
    for line in support_rows:
        print(line)
    timings = report["timings"]
    n = report["images"]
    print("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    if per_image is not None:
        print(f"depth maps: {per_image:.2f} s per image; whole stage {dense_s / n:.2f} s per image "
              f"({dense_s:.1f} s for {n}); evaluation {eval_s:.1f} s")  # fmt: skip
    chosen = report.get("reference_images", n)
    print(f"reference views: {chosen} of {n} keyframes ({100 * chosen / n:.0f} %), selection "
          f"{options.view_selection}")  # fmt: skip
    if per_image is not None:
        hours = args.project_keyframes * chosen / n * per_image / 3600.0
        print(f"projected depth maps for {args.project_keyframes} keyframes: "
              f"{args.project_keyframes * chosen / n:.0f} references x {per_image:.2f} s = "
              f"{hours:.2f} h on this machine (one process)")  # fmt: skip
    print(f"load average (1 min): {load_before:.1f} before, {load_after:.1f} after the stage "
          f"({os.cpu_count()} cores)")  # fmt: skip
    five = rows[0][1][1]
    goal = five.accuracy >= 0.9 and five.completeness >= 0.7
    print(f"goal at 5 cm (accuracy >= 90 %, completeness >= 70 %): {'met' if goal else 'NOT met'}")


def one_map_support(
    dense: DenseFolder,
    fused_m: np.ndarray,
    views: list[PinholeView],
    errors: np.ndarray,
    min_images: int,
) -> list[str]:
    """Lines on the fused points of fewer than `min_images` images (left out of the mesh
    by default): how many there are at each stereo pair support and depth band, and how
    many of them lie within 5 cm of the truth (the evidence behind the mesh's rules
    `mesh_single_image_min_pairs` and `mesh_single_image_near_*`).
    fused_m: the fused points (`dense.fused`'s vertices); errors: their distances to
    the truth (m)."""
    from postproc.dense.colmap_io import read_fusion_visibility
    from postproc.dense.stage import pair_support

    visible = read_fusion_visibility(dense.fused_visibility)
    weak = np.flatnonzero(visible.counts < min_images)
    if not len(weak):
        return []
    support = pair_support(
        fused_m[weak], visible.subset(weak), DenseWorkspace(dense.workspace), views
    )
    bands = [(0.0, 2.0), (2.0, 4.0), (4.0, 5.0), (5.0, 6.0), (6.0, 7.0), (7.0, 8.0),
             (8.0, np.inf)]  # fmt: skip
    lines = [
        f"points of fewer than {min_images} depth maps: {len(weak)} of {len(visible)} "
        f"({100 * len(weak) / len(visible):.0f} %); by the stereo pairs agreeing at the pixel "
        "and the depth in the map's camera: points, % within 5 cm of the truth",
        "pairs" + "".join(f"{f'{lo:g}-{hi:g} m':>17s}" for lo, hi in bands),
    ]
    for level in range(int(support.pairs.max()) + 1):
        cells = []
        for lo, hi in bands:
            at = (support.pairs == level) & (support.depth_m >= lo) & (support.depth_m < hi)
            share = f"{100 * np.mean(errors[weak[at]] < 0.05):.1f}" if at.any() else "-"
            cells.append(f"{int(at.sum()):>9d} {share:>5s} %")
        lines.append(f"{level:>5d}" + "".join(cells))
    return lines


if __name__ == "__main__":
    main()
