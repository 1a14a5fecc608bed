"""Multi-session merging: ours against the paper's method on synthetic surveys, and
AprilGrid detection quality on the real photos.

    .venv/bin/python bench/bench_merge.py [--seeds 5] [--sessions 2] [--outliers 0.1]

Each seed renders a survey (`postproc.merge.synthetic.make_survey`): two grids
like the Pamir's (4x2 and 5x4 tags of 88 mm, 10 m apart on a tilted deck),
dives filming each grid in 2 passes of 10 keyframes at 0.8-2 m and up to 55
degrees off the normal, 960x540 images with strong barrel distortion, blur
and noise; SLAM keyframe poses with per-keyframe jitter (0.15 deg, 1 cm), a
drift shared by each pass (0.2 deg, 2 cm), a session tilt (0.05 deg) and 10 %
outlier keyframes (3-12 deg, 0.15-0.6 m). Every method then runs the whole
stage (`postproc.merge.stage.run`: detection, PnP, averaging, alignment) on
the same folders. Errors are those of `T_S1_Sk` (rotation angle, translation)
against the truth, RMS over seeds and sessions. The session and target yaws
stay within +-120 deg so the paper's Euler means never meet the +-180 wrap.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("WRECKMAP_PROGRESS", "0")

from postproc.merge.detect import (
    DetectionOptions,
    detect_tags,
    homography_residuals_px,
    line_fit_residuals_px,
)
from postproc.merge.stage import MergeOptions, run
from postproc.merge.synthetic import (
    SurveyOptions,
    SurveyTruth,
    apply_slam_error,
    make_survey,
    outlier_pose_error,
    random_pose_error,
    write_slam_folder,
)
from shared.calibration.aprilgrid import AprilGridTarget
from shared.formats.tum import read_tum
from shared.geometry import invert_pose, pose_difference

REPO = Path(__file__).resolve().parents[1]
METHODS = (
    ("paper (6 DoF, Euler)", MergeOptions(method="paper", plot=False)),
    ("ours 6 DoF", MergeOptions(method="ours", dof=6, plot=False)),
    ("ours 4 DoF", MergeOptions(method="ours", dof=4, plot=False)),
)


def bench_photos() -> None:
    import cv2

    grid = AprilGridTarget(tag_rows=6, tag_cols=6, tag_size_m=0.088, tag_spacing_ratio=0.3)
    folder = REPO.parent / "shared" / "data" / "aprilgrid"
    print("real photos (6x6 Kalibr grid on a monitor, 3072x4080 phone images)")
    print(
        f"{'photo':<8} {'refine':<7} {'tags':>4} {'time s':>7} {'line med px':>12} "
        f"{'line rms px':>12} {'H rms px':>9}"
    )
    for name in ("000.jpg", "001.jpg"):
        image = cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
        if image is None:
            print(f"{name}: missing")
            continue
        for subpix in (False, True):
            start = time.perf_counter()
            detections = detect_tags(image, DetectionOptions(subpix=subpix))
            elapsed = time.perf_counter() - start
            lines = line_fit_residuals_px(detections, grid)
            homography = homography_residuals_px(detections, grid)
            print(
                f"{name:<8} {'subpix' if subpix else 'none':<7} {len(detections):>4} "
                f"{elapsed:>7.2f} {np.median(lines):>12.3f} {np.sqrt(np.mean(lines**2)):>12.3f} "
                f"{np.sqrt(np.mean(homography**2)):>9.3f}"
            )
    print()


def make_fieldsim_survey(
    root: Path,
    seed: int,
    sessions: int,
    duration_s: float,
    outliers: float,
    *,
    yaw_drift_only: bool = True,
) -> tuple[list[Path], list[Path], SurveyTruth]:
    """SLAM-like folders from the survey simulator (`field.sim`): its wreck, its two hull
    grids, its diver routes and renderer; SLAM errors added to the true camera poses.

    Keyframes at 1 Hz where a grid is within 3.5 m and at least half in view. SLAM error:
    a random-walk drift (0.02 deg and 3 mm per sqrt(s); the rotation about z only unless
    `yaw_drift_only` is false), per-keyframe jitter (0.15 deg, 1 cm), a session tilt
    (0.05 deg) and `outliers` gross errors (3-12 deg, 0.15-0.6 m).
    """
    import cv2

    from field.sim.survey import SurveyOptions as SimOptions
    from field.sim.survey import SurveySimulator
    from shared.calibration.kalibr import write_target_yaml
    from shared.geometry import make_pose, so3_exp

    sim = SurveySimulator(
        SimOptions(
            sessions=sessions, duration_s=duration_s, width=960, height=540, video=False, seed=seed
        )
    )
    camera = sim.camera
    rng = np.random.default_rng(1000 + seed)
    placements = sim.scene_targets
    target_paths = [
        write_target_yaml(root / "targets" / f"{p.name}.yaml", p.target) for p in placements
    ]
    folders, world_from_session = [], {}
    step = max(round(sim.options.fps), 1)
    for k, session in enumerate(sim.sessions):
        stamps = session.frame_stamps_cam_ns[::step]
        world_from_cam = sim.world_from_cam(k, stamps)
        seen = np.zeros(len(stamps), dtype=bool)
        for placement in placements:
            _, corners = placement.target.all_corner_points()
            points = corners.reshape(-1, 3)
            for i, pose in enumerate(world_from_cam):
                cam_from_target = invert_pose(pose) @ placement.world_from_target
                p_cam = points @ cam_from_target[:3, :3].T + cam_from_target[:3, 3]
                if np.any(p_cam[:, 2] <= 0.1) or np.linalg.norm(cam_from_target[:3, 3]) > 3.5:
                    continue
                px = camera.project(p_cam)
                inside = (px[:, 0] >= 0) & (px[:, 0] < camera.width)
                inside &= (px[:, 1] >= 0) & (px[:, 1] < camera.height)
                seen[i] |= inside.mean() >= 0.5
        # The session frame: gravity-aligned (up to a small tilt) at the first camera.
        first = world_from_cam[0]
        yaw = np.arctan2(first[1, 2], first[0, 2])
        tilt = so3_exp(np.r_[rng.normal(0, np.deg2rad(0.05), 2), 0.0])
        c, s_ = np.cos(yaw), np.sin(yaw)
        w_from_s = make_pose(tilt @ np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]), first[:3, 3])
        world_from_session[f"dive{k + 1}"] = w_from_s
        drift_rot = np.zeros(3)
        drift_t = np.zeros(3)
        axes = np.array([0.0, 0.0, 1.0]) if yaw_drift_only else np.ones(3)
        kept_stamps, estimates, images = [], [], []
        previous = int(stamps[0])
        for i, stamp in enumerate(stamps):
            dt = (int(stamp) - previous) / 1e9
            previous = int(stamp)
            # Visual-inertial SLAM sees gravity: roll and pitch stay bounded, yaw drifts.
            drift_rot += rng.normal(0, np.deg2rad(0.02) * np.sqrt(dt), 3) * axes
            drift_t += rng.normal(0, 0.003 * np.sqrt(dt), 3)
            if not seen[i]:
                continue
            error = make_pose(so3_exp(drift_rot), drift_t) @ random_pose_error(rng, 0.15, 0.01)
            if rng.uniform() < outliers:
                error = outlier_pose_error(rng, (3.0, 12.0), (0.15, 0.6))
            session_from_cam = invert_pose(w_from_s) @ world_from_cam[i]
            estimates.append(apply_slam_error(session_from_cam, error))
            rgb = sim.render_frame(k, int(stamp)).image_rgb
            images.append(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
            kept_stamps.append(int(stamp))
        folders.append(
            write_slam_folder(
                root / f"dive{k + 1}", camera, kept_stamps, np.array(estimates), images
            )
        )
    truth = SurveyTruth(
        world_from_session=world_from_session,
        world_from_target={p.name: p.world_from_target for p in placements},
        outlier_stamps_ns={},
    )
    return folders, target_paths, truth


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--sessions", type=int, default=2)
    parser.add_argument("--outliers", type=float, default=0.1, help="outlier keyframe share")
    parser.add_argument("--no-photos", action="store_true")
    parser.add_argument(
        "--scene",
        choices=("synthetic", "fieldsim"),
        default="synthetic",
        help="synthetic: postproc.merge.synthetic surveys; fieldsim: field.sim's wreck and routes",
    )
    parser.add_argument("--duration", type=float, default=240.0, help="fieldsim: s per dive")
    parser.add_argument(
        "--tilt-drift",
        action="store_true",
        help="fieldsim: let roll and pitch drift too (default: yaw only, as VI-SLAM)",
    )
    args = parser.parse_args()
    if not args.no_photos:
        bench_photos()

    errors: dict[str, list[tuple[float, float, float]]] = {name: [] for name, _ in METHODS}
    times: dict[str, list[float]] = {name: [] for name, _ in METHODS}
    sigmas: dict[str, list[tuple[float, float]]] = {name: [] for name, _ in METHODS}
    with tempfile.TemporaryDirectory(prefix="bench_merge_") as tmp:
        for seed in range(args.seeds):
            root = Path(tmp) / f"seed{seed}"
            start = time.perf_counter()
            if args.scene == "synthetic":
                folders, targets, truth = make_survey(
                    root,
                    SurveyOptions(sessions=args.sessions, outlier_fraction=args.outliers),
                    seed=seed,
                )
            else:
                folders, targets, truth = make_fieldsim_survey(
                    root,
                    seed,
                    args.sessions,
                    args.duration,
                    args.outliers,
                    yaw_drift_only=not args.tilt_drift,
                )
            render_s = time.perf_counter() - start
            keyframes = sum(len(list((f / "keyframes").iterdir())) for f in folders)
            line = f"seed {seed}: {keyframes} keyframes rendered in {render_s:.0f} s;"
            for name, options in METHODS:
                start = time.perf_counter()
                out = root / name.replace(" ", "_").replace(",", "").replace("(", "")
                document = json.loads(run(options, folders, targets, out).read_text())
                times[name].append(time.perf_counter() - start)
                reference = truth.world_from_session["dive1"]
                for k in range(2, args.sessions + 1):
                    entry = document["sessions"][f"dive{k}"]
                    if not entry["placed"]:
                        errors[name].append((np.inf, np.inf, np.inf))
                        continue
                    expected = invert_pose(reference) @ truth.world_from_session[f"dive{k}"]
                    estimate = np.array(entry["T_W_S"])
                    rot, trans = pose_difference(estimate, expected)
                    # Where it matters: the session's keyframes (the map) moved into W.
                    points = read_tum(folders[k - 1] / "keyframes.tum").positions
                    moved = points @ (estimate[:3, :3] - expected[:3, :3]).T
                    moved += estimate[:3, 3] - expected[:3, 3]
                    map_error = float(np.sqrt(np.mean(np.sum(moved**2, axis=1))))
                    errors[name].append((np.rad2deg(rot), trans, map_error))
                    sigmas[name].append((entry["sigma_rotation_deg"], entry["sigma_translation_m"]))
                rot_e, trans_e, map_e = errors[name][-1]
                line += (
                    f" {name.split(' (')[0]}: {rot_e:.3f} deg {100 * trans_e:.1f} cm"
                    f" map {100 * map_e:.1f} cm;"
                )
            print(line, flush=True)

    print()
    print(f"session-to-session error, RMS over {args.seeds} seeds x {args.sessions - 1} session(s)")
    print("(trans: at the session origin; map: RMS over the session's keyframe positions)")
    print(
        f"{'method':<22} {'rot RMS deg':>12} {'rot max deg':>12} {'trans RMS cm':>13} "
        f"{'map RMS cm':>11} {'map max cm':>11} {'reported 1-sigma (deg, cm)':>28} {'run s':>6}"
    )
    rms = {}
    for name, _ in METHODS:
        e = np.array(errors[name])
        rms[name] = np.sqrt(np.mean(e**2, axis=0))
        s = np.array(sigmas[name]) if sigmas[name] else np.full((1, 2), np.nan)
        print(
            f"{name:<22} {rms[name][0]:>12.3f} {e[:, 0].max():>12.3f} "
            f"{100 * rms[name][1]:>13.2f} {100 * rms[name][2]:>11.2f} {100 * e[:, 2].max():>11.2f} "
            f"{np.mean(s[:, 0]):>14.3f}, {100 * np.mean(s[:, 1]):>11.2f} "
            f"{np.mean(times[name]):>6.1f}"
        )
    paper = rms[METHODS[0][0]]
    print()
    print("median over seeds and sessions (rot deg, trans cm, map cm):")
    medians = {}
    for name, _ in METHODS:
        medians[name] = np.median(np.array(errors[name]), axis=0)
        m = medians[name]
        print(f"  {name:<22} {m[0]:.3f} deg  {100 * m[1]:.2f} cm  map {100 * m[2]:.2f} cm")
    print()
    for name, _ in METHODS[1:]:
        print(
            f"paper / {name}: rotation {paper[0] / rms[name][0]:.1f}x, "
            f"translation {paper[1] / rms[name][1]:.1f}x, map {paper[2] / rms[name][2]:.1f}x "
            "(target: >= 2x)"
        )
        m, p = medians[name], medians[METHODS[0][0]]
        print(
            f"  medians: rotation {p[0] / m[0]:.1f}x, translation {p[1] / m[1]:.1f}x, "
            f"map {p[2] / m[2]:.1f}x"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
