"""SfM seeded by SLAM poses against COLMAP's incremental mapper, on the survey simulator.

Run: .venv/bin/python bench/bench_sfm.py [--keyframes 300] [--fractions 0.33,0.67,1]
Two simulated sessions (field.sim) rendered at 640x360, keyframes at 2 Hz, with
SLAM-like priors: a path-proportional biased random walk (2 % of the distance
travelled) plus heading drift and jitter, placed in the world by their true
`T_W_S` (as the merge stage would). Prints, per session, the ATE of the priors
and of the refined keyframes against the truth (aligned "none", "se3" and
"sim3"), the time of each step, and pycolmap's incremental mapper run from
scratch (no priors) on the same database (same features, same verified pairs)
in the same process: its mapping time against ours, and its sim3 ATE.
Then the stage's run time on the first quarter and half of each session
(and all of it, from the first run), i.e. shorter dives at the same keyframe
density: the time per keyframe should stay about constant (near-linear growth).
Writes nothing outside --work (default: a temporary folder).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from postproc.sfm.features import FeatureOptions
from postproc.sfm.stage import SfmOptions, run
from shared.formats.tum import read_tum, write_tum
from shared.geometry import invert_pose
from shared.trajectory import Trajectory, ate
from tests.postproc.sfm.slam_like import (
    SlamLikeSession,
    write_merge_like,
    write_slam_like_survey,
)


def ate_row(estimate: Trajectory, truth: Trajectory) -> str:
    return "  ".join(
        f"{align} {ate(estimate, truth, align=align).rmse_m * 100:6.2f} cm"  # type: ignore[arg-type]
        for align in ("none", "se3", "sim3")
    )


def subset(sessions: list[SlamLikeSession], fraction: float, root: Path) -> list[SlamLikeSession]:
    """SLAM folders holding the first `fraction` of each session's keyframes (linked images)."""
    out = []
    for s in sessions:
        n = max(round(len(s.estimate) * fraction), 3)
        folder = root / s.folder.name
        (folder / "keyframes").mkdir(parents=True)
        shutil.copytree(s.folder / "calib", folder / "calib")
        estimate = Trajectory(s.estimate.stamps_ns[:n], s.estimate.poses[:n])
        truth = Trajectory(s.truth_world_from_cam.stamps_ns[:n], s.truth_world_from_cam.poses[:n])
        write_tum(folder / "keyframes.tum", estimate)
        for stamp in estimate.stamps_ns.tolist():
            (folder / "keyframes" / f"{stamp}.png").symlink_to(
                s.folder / "keyframes" / f"{stamp}.png"
            )
        out.append(SlamLikeSession(folder, s.world_from_session, truth, estimate))
    return out


def incremental_from_scratch(
    database: Path, images: Path, work: Path, threads: int
) -> tuple[float, dict[str, np.ndarray]]:
    """pycolmap's incremental mapper without priors on a copy of `database`; time, T_W_C."""
    import pycolmap

    db = work / "incremental.db"
    shutil.copyfile(database, db)
    with pycolmap.Database.open(db) as handle:
        handle.clear_pose_priors()
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_extra_params = False
    options.extract_colors = False
    options.num_threads = threads
    options.random_seed = 0
    (work / "incremental").mkdir(exist_ok=True)
    start = time.perf_counter()
    models = pycolmap.incremental_mapping(db, images, work / "incremental", options=options)
    seconds = time.perf_counter() - start
    poses: dict[str, np.ndarray] = {}
    if models:
        best = max(models.values(), key=lambda r: r.num_reg_images())
        for image in best.images.values():
            if image.has_pose:
                T = np.eye(4)
                T[:3, :4] = image.cam_from_world().matrix()
                poses[image.name] = invert_pose(T)
        print(f"  incremental: {len(models)} model(s), largest {best.num_reg_images()} images")
    return seconds, poses


