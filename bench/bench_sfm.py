"""SfM seeded by SLAM poses against COLMAP's incremental mapper from scratch, on the simulator.

Run: .venv/bin/python bench/bench_sfm.py [--keyframes 600] [--sessions 2]
     [--fractions 0.27,0.54,1] [--baseline-fractions 0.54] [--ba-max-track-length N]
     [--refine-only] [--work DIR]

Two simulated sessions (sim) rendered at 640x360, keyframes at 2 Hz, with
SLAM-like priors: a path-proportional biased random walk (2 % of the distance
travelled) plus heading drift and jitter, placed in the world by their true
`T_W_S` (as the merge stage would). Our stage runs on the first `fraction` of
each session (shorter dives at the same keyframe density) for every fraction:
per size it prints the time of each step (the first pass of triangulation and
adjustment rounds at the priors, then the pass on tracks rebuilt at the refined
poses, see `postproc.sfm.refine`), seconds per keyframe (scaling) and the ATE
of the priors and of the refined keyframes per session, without alignment (the
world frame and metric scale kept), rigid (se3) and similarity (sim3). The scaling
summary gives, per size, the wall and CPU time of the stage (this process and its
children: the figure that holds on a shared machine), the mean observations per point
going into the adjustments, and the exponent k of time ~ keyframes^k between the
smallest and the largest size. `--sessions 1 --keyframes 1200 --fractions 0.3,1
--baseline-fractions ''` is a 10-minute dive that keeps revisiting the wreck, and its
first 3 minutes (the sizes `bench_pipeline.py` measures SfM's k at).
`--refine-only` reruns only the refinement (triangulation and adjustment rounds,
`postproc.sfm.refine`) on a copy of the database an earlier run at the same size
left in --work (same features, matches and priors), timed by CPU; it prints its
rounds, k and errors the same way, to compare refinement settings without
extracting and matching again.

The baseline, at the `--baseline-fractions` sizes, is what the paper did and the
issue asks to beat: COLMAP from scratch on the same images, i.e. pycolmap 4.2.1
feature extraction with its default settings (up to 8192 SIFT features, first
octave -1, longer side up to 3200 px), exhaustive matching with its default
matcher (CPU SIFT matcher, ratio 0.8, cross-check, RANSAC verification at 4 px),
and the incremental mapper without priors (the calibrated camera held fixed, as
ours). On two loaded cores that takes hours, so only parts are measured:
(a) the incremental mapper from scratch on our database (our features, our pair
list, priors removed): measured, the mapping-alone ratio and the baseline's
accuracy; it is a lower bound of the mapping time with default features;
(b) exhaustive matching at our feature budget: the pair rate measured on
`--sample-pairs` random pairs (overlapping ones in the proportion exhaustive
matching sees them) times N(N-1)/2 (extrapolated);
(c) the default features: extraction measured on `--sample-images` random
images and the pair rate on pairs among them, both scaled to N images and
N(N-1)/2 pairs (extrapolated).
Both the measured and the extrapolated figures are printed.
Writes nothing outside --work (default: a temporary folder); the simulated
survey there is reused by later runs with the same --keyframes.
"""

from __future__ import annotations

import argparse
import os
import pickle
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from postproc.sfm.features import FeatureOptions
from postproc.sfm.stage import SfmOptions, run
from shared.folders import SfmFolder, SlamFolder
from shared.geometry import invert_pose
from shared.trajectory import Trajectory, ate
from sim.slam_like import (
    SlamLikeSession,
    write_merge_like,
    write_slam_like_survey,
)

Align = Literal["se3", "sim3", "none"]


def load() -> str:
    path = Path("/proc/loadavg")
    return path.read_text().split()[0] if path.exists() else "?"


def cpu_s() -> float:
    """CPU seconds of this process and its finished children so far (user + system)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def set_refine_option(options: SfmOptions, setting: str) -> None:
    """Set one `RefineOptions` field from "name=value" (parsed as the field's current type)."""
    name, _, text = setting.partition("=")
    if not hasattr(options.refine, name):
        raise SystemExit(f"--refine {setting}: RefineOptions has no field {name!r}")
    current = getattr(options.refine, name)
    value: Any
    if text.lower() in ("none", ""):
        value = None
    elif isinstance(current, bool):
        value = text.lower() in ("1", "true", "yes", "on")
    elif isinstance(current, int):
        value = int(text)
    elif isinstance(current, float) or current is None:  # None: an optional number, unset
        value = float(text)
    else:
        value = text
    setattr(options.refine, name, value)
    options.refine.__post_init__()


def ate_row(estimate: Trajectory, truth: Trajectory) -> str:
    return "  ".join(
        f"{align} {ate(estimate, truth, align=align).rmse_m * 100:6.2f} cm"
        for align in ("none", "se3", "sim3")
    )


def survey(work: Path, keyframes: int, sessions_n: int = 2) -> list[SlamLikeSession]:
    """The simulated survey, `keyframes` over `sessions_n` sessions (rendered once, then
    reused from `work`)."""
    root = work / (f"survey_{keyframes}" if sessions_n == 2 else f"survey_{keyframes}_{sessions_n}")
    cache = root / "sessions.pkl"
    if cache.exists():
        with cache.open("rb") as f:
            sessions: list[SlamLikeSession] = pickle.load(f)  # our own file, written below
        # The session folders sit beside the pickle; an older run may have stored them
        # relative to its working folder, which the merge's paths cannot resolve.
        for s in sessions:
            s.folder = root / s.folder.name
        return sessions
    start = time.perf_counter()
    sessions = write_slam_like_survey(
        root,
        sessions=sessions_n,
        duration_s=keyframes / sessions_n / 2.0,  # keyframes at 2 Hz
        keyframe_hz=2.0,
        width=640,
        height=360,
        texel_m=0.01,
        seed=1,
    )
    with cache.open("wb") as f:
        pickle.dump(sessions, f)
    n = sum(len(s.estimate) for s in sessions)
    print(f"simulated {n} keyframes in {time.perf_counter() - start:.0f} s (640x360, 2 Hz)")
    return sessions


def subset(sessions: list[SlamLikeSession], fraction: float, root: Path) -> list[SlamLikeSession]:
    """SLAM folders holding the first `fraction` of each session's keyframes (linked images)."""
    if fraction >= 1:
        return sessions
    out = []
    shutil.rmtree(root, ignore_errors=True)
    for s in sessions:
        n = max(round(len(s.estimate) * fraction), 3)
        folder = root / s.folder.name
        source, slam = SlamFolder(s.folder), SlamFolder(folder)
        slam.keyframes.mkdir(parents=True)
        shutil.copytree(source.calib, slam.calib)
        shutil.copyfile(source.stats, slam.stats)
        estimate = Trajectory(s.estimate.stamps_ns[:n], s.estimate.poses[:n])
        truth = Trajectory(s.truth_world_from_cam.stamps_ns[:n], s.truth_world_from_cam.poses[:n])
        slam.write_keyframes(estimate)
        for stamp in estimate.stamps_ns.tolist():
            slam.keyframe_image(stamp).symlink_to(source.keyframe_image(stamp).resolve())
        out.append(SlamLikeSession(folder, s.world_from_session, truth, estimate))
    return out


def run_ours(
    sessions: list[SlamLikeSession], options: SfmOptions, work: Path
) -> tuple[dict[str, Any], float, float, Path]:
    """Our stage on `sessions`; its stats, wall seconds, CPU seconds and output folder."""
    shutil.rmtree(work, ignore_errors=True)  # a rerun in the same --work starts afresh
    merge = write_merge_like(work / "merge", sessions, placed=[True] * len(sessions))
    out = work / "sfm"
    start, start_cpu = time.perf_counter(), cpu_s()
    run(options, [merge], out, overwrite=True)
    total, cpu = time.perf_counter() - start, cpu_s() - start_cpu
    return SfmFolder(out).read_stats(), total, cpu, out


def worst_ate_m(out: Path, sessions: list[SlamLikeSession], align: Align) -> float:
    """The worst session's ATE of our refined keyframes (m)."""
    return max(
        ate(
            SfmFolder(out).read_session_keyframes(s.folder.name),
            s.truth_world_from_cam,
            align=align,
        ).rmse_m
        for s in sessions
    )


def refine_only(
    sessions: list[SlamLikeSession], options: SfmOptions, work: Path
) -> tuple[dict[str, Any], float, float, dict[str, np.ndarray]]:
    """The refinement alone on a copy of the database an earlier `run_ours` left in `work`;
    stats-like rounds and counts, wall and CPU seconds, refined `T_W_C` by image name."""
    from postproc.sfm.inputs import read_inputs
    from postproc.sfm.refine import refine_with_priors
    from postproc.sfm.stage import build_keyframes

    database = SfmFolder(work / "sfm").database
    if not database.is_file():
        raise SystemExit(f"{database}: missing (run once without --refine-only first)")
    keyframes, _ = build_keyframes(read_inputs([work / "merge"]), options)
    copy = work / "refine_only.db"
    shutil.copyfile(database, copy)
    start, start_cpu = time.perf_counter(), cpu_s()
    result = refine_with_priors(copy, keyframes, options.refine)
    total, cpu = time.perf_counter() - start, cpu_s() - start_cpu
    copy.unlink()
    model = result.reconstruction
    stats = {
        "keyframes": len(keyframes),
        "registered_images": int(model.num_reg_images()),
        "points3D": int(model.num_points3D()),
        "mean_track_length": float(model.compute_mean_track_length()),
        "mean_reprojection_error_px": float(model.compute_mean_reprojection_error()),
        "rounds": result.rounds,
        "seconds": result.seconds,
    }
    return stats, total, cpu, result.world_from_cam


def refined_ate_m(
    world_from_cam: dict[str, np.ndarray], sessions: list[SlamLikeSession], align: Align
) -> float:
    """The worst session's ATE of refined `T_W_C` by image name (m; keyframes in the model)."""
    worst = 0.0
    for s in sessions:
        truth = s.truth_world_from_cam
        names = [f"{s.folder.name}/{t}.png" for t in truth.stamps_ns.tolist()]
        keep = [i for i, name in enumerate(names) if name in world_from_cam]
        refined = Trajectory(
            truth.stamps_ns[keep], np.stack([world_from_cam[names[i]] for i in keep])
        )
        kept = Trajectory(truth.stamps_ns[keep], truth.poses[keep])
        worst = max(worst, ate(refined, kept, align=align).rmse_m)
    return worst


def print_rounds(rounds: list[dict[str, float]]) -> None:
    for k, r in enumerate(rounds, 1):
        capped = r.get("adjusted_observations_per_point", r.get("observations_per_point", 0.0))
        print(
            f"  round {k} ({'rebuilt' if r['rebuilt_tracks'] else 'first'} pass): BA "
            f"{r['bundle_adjust_s']:.1f} s, tracks {r['tracks_s']:.1f} s"
            + (
                f" (merge {r['merge_tracks_s']:.1f}, retriangulate {r['retriangulate_s']:.1f}, "
                f"cap {r['cap_tracks_s']:.1f} s)"
                if "merge_tracks_s" in r
                else ""
            )
            + f", filter {r['filter_s']:.1f} s, {r['points']:.0f} "
            f"points, {r.get('observations_per_point', 0.0):.1f} observations per point "
            f"({capped:.1f} adjusted), p95 camera move {r['p95_camera_move_m'] * 100:.1f} cm "
            f"({r.get('p95_shape_move_m', float('nan')) * 100:.1f} cm without a common "
            "similarity)"
        )


def print_ours(
    stats: dict[str, Any], total: float, cpu: float, out: Path, sessions: list[SlamLikeSession]
) -> None:
    sec = stats["seconds"]
    n = stats["keyframes"]
    print(f"\n== ours: {n} keyframes, {stats['pairs']['total']} pairs {stats['pairs']}")
    print(
        "  time: extract {extract_s:.1f} s, pairs {pairs_s:.2f} s, match {match_s:.1f} s, "
        "triangulate {triangulate_s:.1f} s, BA rounds {bundle_adjust_s:.1f} s".format(**sec)
        + f", rebuilt tracks + BA rounds {sec.get('rebuild_tracks_s', 0.0):.1f} s"
        + f", total {total:.1f} s ({total / n:.3f} s/keyframe; {cpu:.1f} s CPU; load {load()})"
    )
    print_rounds(stats["rounds"])
    print(
        f"  {stats['registered_images']} registered, {stats['points3D']} points, "
        f"{stats['matches']['keypoints'] / n:.0f} keypoints/image, reprojection "
        f"{stats['mean_reprojection_error_px']:.3f} px, {len(stats['rounds'])} rounds (p95 "
        "moves "
        + ", ".join(f"{r['p95_camera_move_m'] * 100:.1f}" for r in stats["rounds"])
        + " cm)"
    )
    for s in sessions:
        prior = s.estimate.transformed(s.world_from_session)
        refined = SfmFolder(out).read_session_keyframes(s.folder.name)
        print(f"  {s.folder.name} prior   ATE {ate_row(prior, s.truth_world_from_cam)}")
        print(f"  {s.folder.name} refined ATE {ate_row(refined, s.truth_world_from_cam)}")


def _default_matching(threads: int) -> tuple[Any, Any]:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    return matching, pycolmap.TwoViewGeometryOptions()


def _match_list(database: Path, pairs: list[tuple[str, str]], path: Path, threads: int) -> float:
    """Match and verify `pairs` with pycolmap's default settings; seconds."""
    import pycolmap

    from postproc.sfm.features import write_pairs_file

    matching, verification = _default_matching(threads)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = write_pairs_file(path, pairs)
    start = time.perf_counter()
    pycolmap.match_image_pairs(
        database,
        matching_options=matching,
        pairing_options=pairing,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )
    return time.perf_counter() - start


def incremental(
    database: Path, images: Path, work: Path, threads: int
) -> tuple[float, dict[str, np.ndarray]]:
    """pycolmap's incremental mapper without priors (camera held fixed); seconds, T_W_C."""
    import pycolmap

    with pycolmap.Database.open(database) as handle:
        handle.clear_pose_priors()
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_extra_params = False
    options.extract_colors = False
    options.num_threads = threads
    options.random_seed = 0
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    start = time.perf_counter()
    models = pycolmap.incremental_mapping(database, images, work, options=options)
    seconds = time.perf_counter() - start
    poses: dict[str, np.ndarray] = {}
    if models:
        best = max(models.values(), key=lambda r: r.num_reg_images())
        for image in best.images.values():
            if image.has_pose:
                T = np.eye(4)
                T[:3, :4] = image.cam_from_world().matrix()
                poses[image.name] = invert_pose(T)
        print(f"    {len(models)} model(s), largest {best.num_reg_images()} images")
    return seconds, poses


def baseline_ate(
    poses: dict[str, np.ndarray], sessions: list[SlamLikeSession], label: str
) -> list[float]:
    out = []
    for s in sessions:
        names = [f"{s.folder.name}/{t}.png" for t in s.estimate.stamps_ns.tolist()]
        keep = [i for i, name in enumerate(names) if name in poses]
        if len(keep) < 3:
            print(f"    {label} {s.folder.name}: {len(keep)}/{len(names)} images registered")
            out.append(float("nan"))
            continue
        est = Trajectory(s.estimate.stamps_ns[keep], np.stack([poses[names[i]] for i in keep]))
        truth = Trajectory(
            s.truth_world_from_cam.stamps_ns[keep], s.truth_world_from_cam.poses[keep]
        )
        sim3 = ate(est, truth, align="sim3").rmse_m
        out.append(sim3)
        print(
            f"    {label} {s.folder.name}: {len(keep)}/{len(names)} images, sim3 ATE "
            f"{sim3 * 100:.2f} cm"
        )
    return out


def _pair_rate(
    database: Path, pairs: list[tuple[str, str]], work: Path, threads: int, label: str
) -> float:
    """Seconds per pair to match and verify `pairs` with pycolmap's defaults (on a copy)."""
    import pycolmap

    db = work / f"rate_{label}.db"
    shutil.copyfile(database, db)
    with pycolmap.Database.open(db) as handle:
        handle.clear_two_view_geometries()
        handle.clear_matches()
    return _match_list(db, pairs, work / f"rate_{label}.txt", threads) / len(pairs)


def baseline(
    out: Path,
    sessions: list[SlamLikeSession],
    work: Path,
    threads: int,
    sample_pairs: int,
    sample_images: int,
) -> dict[str, float]:
    """COLMAP from scratch (see the module docstring) on the images of our run `out`."""
    import pycolmap

    work.mkdir(parents=True, exist_ok=True)
    sfm = SfmFolder(out)
    images = sfm.images
    with pycolmap.Database.open(sfm.database) as handle:
        names = sorted(image.name for image in handle.read_all_images())
    n = len(names)
    exhaustive = n * (n - 1) / 2
    ours = {tuple(sorted(line.split())) for line in sfm.pairs.read_text().splitlines()}
    share = len(ours) / exhaustive
    rng = np.random.default_rng(0)
    figures: dict[str, float] = {"keyframes": n, "exhaustive_pairs": exhaustive}

    print("  (a) incremental mapping from scratch on our database (no priors), measured")
    db = work / "ours_no_priors.db"
    shutil.copyfile(sfm.database, db)
    figures["mapping_s"], poses = incremental(db, images, work / "inc_same", threads)
    ates = baseline_ate(poses, sessions, "incremental")
    figures["ate_sim3_max_m"] = float(np.nanmax(ates))
    print(f"    mapping {figures['mapping_s']:.1f} s")

    def pick(pool: list[str], count: int) -> list[tuple[str, str]]:
        """`count` random pairs of `pool`, overlapping ones in exhaustive's proportion."""
        pairs = [(a, b) for i, a in enumerate(pool) for b in pool[i + 1 :]]
        overlap = [p for p in pairs if p in ours]
        other = [p for p in pairs if p not in ours]
        k_overlap = min(max(round(count * share), 1), len(overlap))
        k_other = min(count - k_overlap, len(other))
        chosen = [overlap[i] for i in rng.permutation(len(overlap))[:k_overlap]]
        chosen += [other[i] for i in rng.permutation(len(other))[:k_other]]
        return chosen

    print("  (b) our feature budget, exhaustive matching (pair rate measured, extrapolated)")
    rate = _pair_rate(sfm.database, pick(names, sample_pairs), work, threads, "ours")
    figures["ours_pair_rate_s"] = rate
    figures["ours_exhaustive_s"] = rate * exhaustive
    print(
        f"    {rate * 1000:.0f} ms/pair (measured on {sample_pairs} pairs) x {exhaustive:.0f} "
        f"pairs = {figures['ours_exhaustive_s']:.0f} s (extrapolated)"
    )

    print(
        "  (c) pycolmap's default features (8192 SIFT, first octave -1), exhaustive matching "
        f"(measured on {sample_images} images and {sample_pairs} of their pairs, extrapolated)"
    )
    db = work / "defaults.db"
    shutil.copyfile(sfm.database, db)  # the same cameras and images, nothing else
    with pycolmap.Database.open(db) as handle:
        handle.clear_two_view_geometries()
        handle.clear_matches()
        handle.clear_descriptors()
        handle.clear_keypoints()
        handle.clear_pose_priors()
    some = sorted(names[i] for i in rng.permutation(n)[:sample_images])
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    start = time.perf_counter()
    pycolmap.extract_features(
        db, images, image_names=some, extraction_options=extraction, device=pycolmap.Device.cpu
    )
    per_image = (time.perf_counter() - start) / len(some)
    with pycolmap.Database.open(db) as handle:
        keypoints = handle.num_keypoints() / len(some)
    figures["defaults_extract_s"] = per_image * n
    print(
        f"    extraction {per_image:.2f} s/image ({keypoints:.0f} keypoints/image, measured) x "
        f"{n} = {figures['defaults_extract_s']:.0f} s (extrapolated)"
    )
    rate = _pair_rate(db, pick(some, sample_pairs), work, threads, "defaults")
    figures["defaults_pair_rate_s"] = rate
    figures["defaults_exhaustive_s"] = rate * exhaustive
    print(
        f"    matching {rate * 1000:.0f} ms/pair (measured) x {exhaustive:.0f} pairs = "
        f"{figures['defaults_exhaustive_s']:.0f} s (extrapolated)"
    )
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=600, help="survey size, all sessions")
    parser.add_argument("--sessions", type=int, default=2, help="simulated dives")
    parser.add_argument(
        "--ba-max-track-length",
        type=int,
        help="observations per point in each adjustment (0: no cap; default: the stage's)",
    )
    parser.add_argument(
        "--refine",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a RefineOptions field (repeatable), e.g. robust_prior_loss=false",
    )
    parser.add_argument("--fractions", default="0.27,0.54,1", help="sizes our stage runs at")
    parser.add_argument(
        "--baseline-fractions", default="0.54", help="sizes the baseline runs at ('' for none)"
    )
    parser.add_argument("--threads", type=int, default=-1)
    parser.add_argument(
        "--sample-pairs", type=int, default=300, help="pairs timed to extrapolate exhaustive"
    )
    parser.add_argument(
        "--sample-images", type=int, default=60, help="images timed at default extraction"
    )
    parser.add_argument(
        "--refine-only",
        action="store_true",
        help="rerun only the refinement on the databases an earlier run left in --work",
    )
    parser.add_argument("--work", type=Path, help="keep data and outputs here")
    args = parser.parse_args()
    # Absolute: the merge folder and the image links name the session folders.
    work = (args.work or Path(tempfile.mkdtemp(prefix="bench_sfm_"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    sessions = survey(work, args.keyframes, args.sessions)
    options = SfmOptions(features=FeatureOptions(num_threads=args.threads))
    options.refine.num_threads = args.threads
    if args.ba_max_track_length is not None:
        options.refine.ba_max_track_length = args.ba_max_track_length or None
    for setting in args.refine:
        set_refine_option(options, setting)
    print(
        f"ours: {options.features.max_num_features} SIFT features, first octave "
        f"{options.features.first_octave or 'auto'}, sequential "
        f"{options.pairs.sequential_neighbours} + spatial {options.pairs.spatial_neighbours} "
        f"pairs per keyframe; at most {options.refine.ba_max_track_length or 'all'} "
        f"observations per point in each adjustment; {os.cpu_count()} cores, load {load()}"
        + (f"; refine options set: {', '.join(args.refine)}" if args.refine else "")
    )

    fractions = [float(f) for f in args.fractions.split(",") if f]
    baseline_at = {float(f) for f in args.baseline_fractions.split(",") if f}
    rows = []
    if args.refine_only:
        baseline_at = set()
    for fraction in sorted(set(fractions) | baseline_at):
        part = subset(sessions, fraction, work / f"part_{fraction:.2f}")
        if args.refine_only:
            stats, total, cpu, poses = refine_only(part, options, work / f"ours_{fraction:.2f}")
            print(
                f"\n== ours, refinement only: {stats['keyframes']} keyframes, "
                f"{stats['registered_images']} registered, {stats['points3D']} points, "
                f"{total:.1f} s wall, {cpu:.1f} s CPU (load {load()})"
            )
            print(
                "  steps (wall): "
                + ", ".join(f"{k} {v:.1f} s" for k, v in stats["seconds"].items())
            )
            print_rounds(stats["rounds"])
            rows.append(
                {
                    "keyframes": stats["keyframes"],
                    "wall_s": total,
                    "cpu_s": cpu,
                    "observations_per_point": max(
                        (r.get("observations_per_point", 0.0) for r in stats["rounds"]),
                        default=0.0,
                    ),
                    "track_length": stats["mean_track_length"],
                    "ate_none_m": refined_ate_m(poses, part, "none"),
                    "ate_sim3_m": refined_ate_m(poses, part, "sim3"),
                }
            )
            continue
        stats, total, cpu, out = run_ours(part, options, work / f"ours_{fraction:.2f}")
        print_ours(stats, total, cpu, out, part)
        rows.append(
            {
                "keyframes": stats["keyframes"],
                "pairs": stats["pairs"]["total"],
                "wall_s": total,
                "cpu_s": cpu,
                "steps": stats["seconds"],
                "observations_per_point": max(
                    (r.get("observations_per_point", 0.0) for r in stats["rounds"]), default=0.0
                ),
                "track_length": stats["mean_track_length"],
                "ate_none_m": worst_ate_m(out, part, "none"),
                "ate_sim3_m": worst_ate_m(out, part, "sim3"),
            }
        )
        if fraction not in baseline_at:
            continue
        n = stats["keyframes"]
        print(f"\n== baseline at {n} keyframes (load {load()})")
        b = baseline(
            out,
            part,
            work / f"baseline_{fraction:.2f}",
            args.threads,
            args.sample_pairs,
            args.sample_images,
        )
        sec = stats["seconds"]
        mapping_ours = sec["refine_s"]
        ours_ate = rows[-1]["ate_sim3_m"]
        defaults = b["defaults_extract_s"] + b["defaults_exhaustive_s"] + b["mapping_s"]
        same = sec["extract_s"] + b["ours_exhaustive_s"] + b["mapping_s"]
        print(f"\n== ratio at {n} keyframes (load {load()})")
        print(
            f"  accuracy, worst session sim3 ATE: incremental {b['ate_sim3_max_m'] * 100:.2f} cm, "
            f"ours {ours_ate * 100:.2f} cm"
        )
        print(
            f"  mapping alone, same database (measured): incremental {b['mapping_s']:.1f} s vs "
            f"ours (triangulate + BA) {mapping_ours:.1f} s: x{b['mapping_s'] / mapping_ours:.1f}"
        )
        print(
            "  from images, as the paper (COLMAP default features, exhaustive matching, "
            f"incremental): extract {b['defaults_extract_s']:.0f} s (extrapolated) + match "
            f"{b['defaults_exhaustive_s']:.0f} s (extrapolated) + map {b['mapping_s']:.0f} s "
            f"(measured with our features: a lower bound) = {defaults:.0f} s vs ours "
            f"{total:.0f} s (measured): x{defaults / total:.1f}"
        )
        print(
            "  from images with our feature budget (exhaustive matching, incremental): extract "
            f"{sec['extract_s']:.0f} s (measured) + match {b['ours_exhaustive_s']:.0f} s "
            f"(extrapolated) + map {b['mapping_s']:.0f} s (measured) = {same:.0f} s vs ours "
            f"{total:.0f} s: x{same / total:.1f}"
        )

    print(f"\n== scaling (first part of each session, same density; load {load()})")
    rows.sort(key=lambda r: r["keyframes"])
    what = "refinement" if args.refine_only else "total"
    for r in rows:
        steps = r.get("steps")
        detail = (
            f"; extract {steps['extract_s']:.1f}, match {steps['match_s']:.1f}, refine "
            f"{steps['refine_s']:.1f} s wall"
            if steps
            else ""
        )
        print(
            f"  {r['keyframes']:5d} keyframes: {what} {r['wall_s']:6.1f} s wall, "
            f"{r['cpu_s']:6.1f} s CPU ({r['cpu_s'] / r['keyframes']:.3f} s/keyframe{detail}); "
            f"largest mean observations per point {r['observations_per_point']:.1f}, final "
            f"track length {r['track_length']:.1f}; worst session ATE "
            f"{r['ate_none_m'] * 100:.2f} cm (no alignment), {r['ate_sim3_m'] * 100:.2f} cm (sim3)"
        )
    if len(rows) > 1 and rows[-1]["keyframes"] > rows[0]["keyframes"]:
        ratio = np.log(rows[-1]["keyframes"] / rows[0]["keyframes"])
        k_cpu = np.log(rows[-1]["cpu_s"] / rows[0]["cpu_s"]) / ratio
        k_wall = np.log(rows[-1]["wall_s"] / rows[0]["wall_s"]) / ratio
        line = f"  k of the {what} ({rows[0]['keyframes']} -> {rows[-1]['keyframes']} "
        line += f"keyframes): CPU {k_cpu:.2f}, wall {k_wall:.2f}"
        if not args.refine_only:
            refine_s = [r["steps"]["refine_s"] for r in (rows[0], rows[-1])]
            line += f" (refinement alone, wall: {np.log(refine_s[1] / refine_s[0]) / ratio:.2f})"
        print(line)
    print(f"\n(work folder: {work})")


if __name__ == "__main__":
    main()