def exhaustive_matching_seconds(
    database: Path, names: list[str], ours: set[tuple[str, str]], work: Path, sample: int
) -> float:
    """Time to match every pair (what a mapper without priors needs to link sessions),
    extrapolated from matching `sample` random pairs that our selection left out."""
    import pycolmap

    from postproc.sfm.features import FeatureOptions, match_pairs, write_pairs_file

    db = work / "exhaustive.db"
    shutil.copyfile(database, db)
    with pycolmap.Database.open(db) as handle:
        handle.clear_matches()
        handle.clear_two_view_geometries()
    rng = np.random.default_rng(0)
    n = len(names)
    chosen: set[tuple[str, str]] = set()
    while len(chosen) < sample:
        i, j = sorted(rng.choice(n, size=2, replace=False).tolist())
        pair = (names[i], names[j])
        if pair not in ours:
            chosen.add(pair)
    # Matching cost differs little between overlapping pairs and others; sample both in
    # the proportion exhaustive matching sees them.
    share = len(ours) / (n * (n - 1) / 2)
    ours_sample = rng.permutation(sorted(ours))[: max(int(sample * share), 1)]
    pairs = sorted(chosen) + [tuple(p) for p in ours_sample.tolist()]
    path = write_pairs_file(work / "exhaustive_sample.txt", pairs)
    start = time.perf_counter()
    match_pairs(db, path, FeatureOptions())
    per_pair = (time.perf_counter() - start) / len(pairs)
    return per_pair * n * (n - 1) / 2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=300, help="total keyframes, 2 sessions")
    parser.add_argument("--fractions", default="0.25,0.5", help="session fractions for scaling")
    parser.add_argument("--threads", type=int, default=-1)
    parser.add_argument("--no-incremental", action="store_true")
    parser.add_argument(
        "--sample-pairs", type=int, default=300, help="pairs timed to extrapolate exhaustive"
    )
    parser.add_argument("--work", type=Path, help="keep data and outputs here")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_sfm_"))
    work.mkdir(parents=True, exist_ok=True)
    duration_s = args.keyframes / 2 / 2.0  # two sessions at 2 Hz
    start = time.perf_counter()
    sessions = write_slam_like_survey(
        work / "survey",
        sessions=2,
        duration_s=duration_s,
        keyframe_hz=2.0,
        width=640,
        height=360,
        texel_m=0.01,
        seed=1,
    )
    n = sum(len(s.estimate) for s in sessions)
    print(f"simulated {n} keyframes in {time.perf_counter() - start:.0f} s (640x360, 2 Hz)")
    options = SfmOptions(features=FeatureOptions(num_threads=args.threads))
    options.refine.num_threads = args.threads

    merge = write_merge_like(work / "merge", sessions, placed=[True, True])
    out = work / "sfm"
    start = time.perf_counter()
    run(options, [merge], out, overwrite=True)
    total = time.perf_counter() - start
    stats = json.loads((out / "stats.json").read_text())
    sec = stats["seconds"]
    mapping_ours = sec["refine_s"]
    print(f"\n== ours: {n} keyframes, {stats['pairs']['total']} pairs {stats['pairs']}")
    print(
        "  time: extract {extract_s:.1f} s, pairs {pairs_s:.2f} s, match {match_s:.1f} s, "
        "triangulate {triangulate_s:.1f} s, BA rounds {bundle_adjust_s:.1f} s, "
        "total {total_s:.1f} s".format(**sec)
    )
    print(
        f"  {stats['registered_images']} registered, {stats['points3D']} points, "
        f"reprojection {stats['mean_reprojection_error_px']:.3f} px, "
        f"{len(stats['rounds'])} rounds, exhaustive would be {n * (n - 1) // 2} pairs"
    )
    for s in sessions:
        prior = s.estimate.transformed(s.world_from_session)
        refined = read_tum(out / "sessions" / s.folder.name / "keyframes.tum")
        print(f"  {s.folder.name} prior   ATE {ate_row(prior, s.truth_world_from_cam)}")
        print(f"  {s.folder.name} refined ATE {ate_row(refined, s.truth_world_from_cam)}")

    if not args.no_incremental:
        print("\n== pycolmap incremental mapping from scratch (same database, no priors)")
        seconds, poses = incremental_from_scratch(
            out / "database.db", out / "images", work, args.threads
        )
        all_names = sorted(
            f"{s.folder.name}/{t}.png" for s in sessions for t in s.estimate.stamps_ns.tolist()
        )
        ours_pairs = {
            tuple(sorted(line.split()))  # type: ignore[misc]
            for line in (out / "pairs.txt").read_text().splitlines()
        }
        exhaustive = exhaustive_matching_seconds(
            out / "database.db", all_names, ours_pairs, work, args.sample_pairs
        )
        scratch = sec["extract_s"] + exhaustive + seconds
        print(
            f"  mapping alone: {seconds:.1f} s vs ours (triangulate + BA) {mapping_ours:.1f} s "
            f"(x{seconds / mapping_ours:.1f})"
        )
        print(
            f"  from images: extract {sec['extract_s']:.0f} s + exhaustive matching "
            f"{exhaustive:.0f} s (extrapolated from {args.sample_pairs} pairs) + mapping "
            f"{seconds:.0f} s = {scratch:.0f} s vs ours {total:.0f} s (x{scratch / total:.1f})"
        )
        for s in sessions:
            names = [f"{s.folder.name}/{t}.png" for t in s.estimate.stamps_ns.tolist()]
            keep = [i for i, name in enumerate(names) if name in poses]
            if len(keep) < 3:
                print(f"  {s.folder.name}: {len(keep)} images registered")
                continue
            est = Trajectory(s.estimate.stamps_ns[keep], np.stack([poses[names[i]] for i in keep]))
            truth = Trajectory(
                s.truth_world_from_cam.stamps_ns[keep], s.truth_world_from_cam.poses[keep]
            )
            sim3 = ate(est, truth, align="sim3").rmse_m
            print(
                f"  {s.folder.name} incremental: {len(keep)}/{len(names)} images, sim3 ATE "
                f"{sim3 * 100:.2f} cm"
            )

    print("\n== scaling (first part of each session, same density)")
    rows = [(n, stats["pairs"]["total"], total, sec)]
    for fraction in [float(f) for f in args.fractions.split(",")]:
        part = subset(sessions, fraction, work / f"part_{fraction:.2f}")
        m = write_merge_like(work / f"merge_{fraction:.2f}", part, placed=[True, True])
        out_part = work / f"sfm_{fraction:.2f}"
        start = time.perf_counter()
        run(options, [m], out_part, overwrite=True)
        seconds = time.perf_counter() - start
        st = json.loads((out_part / "stats.json").read_text())
        rows.append((st["keyframes"], st["pairs"]["total"], seconds, st["seconds"]))
    for k, pairs, seconds, steps in sorted(rows, key=lambda r: r[0]):
        print(
            f"  {k:5d} keyframes {pairs:6d} pairs: total {seconds:6.1f} s "
            f"({seconds / k:.2f} s/keyframe; extract {steps['extract_s']:.1f}, "
            f"match {steps['match_s']:.1f}, refine {steps['refine_s']:.1f})"
        )
    print(f"\n(work folder: {work})")


if __name__ == "__main__":
    main()
