"""Multi-session merging: ours against the paper's method on synthetic surveys and on
the simulated wreck, and AprilGrid detection quality on the real photos.

    .venv/bin/python bench/bench_merge.py [--seeds 5] [--sessions 2] [--outliers 0.1]
    .venv/bin/python bench/bench_merge.py --scene fieldsim --seeds 8 [--cache DIR]
    .venv/bin/python bench/bench_merge.py --scene fieldsim --every-keyframe --features \
        --seeds 8 --no-photos --cache DIR [--sfm] [--draws 4]

Synthetic (`sim.targets.make_survey`): two grids like the Pamir's
(4x2 and 5x4 tags of 88 mm, 10 m apart on a tilted deck), dives filming each
grid in 2 passes of 10 keyframes at 0.8-2 m and up to 55 degrees off the
normal, 960x540 images with strong barrel distortion, blur and noise; SLAM
keyframe poses with per-keyframe jitter (0.15 deg, 1 cm), an independent
error per pass (0.2 deg, 2 cm), a session tilt (0.05 deg) and 10 % outlier
keyframes (3-12 deg, 0.15-0.6 m). The session and target yaws stay within
+-120 deg so the paper's Euler means never meet the +-180 wrap.

Wreck (`--scene fieldsim`): `sim`'s wreck, hull grids, diver routes and
renderer; keyframes at 1 Hz where a grid is in view; the SLAM error is a random
walk from the session start (see `make_fieldsim_survey`), so a target filmed
late carries more drift than one filmed early.

Every method runs the whole stage (`postproc.merge.stage.run`: detection, PnP,
averaging, alignment) on the same folders; the tag detections of a keyframe are
computed once and shared (`memoise_detections`), so the run times below are
those of PnP, averaging and alignment, plus detection for the first method.
Two errors, the same for every method:

* session frame: `T_S1_Sk` against the truth. The truth is each session's frame
  where its SLAM defines it (the first pose, where the drift is zero), which is
  what `T_W_S` in transforms.json claims to be. No target-based method reaches
  zero here: it sees the frame only through keyframes that have drifted since.
* at the targets (wreck only): what merging is for, the two maps laid over each
  other where they overlap. Near target m, session s's map sits in a frame
  `A_s,m` off its true frame (the mean drift of the keyframes that see m, from
  the simulator's per-keyframe truth); the transform that overlays the maps
  there is `T*_m = A_1,m inv(T_W_S1) T_W_Sk inv(A_k,m)`. The error is the
  rotation between `T_S1_Sk` and `T*_m` and the distance it moves the target's
  centre from where `T*_m` puts it, RMS over targets. When the two targets'
  `T*_m` disagree (drift between them) no rigid transform satisfies both:
  "ideal rigid" takes the mean rotation of the `T*_m` (its rotation error is
  the lowest any single transform can have there) and the translation that
  zeroes the mean position error over the targets (a compromise, not a bound).

With a random-walk drift the two ask for different transforms: the frame is
best found from the earliest passes (our drift-weighted mean), the overlay at
the targets from all passes alike ("plain mean"). Errors are RMS over seeds and
sessions; `--cache` keeps the rendered folders so methods can be rerun.

"tilt prior" rows: the 6-DoF fit with a gravity prior on the relative roll and
pitch (`MergeOptions.tilt_sigma_deg`), given the simulators' own per-session
tilt (`SIM_TILT_SIGMA_DEG`), as a SLAM would report its roll/pitch uncertainty.
A 4-DoF fit keeps the sessions' whole relative tilt (0.1 deg RMS here), a plain
6-DoF fit all of the targets' tilt noise; the prior weighs the two.

Natural features (`--scene fieldsim --every-keyframe --features`): keyframes at
1 Hz along the whole dive (as a SLAM writes them, not only near the grids), and
two more rows over the same folders and seeds: "features only (no targets)" (the
target YAMLs are not given: place recognition, verification and the joint
estimate alone) and "targets + features" (both in the joint estimate). A third
error table, "where the maps share structure", is the overlay error of
`T_S1_Sk` at keyframe pairs that film the same place (`shared_structure_references`),
the natural-feature analogue of the at-targets error. With every keyframe the
target rows see the grids from further and more obliquely than in the default
scene, so their figures differ from a run without `--every-keyframe`.

After SfM (`--sfm`, wreck only): the SfM stage (`postproc.sfm.stage.run`, default
options) runs on the merge of the methods in `SFM_METHODS`, and two errors of the
maps laid over each other are printed for the merged keyframes (before) and the
refined ones (after), the same for every method:

* maps: each session's keyframes are fitted rigidly to their true positions
  (`A_k`, outlier keyframes left out); `inv(A_1) A_k` is how far session k's map as a
  whole sits from where session 1's puts it: its rotation, and the RMS distance it
  moves session k's keyframes. Unlike the session frame above it does not depend on
  the drift at the session start, so it is defined after SfM too, where no `T_W_S`
  is refined.
* shared places: per keyframe pair filming the same structure (as above, true
  poses), the relative pose of the two cameras against the truth: its rotation, and
  the error of the point 2.5 m ahead of session k's camera seen from session 1's.

Draws (`--draws N`, wreck with `--every-keyframe`): one rendered seed is one scene,
and its SLAM errors one draw from the error model (`SlamErrors`), so a handful of seeds
decides little: on the four 240 s seeds the render's own draws put the targets alone at
0.060 deg and twelve fresh draws of the same scenes at 0.120 deg. With `--draws N`
every seed is merged again with N - 1 fresh draws of its SLAM errors
(`redraw_fieldsim`: the same images, targets and truth, new keyframe poses), and
every row pools seeds x draws; the first draw is the render's own.

"floor: exact at 1st sight" (wreck only): `T_S1_Sk` from targets known exactly
at each session's first sighting. The drift before it is in every later keyframe
and nothing observed tells it apart from the frame, so no target method beats
this row's session-frame error on average (`first_sighting_floor`); its
"reported" column is the rotation error the drift model expects there.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import pickle
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("WRECKMAP_PROGRESS", "0")

from postproc.merge.stage import MergeOptions, run
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.aprilgrid_detection import (
    DetectionOptions,
    detect_tags,
    homography_residuals_px,
    line_fit_residuals_px,
)
from shared.clock import seconds_from_ns
from shared.folders import SlamFolder
from shared.geometry import (
    invert_pose,
    make_pose,
    pose_difference,
    rotation_angle_rad,
    rotation_mean_chordal,
    so3_exp,
    umeyama_pose,
)
from shared.trajectory import Trajectory
from sim.targets import (
    SurveyOptions,
    SurveyTruth,
    apply_slam_error,
    make_survey,
    outlier_pose_error,
    random_pose_error,
    write_slam_folder,
)

REPO = Path(__file__).resolve().parents[1]
FloatArray = npt.NDArray[np.float64]
#: Roll/pitch error (deg, 1 sigma per axis) of each simulated session's gravity alignment:
#: `SurveyOptions.tilt_deg` and the tilt in `make_fieldsim_survey`. The "tilt prior" rows
#: are given it, as a SLAM would report its own tilt uncertainty.
SIM_TILT_SIGMA_DEG = SurveyOptions().tilt_deg
METHODS = (
    ("paper (6 DoF, Euler)", MergeOptions(method="paper", plot=False)),
    ("ours 6 DoF", MergeOptions(method="ours", dof=6, natural_features=False, plot=False)),
    ("ours 4 DoF", MergeOptions(method="ours", dof=4, natural_features=False, plot=False)),
    (
        "ours 4 DoF, plain mean",
        MergeOptions(
            method="ours", dof=4, drift_weighting=False, natural_features=False, plot=False
        ),
    ),
    (
        "ours 6 DoF + tilt prior",
        MergeOptions(
            method="ours",
            dof=6,
            tilt_sigma_deg=SIM_TILT_SIGMA_DEG,
            natural_features=False,
            plot=False,
        ),
    ),
    (
        "ours tilt prior, plain mean",
        MergeOptions(
            method="ours",
            dof=6,
            tilt_sigma_deg=SIM_TILT_SIGMA_DEG,
            drift_weighting=False,
            natural_features=False,
            plot=False,
        ),
    ),
)
#: Natural-feature rows (`--features`): the joint estimate with no targets at all
#: (the target YAMLs are not given) and with targets and features together.
FEATURE_METHODS = (
    (
        "features only (no targets)",
        MergeOptions(method="ours", dof=6, tilt_sigma_deg=SIM_TILT_SIGMA_DEG, plot=False),
    ),
    (
        "targets + features",
        MergeOptions(
            method="ours",
            dof=6,
            tilt_sigma_deg=SIM_TILT_SIGMA_DEG,
            natural_features=True,
            plot=False,
        ),
    ),
)
NO_TARGETS = FEATURE_METHODS[0][0]
#: The fieldsim SLAM's rotation drift, a random walk (deg per sqrt(s), 1 sigma per axis).
DRIFT_RATE_DEG = 0.02
#: Each fieldsim keyframe's own SLAM error besides the drift (deg, m; 1 sigma per axis).
JITTER = (0.15, 0.01)
#: The methods whose merge the SfM stage refines with `--sfm`: the paper's, the
#: target-only row the feature rows compare with, and both feature rows.
SFM_METHODS = ("paper (6 DoF, Euler)", "ours 6 DoF + tilt prior", *(n for n, _ in FEATURE_METHODS))
#: The session-frame row no estimator can beat on average (wreck only, see `first_sighting_floor`).
FLOOR = "floor: exact at 1st sight"


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
            detections = detect_tags(np.asarray(image, np.uint8), DetectionOptions(subpix=subpix))
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
    every_keyframe: bool = False,
    jitter: tuple[float, float] = JITTER,
) -> tuple[list[Path], list[Path], SurveyTruth]:
    """SLAM-like folders from the survey simulator (`sim`): its wreck, its two hull
    grids, its diver routes and renderer; SLAM errors added to the true camera poses.

    Keyframes at 1 Hz where a grid is within 3.5 m and at least half in view. SLAM error:
    a random-walk drift (0.02 deg and 3 mm per sqrt(s); the rotation about z only unless
    `yaw_drift_only` is false), per-keyframe jitter (`jitter`: deg and m, 1 sigma per
    axis; default `JITTER`), a session tilt
    (0.05 deg) and `outliers` gross errors (3-12 deg, 0.15-0.6 m). `every_keyframe`:
    keyframes at 1 Hz along the whole dive, as a SLAM writes them (natural-feature
    merging needs the structure between the targets too).
    """
    import cv2

    from shared.calibration.kalibr import write_target_yaml
    from sim.survey import SurveyOptions as SimOptions
    from sim.survey import SurveySimulator

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
    outlier_stamps: dict[str, list[int]] = {}
    step = max(round(sim.options.fps), 1)
    for k, session in enumerate(sim.sessions):
        stamps = session.frame_stamps_cam_ns[::step]
        world_from_cam = sim.world_from_cam(k, stamps)
        seen_by = {p.name: np.zeros(len(stamps), dtype=bool) for p in placements}
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
                seen_by[placement.name][i] = inside.mean() >= 0.5
        seen = np.any(np.array(list(seen_by.values())), axis=0)
        if every_keyframe:
            seen = np.ones(len(stamps), dtype=bool)
        # The session frame: gravity-aligned (up to a small tilt) at the first camera.
        first = world_from_cam[0]
        yaw = np.arctan2(first[1, 2], first[0, 2])
        tilt = so3_exp(np.r_[rng.normal(0, np.deg2rad(0.05), 2), 0.0])
        c, s_ = np.cos(yaw), np.sin(yaw)
        w_from_s = make_pose(tilt @ np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]), first[:3, 3])
        world_from_session[f"dive{k + 1}"] = w_from_s
        errors = SlamErrors(rng, yaw_drift_only=yaw_drift_only, jitter=jitter, outliers=outliers)
        kept_stamps, estimates, images = [], [], []
        true_poses, drift_poses, outlier_flags, kept_index = [], [], [], []
        slam_poses = []
        previous = int(stamps[0])
        for i, stamp in enumerate(stamps):
            drift = errors.drift_after(seconds_from_ns(int(stamp) - previous))
            previous = int(stamp)
            slam_poses.append(apply_slam_error(invert_pose(w_from_s) @ world_from_cam[i], drift))
            if not seen[i]:
                continue
            error, outlier = errors.keyframe_error(drift)
            session_from_cam = invert_pose(w_from_s) @ world_from_cam[i]
            estimates.append(apply_slam_error(session_from_cam, error))
            true_poses.append(session_from_cam)
            drift_poses.append(apply_slam_error(session_from_cam, drift))
            outlier_flags.append(outlier)
            kept_index.append(i)
            rgb = sim.render_frame(k, int(stamp)).image_rgb
            images.append(np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), np.uint8))
            kept_stamps.append(int(stamp))
        folders.append(
            write_slam_folder(
                root / f"dive{k + 1}", camera, kept_stamps, np.array(estimates), images
            )
        )
        # The SLAM trajectory from the session start (its first pose anchors the frame);
        # camera poses stand in for the body's here: the stage only reads its stamps.
        SlamFolder(root / f"dive{k + 1}").write_trajectory(Trajectory(stamps, np.array(slam_poses)))
        # Per-keyframe truth for the at-target reference (beside the folders, not in them).
        np.savez(
            root / f"truth_dive{k + 1}.npz",
            stamps_ns=np.array(kept_stamps, dtype=np.int64),
            session_from_cam_true=np.array(true_poses),
            session_from_cam_drift=np.array(drift_poses),
            outlier=np.array(outlier_flags, dtype=bool),
            allow_pickle=True,  # numpy's default, named so that mypy maps the masks to **kwds
            **{f"seen_{name}": mask[kept_index] for name, mask in seen_by.items()},
        )
        outlier_stamps[f"dive{k + 1}"] = [
            t for t, o in zip(kept_stamps, outlier_flags, strict=True) if o
        ]
    truth = SurveyTruth(
        world_from_session=world_from_session,
        world_from_target={p.name: p.world_from_target for p in placements},
        outlier_stamps_ns=outlier_stamps,
    )
    return folders, target_paths, truth


class SlamErrors:
    """The wreck scene's SLAM error model, drawn keyframe by keyframe from `rng`.

    A random-walk drift from the session anchor (0.02 deg and 3 mm per sqrt(s); the
    rotation about z only when `yaw_drift_only`, as a visual-inertial SLAM sees
    gravity), each keyframe's own jitter (`jitter`: deg and m, 1 sigma per axis) and a
    share `outliers` of gross errors (3-12 deg, 0.15-0.6 m).
    """

    def __init__(
        self,
        rng: np.random.Generator,
        *,
        yaw_drift_only: bool,
        jitter: tuple[float, float],
        outliers: float,
    ) -> None:
        self.rng = rng
        self.axes = np.array([0.0, 0.0, 1.0]) if yaw_drift_only else np.ones(3)
        self.jitter = jitter
        self.outliers = outliers
        self.rotation = np.zeros(3)
        self.translation = np.zeros(3)

    def drift_after(self, dt_s: float) -> FloatArray:
        """The drift (4, 4) `dt_s` seconds after the previous keyframe's."""
        step = np.deg2rad(DRIFT_RATE_DEG) * np.sqrt(dt_s)
        self.rotation += self.rng.normal(0, step, 3) * self.axes
        self.translation += self.rng.normal(0, 0.003 * np.sqrt(dt_s), 3)
        return make_pose(so3_exp(self.rotation), self.translation)

    def keyframe_error(self, drift: FloatArray) -> tuple[FloatArray, bool]:
        """A keyframe's whole error (4, 4) at `drift`, and whether it is an outlier."""
        error = drift @ random_pose_error(self.rng, *self.jitter)
        outlier = bool(self.rng.uniform() < self.outliers)
        if outlier:
            error = outlier_pose_error(self.rng, (3.0, 12.0), (0.15, 0.6))
        return error, outlier


def redraw_fieldsim(
    root: Path,
    dest: Path,
    seed: int,
    draw: int,
    *,
    yaw_drift_only: bool,
    jitter: tuple[float, float],
    outliers: float,
) -> tuple[Path, list[Path], list[Path], SurveyTruth]:
    """The rendered wreck survey at `root` (`make_fieldsim_survey` with `every_keyframe`)
    with its SLAM errors drawn again (stream `(seed, draw)`), written to `dest`.

    The images, targets, true poses and session frames stay; the keyframe poses, the
    trajectory and the per-keyframe truth (drift, outliers) are new. The keyframe
    images are linked, not copied. Returns what `make_fieldsim_survey` returns, with
    `dest` first.
    """
    with (root / "bench_truth.pkl").open("rb") as f:
        folders, targets, truth = pickle.load(f)
    rng = np.random.default_rng((seed, draw))
    new_folders = []
    outlier_stamps: dict[str, list[int]] = {}
    for folder in folders:
        name = Path(folder).name
        data = dict(np.load(root / f"truth_{name}.npz"))
        stamps = data["stamps_ns"]
        true = data["session_from_cam_true"]
        if len(SlamFolder(folder).read_trajectory().stamps_ns) != len(stamps):
            raise ValueError(f"{root}: redrawing needs every keyframe (--every-keyframe)")
        errors = SlamErrors(rng, yaw_drift_only=yaw_drift_only, jitter=jitter, outliers=outliers)
        estimates, drifts, flags = [], [], []
        previous = int(stamps[0])
        for stamp, session_from_cam in zip(stamps, true, strict=True):
            drift = errors.drift_after(seconds_from_ns(int(stamp) - previous))
            previous = int(stamp)
            error, outlier = errors.keyframe_error(drift)
            estimates.append(apply_slam_error(session_from_cam, error))
            drifts.append(apply_slam_error(session_from_cam, drift))
            flags.append(outlier)
        out = dest / name
        out.mkdir(parents=True)
        slam = SlamFolder(out)
        slam.keyframes.symlink_to(SlamFolder(folder).keyframes.resolve(), target_is_directory=True)
        shutil.copytree(Path(folder) / "calib", out / "calib")
        slam.write_keyframes(Trajectory(stamps, np.array(estimates)))
        slam.write_trajectory(Trajectory(stamps, np.array(drifts)))
        data.update(session_from_cam_drift=np.array(drifts), outlier=np.array(flags, dtype=bool))
        np.savez(dest / f"truth_{name}.npz", **data)
        outlier_stamps[name] = [int(t) for t, o in zip(stamps, flags, strict=True) if o]
        new_folders.append(out)
    return dest, new_folders, targets, replace(truth, outlier_stamps_ns=outlier_stamps)


def at_target_references(
    root: Path, truth: SurveyTruth, reference: str, session: str
) -> list[tuple[FloatArray, FloatArray]]:
    """Per target seen by both sessions: (T*_m, target centre in the session's map).

    The SLAM map of session s near target m sits in a frame `A_s,m` off the true
    session frame: the mean over the (non-outlier) keyframes that see m of their
    drift `T_S_C_slam @ inv(T_S_C_true)`. The transform that overlays the two maps
    at m is `T*_m = A_1,m @ inv(T_W_S1) @ T_W_Sk @ inv(A_k,m)`.
    """
    data = {name: np.load(root / f"truth_{name}.npz") for name in (reference, session)}
    frames = {}
    for name, d in data.items():
        for target in truth.world_from_target:
            chosen = d[f"seen_{target}"] & ~d["outlier"]
            if not np.any(chosen):
                continue
            drift = d["session_from_cam_drift"][chosen] @ np.linalg.inv(
                d["session_from_cam_true"][chosen]
            )
            frames[name, target] = make_pose(
                rotation_mean_chordal(drift[:, :3, :3], np.ones(len(drift))),
                drift[:, :3, 3].mean(axis=0),
            )
    expected = invert_pose(truth.world_from_session[reference]) @ truth.world_from_session[session]
    out = []
    for target, world_from_target in truth.world_from_target.items():
        if (reference, target) not in frames or (session, target) not in frames:
            continue
        a1, ak = frames[reference, target], frames[session, target]
        centre = ak @ invert_pose(truth.world_from_session[session]) @ world_from_target
        out.append((a1 @ expected @ invert_pose(ak), centre[:3, 3]))
    return out


def at_target_error(
    estimate: FloatArray, references: list[tuple[FloatArray, FloatArray]]
) -> list[tuple[float, float]]:
    """(rotation deg, position error m at the target centre) of `estimate` per target."""
    out = []
    for wanted, centre in references:
        rot, _ = pose_difference(estimate, wanted)
        moved = estimate[:3, :3] @ centre + estimate[:3, 3]
        out.append(
            (
                float(np.rad2deg(rot)),
                float(np.linalg.norm(moved - wanted[:3, :3] @ centre - wanted[:3, 3])),
            )
        )
    return out


def shared_structure_references(
    root: Path, truth: SurveyTruth, reference: str, session: str, *, limit: int = 300
) -> list[tuple[FloatArray, FloatArray]]:
    """Per keyframe pair that films the same structure: (T*, that structure in session k's map).

    Two keyframes (one per session, non-outliers) share structure when the points 2.5 m
    ahead of the true cameras lie within 1 m and the viewing directions within 30
    degrees. There the maps sit in frames `A_1(t1)`, `A_k(tk)` off the true session
    frames (the drift of those keyframes), and `T* = A_1 inv(T_W_S1) T_W_Sk inv(A_k)`
    overlays them; the point is the one 2.5 m ahead of session k's camera in its map.
    At most `limit` pairs, evenly spread over the list.
    """
    data = [np.load(root / f"truth_{name}.npz") for name in (reference, session)]
    world = [truth.world_from_session[reference], truth.world_from_session[session]]
    expected = invert_pose(world[0]) @ world[1]
    out = []
    for i, j in _shared_pairs(data, world, limit):
        a1 = data[0]["session_from_cam_drift"][i] @ invert_pose(data[0]["session_from_cam_true"][i])
        ak = data[1]["session_from_cam_drift"][j] @ invert_pose(data[1]["session_from_cam_true"][j])
        point = data[1]["session_from_cam_drift"][j] @ np.array([0.0, 0.0, 2.5, 1.0])
        out.append((a1 @ expected @ invert_pose(ak), point[:3]))
    return out


def _shared_pairs(
    data: list[dict[str, npt.NDArray[np.generic]]], world: list[FloatArray], limit: int
) -> npt.NDArray[np.int64]:
    """Index pairs (i, j) of two sessions' keyframes filming the same structure.

    data: each session's truth (`truth_<session>.npz`); world: their true `T_W_S`.
    The points 2.5 m ahead of the true cameras lie within 1 m, the viewing directions
    within 30 degrees, neither keyframe is an outlier; at most `limit` pairs, evenly
    spread over the list.
    """
    cams = [
        w @ np.asarray(d["session_from_cam_true"], np.float64)
        for w, d in zip(world, data, strict=True)
    ]
    ahead = [c[:, :3, 3] + 2.5 * c[:, :3, 2] for c in cams]
    distance = np.linalg.norm(ahead[0][:, None] - ahead[1][None], axis=2)
    cosine = np.einsum("id,jd->ij", cams[0][:, :3, 2], cams[1][:, :3, 2])
    good = (distance < 1.0) & (cosine > np.cos(np.deg2rad(30.0)))
    good &= ~data[0]["outlier"][:, None].astype(bool) & ~data[1]["outlier"][None].astype(bool)
    pairs = np.argwhere(good)
    if len(pairs) > limit:
        pairs = pairs[np.linspace(0, len(pairs) - 1, limit).astype(int)]
    return pairs


def overlay_errors(
    root: Path,
    truth: SurveyTruth,
    reference: str,
    session: str,
    world_from_cam: dict[str, Trajectory],
    *,
    limit: int = 300,
) -> tuple[tuple[float, float], list[tuple[float, float]]]:
    """How well the estimated maps of `reference` and `session` lie over each other.

    world_from_cam: each session's keyframe poses `T_W_C` as a stage wrote them (the
    merge's keyframes, or the SfM's refined ones), at the simulator's keyframe stamps.
    Returns ((rotation deg, RMS distance m) of session's map as a whole against the
    reference's, the shared places' [(rotation deg, position error m)]); see the module
    docstring ("After SfM").
    """
    names = (reference, session)
    data = [dict(np.load(root / f"truth_{name}.npz")) for name in names]
    world = [truth.world_from_session[name] for name in names]
    to_reference = invert_pose(world[0])
    true_cams, cams = [], []
    for name, d, w in zip(names, data, world, strict=True):
        index = {int(t): i for i, t in enumerate(world_from_cam[name].stamps_ns)}
        rows = [index[int(t)] for t in d["stamps_ns"]]
        cams.append(world_from_cam[name].poses[rows])
        true_cams.append(to_reference @ w @ d["session_from_cam_true"])
    fitted = []
    for cam, true, d in zip(cams, true_cams, data, strict=True):
        good = ~d["outlier"].astype(bool)
        fitted.append(umeyama_pose(true[good, :3, 3], cam[good, :3, 3]))
    misplaced = invert_pose(fitted[0]) @ fitted[1]
    points = true_cams[1][:, :3, 3]
    moved = points @ misplaced[:3, :3].T + misplaced[:3, 3] - points
    maps = (
        float(np.rad2deg(rotation_angle_rad(misplaced[:3, :3]))),
        float(np.sqrt(np.mean(np.sum(moved**2, axis=1)))),
    )
    ahead = np.array([0.0, 0.0, 2.5, 1.0])
    places = []
    for i, j in _shared_pairs(data, world, limit):
        estimate = invert_pose(cams[0][i]) @ cams[1][j]
        expected = invert_pose(true_cams[0][i]) @ true_cams[1][j]
        rotation, _ = pose_difference(estimate, expected)
        position = np.linalg.norm((estimate - expected) @ ahead)
        places.append((float(np.rad2deg(rotation)), float(position)))
    return maps, places


def memoise_features() -> None:
    """Extract each session's keyframe features once for all natural-feature methods.

    `postproc.merge.natural.session_features` depends only on the images and the
    options; everything after it (vocabulary, recognition, verification, the joint
    estimate) runs per method.
    """
    import postproc.merge.natural as natural

    original = natural.session_features
    memo: dict[tuple[str, str], object] = {}

    def features_once(options: object, session: object) -> object:
        # By the images (redrawn SLAM errors link the rendered keyframes).
        folder = SlamFolder(session.folder)  # type: ignore[attr-defined]
        key = (str(folder.keyframes.resolve()), repr(options))
        if key not in memo:
            memo[key] = original(options, session)  # type: ignore[arg-type]
        return memo[key]

    natural.session_features = features_once  # type: ignore[assignment]


def first_sighting_floor(
    root: Path, truth: SurveyTruth, reference: str, session: str
) -> tuple[FloatArray, float]:
    """`T_S1_Sk` an oracle gets from targets known exactly at each session's first sighting.

    The SLAM's drift between the session anchor and the first keyframe that sees a
    target (non-outlier) reaches every later keyframe too, and nothing observed
    afterwards tells it apart from the session frame: a target method's error in
    the session frame is at least this on average (a realised value, not a bound
    per seed). Also returns the expected rotation error (deg RMS) for the scene's
    yaw random walk: `rate sqrt(t1 + tk)`, times from each session's anchor.
    """
    drifts = {}
    times: list[float] = []
    for name in (reference, session):
        d = np.load(root / f"truth_{name}.npz")
        seen = np.zeros(len(d["stamps_ns"]), dtype=bool)
        for target in truth.world_from_target:
            seen |= d[f"seen_{target}"]
        first = int(np.flatnonzero(seen & ~d["outlier"])[0])
        drifts[name] = d["session_from_cam_drift"][first] @ np.linalg.inv(
            d["session_from_cam_true"][first]
        )
        anchor = int(SlamFolder(root / name).read_trajectory().stamps_ns[0])
        times.append(seconds_from_ns(int(d["stamps_ns"][first]) - anchor))
    expected = invert_pose(truth.world_from_session[reference]) @ truth.world_from_session[session]
    result: FloatArray = drifts[reference] @ expected @ invert_pose(drifts[session])
    return result, DRIFT_RATE_DEG * float(np.sqrt(sum(times)))


def _render(
    args: argparse.Namespace, seed: int, tmp: Path
) -> tuple[Path, list[Path], list[Path], SurveyTruth]:
    """The seed's folders: from `--cache` when rendered before with the same settings."""
    key = f"{args.scene}_seed{seed}_s{args.sessions}_o{args.outliers:g}"
    if args.scene == "fieldsim":
        key += f"_d{args.duration:g}" + ("_tilt" if args.tilt_drift else "")
        key += "_all" if args.every_keyframe else ""
        if (args.jitter_deg, args.jitter_cm / 100.0) != JITTER:
            key += f"_j{args.jitter_deg:g}_{args.jitter_cm:g}"
    root = (Path(args.cache) if args.cache else tmp) / key
    done = root / "bench_truth.pkl"
    if done.is_file():
        with done.open("rb") as f:
            folders, targets, truth = pickle.load(f)
        return root, folders, targets, truth
    if root.exists():
        shutil.rmtree(root)
    if args.scene == "synthetic":
        folders, targets, truth = make_survey(
            root, SurveyOptions(sessions=args.sessions, outlier_fraction=args.outliers), seed=seed
        )
    else:
        folders, targets, truth = make_fieldsim_survey(
            root,
            seed,
            args.sessions,
            args.duration,
            args.outliers,
            yaw_drift_only=not args.tilt_drift,
            every_keyframe=args.every_keyframe,
            jitter=(args.jitter_deg, args.jitter_cm / 100.0),
        )
    with done.open("wb") as f:
        pickle.dump((folders, targets, truth), f)
    return root, folders, targets, truth


def _sfm_errors(
    name: str,
    root: Path,
    truth: SurveyTruth,
    folders: list[Path],
    merge: Path,
    document: dict[str, Any],
    maps: dict[tuple[str, str], list[tuple[float, float]]],
    places: dict[tuple[str, str], list[tuple[float, float]]],
    times: list[float],
) -> str:
    """Run the SfM stage on `merge` (its transforms.json: `document`); add the overlay
    errors before and after it."""
    from postproc.sfm.stage import SfmOptions
    from postproc.sfm.stage import run as run_sfm
    from shared.folders import MergeFolder, SfmFolder

    sessions = [Path(f).name for f in folders]
    if not all(document["sessions"][s]["placed"] for s in sessions):
        return " (not all placed: no SfM)"
    out = merge.with_name(merge.name + "_sfm")
    start = time.perf_counter()
    run_sfm(SfmOptions(), folders, out, merge=merge, overwrite=True)
    times.append(time.perf_counter() - start)
    poses = {
        "before": {s: MergeFolder(merge).read_merged_keyframes(s) for s in sessions},
        "after": {s: SfmFolder(out).read_session_keyframes_world(s) for s in sessions},
    }
    text = ""
    for when, world_from_cam in poses.items():
        for other in sessions[1:]:
            whole, shared = overlay_errors(root, truth, sessions[0], other, world_from_cam)
            maps.setdefault((name, when), []).append(whole)
            places.setdefault((name, when), []).extend(shared)
        text += f" maps {when} SfM {whole[0]:.3f} deg {100 * whole[1]:.1f} cm,"
    return f" ({text.strip(' ,')}, SfM {times[-1]:.0f} s)"


def print_sfm_table(
    names: list[str],
    maps: dict[tuple[str, str], list[tuple[float, float]]],
    places: dict[tuple[str, str], list[tuple[float, float]]],
    times: dict[str, list[float]],
) -> None:
    """The `--sfm` table: the maps laid over each other, before and after SfM."""
    print()
    print(
        "maps laid over each other, merged keyframes -> after SfM (RMS over seeds x sessions; "
        "maps: session k's map as a whole against session 1's, rotation and RMS distance "
        "over its keyframes; places: relative pose at keyframe pairs filming the same "
        "structure, rotation and the point 2.5 m ahead)"
    )
    print(
        f"{'method':<28} {'maps deg':>15} {'maps cm':>13} {'places deg':>15} "
        f"{'places cm':>13} {'pairs':>6} {'SfM s':>6}"
    )
    for name in names:
        if (name, "after") not in maps:
            print(f"{name:<28} (no run placed every session)")
            continue
        cells = []
        for table in (maps, places):
            before = np.sqrt(np.mean(np.square(table[(name, "before")]), axis=0))
            after = np.sqrt(np.mean(np.square(table[(name, "after")]), axis=0))
            cells += [
                f"{before[0]:.3f} -> {after[0]:.3f}",
                f"{100 * before[1]:.2f} -> {100 * after[1]:.2f}",
            ]
        print(
            f"{name:<28} {cells[0]:>15} {cells[1]:>13} {cells[2]:>15} {cells[3]:>13} "
            f"{len(places[(name, 'after')]):>6} {np.mean(times[name]):>6.1f}"
        )


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def memoise_detections() -> None:
    """Detect each keyframe once for all methods (they share the detector and its settings).

    The stage calls `shared.calibration.aprilgrid_detection.detect_tags` per keyframe image; the
    result depends only on the pixels and the options, so it is kept by a digest
    of both. Everything after detection (PnP, averaging, alignment) runs per method.
    """
    import hashlib

    import shared.calibration.aprilgrid_detection as detect

    original = detect.detect_tags
    memo: dict[bytes, object] = {}

    def detect_once(image: npt.NDArray[np.uint8], options: DetectionOptions) -> object:
        key = hashlib.sha1(image.tobytes() + repr(options).encode()).digest()
        if key not in memo:
            memo[key] = original(image, options)
        return memo[key]

    detect.detect_tags = detect_once  # type: ignore[assignment]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--sessions", type=int, default=2)
    parser.add_argument("--outliers", type=float, default=0.1, help="outlier keyframe share")
    parser.add_argument("--no-photos", action="store_true")
    parser.add_argument(
        "--scene",
        choices=("synthetic", "fieldsim"),
        default="synthetic",
        help="synthetic: sim.targets surveys; fieldsim: sim's wreck and routes",
    )
    parser.add_argument("--duration", type=float, default=240.0, help="fieldsim: s per dive")
    parser.add_argument(
        "--tilt-drift",
        action="store_true",
        help="fieldsim: let roll and pitch drift too (default: yaw only, as VI-SLAM)",
    )
    parser.add_argument(
        "--every-keyframe",
        action="store_true",
        help="fieldsim: keyframes at 1 Hz along the whole dive (not only near the targets)",
    )
    parser.add_argument(
        "--jitter-deg",
        type=float,
        default=JITTER[0],
        help="fieldsim: each keyframe's own SLAM rotation error besides the drift (deg, 1 sigma "
        "per axis)",
    )
    parser.add_argument(
        "--jitter-cm",
        type=float,
        default=100.0 * JITTER[1],
        help="fieldsim: and its translation error (cm, 1 sigma per axis)",
    )
    parser.add_argument(
        "--draws",
        type=int,
        default=1,
        help="fieldsim with --every-keyframe: per seed, this many draws of the SLAM errors "
        "on the same rendered images (the first is the render's own); every row is pooled "
        "over seeds x draws",
    )
    parser.add_argument(
        "--render-only", action="store_true", help="render (and cache) the seeds, then stop"
    )
    parser.add_argument(
        "--features",
        action="store_true",
        help="fieldsim: also the natural-feature rows (no targets; targets + features)",
    )
    parser.add_argument(
        "--cache", help="keep the rendered folders here and reuse them (same seed and settings)"
    )
    parser.add_argument(
        "--sfm",
        action="store_true",
        help="fieldsim: also run the SfM stage on the merges of SFM_METHODS; maps laid over "
        "each other before and after it",
    )
    args = parser.parse_args()
    if args.draws < 1:
        parser.error("--draws must be at least 1")
    if args.draws > 1 and not (args.scene == "fieldsim" and args.every_keyframe):
        parser.error("--draws needs --scene fieldsim --every-keyframe")
    if args.sfm and args.scene != "fieldsim":
        parser.error("--sfm needs --scene fieldsim (the wreck's per-keyframe truth)")
    if args.sfm:
        import pycolmap

        pycolmap.logging.minloglevel = 2  # errors only: the tables are the output
    if not args.no_photos:
        bench_photos()
    memoise_detections()
    memoise_features()
    methods = list(METHODS) + (list(FEATURE_METHODS) if args.features else [])

    names = [name for name, _ in methods]
    shared: dict[str, list[tuple[float, float]]] = {n: [] for n in [*names, "ideal rigid"]}
    frame: dict[str, list[tuple[float, float, float]]] = {n: [] for n in [*names, FLOOR]}
    local: dict[str, list[tuple[float, float]]] = {n: [] for n in [*names, "ideal rigid"]}
    times: dict[str, list[float]] = {n: [] for n in names}
    sigmas: dict[str, list[tuple[float, float]]] = {n: [] for n in [*names, FLOOR]}
    # --sfm: (method, "before"/"after") -> the maps' and the shared places' errors.
    sfm_names = [n for n in names if args.sfm and n in SFM_METHODS]
    maps: dict[tuple[str, str], list[tuple[float, float]]] = {}
    places: dict[tuple[str, str], list[tuple[float, float]]] = {}
    sfm_times: dict[str, list[float]] = {n: [] for n in sfm_names}
    with tempfile.TemporaryDirectory(prefix="bench_merge_") as tmp:
        for seed, draw in itertools.product(
            range(args.first_seed, args.first_seed + args.seeds), range(args.draws)
        ):
            if args.render_only and draw:
                continue  # the draws share the seed's render
            start = time.perf_counter()
            root, folders, targets, truth = _render(args, seed, Path(tmp))
            if draw:
                root, folders, targets, truth = redraw_fieldsim(
                    root,
                    Path(tmp) / f"seed{seed}_draw{draw}",
                    seed,
                    draw,
                    yaw_drift_only=not args.tilt_drift,
                    jitter=(args.jitter_deg, args.jitter_cm / 100.0),
                    outliers=args.outliers,
                )
            render_s = time.perf_counter() - start
            if args.render_only:
                print(f"seed {seed}: rendered in {render_s:.0f} s ({root})", flush=True)
                continue
            keyframes = sum(len(list(SlamFolder(f).keyframes.iterdir())) for f in folders)
            label = f"seed {seed}" + (f" draw {draw}" if args.draws > 1 else "")
            line = f"{label}: {keyframes} keyframes ready in {render_s:.0f} s;"
            at_targets = args.scene == "fieldsim"
            references = (
                {
                    k: at_target_references(root, truth, "dive1", f"dive{k}")
                    for k in range(2, args.sessions + 1)
                }
                if at_targets
                else {}
            )
            structure = (
                {
                    k: shared_structure_references(root, truth, "dive1", f"dive{k}")
                    for k in range(2, args.sessions + 1)
                }
                if at_targets
                else {}
            )
            for k in range(2, args.sessions + 1) if at_targets else ():
                expected = (
                    invert_pose(truth.world_from_session["dive1"])
                    @ truth.world_from_session[f"dive{k}"]
                )
                oracle, expected_deg = first_sighting_floor(root, truth, "dive1", f"dive{k}")
                rot, trans = pose_difference(oracle, expected)
                frame[FLOOR].append((float(np.rad2deg(rot)), trans, float("nan")))
                # The drift model's expected rotation error in the "reported" column.
                sigmas[FLOOR].append((expected_deg, float("nan")))
            for refs in references.values():
                # The rigid transform closest to every T*_m at its target: the mean
                # rotation, and the translation that zeroes the mean position error.
                rotation = rotation_mean_chordal(
                    np.array([r[0][:3, :3] for r in refs]), np.ones(len(refs))
                )
                shift = np.mean([w[:3, :3] @ c + w[:3, 3] - rotation @ c for w, c in refs], axis=0)
                fitted = make_pose(rotation, shift)
                local["ideal rigid"].extend(at_target_error(fitted, refs))
            for refs in structure.values():
                if not refs:
                    continue
                rotation = rotation_mean_chordal(
                    np.array([r[0][:3, :3] for r in refs]), np.ones(len(refs))
                )
                shift = np.mean([w[:3, :3] @ c + w[:3, 3] - rotation @ c for w, c in refs], axis=0)
                shared["ideal rigid"].extend(at_target_error(make_pose(rotation, shift), refs))
            for name, options in methods:
                start = time.perf_counter()
                out = (
                    Path(tmp)
                    / f"seed{seed}_{draw}"
                    / name.replace(" ", "_").replace(",", "").replace("(", "").replace(")", "")
                )
                given = [] if name == NO_TARGETS else targets
                document = json.loads(run(options, folders, given, out).read_text())
                times[name].append(time.perf_counter() - start)
                reference = truth.world_from_session["dive1"]
                for k in range(2, args.sessions + 1):
                    entry = document["sessions"][f"dive{k}"]
                    if not entry["placed"]:
                        frame[name].append((np.inf, np.inf, np.inf))
                        continue
                    expected = invert_pose(reference) @ truth.world_from_session[f"dive{k}"]
                    estimate = np.array(entry["T_W_S"])
                    rot, trans = pose_difference(estimate, expected)
                    # The session's keyframes (its map) moved into W.
                    points = SlamFolder(folders[k - 1]).read_keyframes().positions
                    moved = points @ (estimate[:3, :3] - expected[:3, :3]).T
                    moved += estimate[:3, 3] - expected[:3, 3]
                    map_error = float(np.sqrt(np.mean(np.sum(moved**2, axis=1))))
                    frame[name].append((float(np.rad2deg(rot)), trans, map_error))
                    sigmas[name].append((entry["sigma_rotation_deg"], entry["sigma_translation_m"]))
                    if at_targets:
                        local[name].extend(at_target_error(estimate, references[k]))
                        shared[name].extend(at_target_error(estimate, structure[k]))
                rot_e, trans_e, _ = frame[name][-1]
                line += f" {name}: {rot_e:.3f} deg {100 * trans_e:.1f} cm"
                if name in sfm_names:
                    line += _sfm_errors(
                        name,
                        root,
                        truth,
                        folders,
                        out,
                        document,
                        maps,
                        places,
                        sfm_times[name],
                    )
                if at_targets:
                    here = np.array(local[name][-len(references[args.sessions]) :])
                    rot_t, pos_t = _rms(list(here[:, 0])), 100 * _rms(list(here[:, 1]))
                    line += f" (at targets {rot_t:.3f} deg {pos_t:.1f} cm)"
                line += ";"
            print(line, flush=True)
    if args.render_only:
        return 0

    count = args.seeds * args.draws * (args.sessions - 1)
    print()
    draws = f" x {args.draws} draws" if args.draws > 1 else ""
    print(
        f"session frame T_S1_Sk against the truth, RMS over {args.seeds} seeds{draws} x "
        f"{args.sessions - 1} session(s)"
    )
    print("(trans: at the session origin; map: RMS over the session's keyframe positions)")
    print(
        f"{'method':<28} {'rot RMS deg':>12} {'rot max deg':>12} {'trans RMS cm':>13} "
        f"{'map RMS cm':>11} {'reported 1-sigma (deg, cm)':>28} {'run s':>6}"
    )
    rms = {}
    for name in [*names, FLOOR]:
        if not frame[name]:
            continue
        e = np.array(frame[name])
        rms[name] = np.sqrt(np.mean(e**2, axis=0))
        s = np.array(sigmas[name]) if sigmas.get(name) else np.full((1, 2), np.nan)
        print(
            f"{name:<28} {rms[name][0]:>12.3f} {e[:, 0].max():>12.3f} "
            f"{100 * rms[name][1]:>13.2f} {100 * rms[name][2]:>11.2f} "
            f"{np.mean(s[:, 0]):>14.3f}, {100 * np.mean(s[:, 1]):>11.2f} "
            f"{np.mean(times.get(name, [np.nan])):>6.1f}"
        )
    paper = rms[names[0]]
    for name in names[1:]:
        print(
            f"  paper / {name}: rotation {paper[0] / rms[name][0]:.1f}x, "
            f"translation {paper[1] / rms[name][1]:.1f}x, map {paper[2] / rms[name][2]:.1f}x "
            "(target: >= 2x)"
        )
    if sigmas[FLOOR]:
        model_rms = float(np.sqrt(np.mean(np.array(sigmas[FLOOR])[:, 0] ** 2)))
        print(f"  {FLOOR}: expected rotation RMS {model_rms:.3f} deg (the drift model)")
    if FLOOR in rms:
        print(
            f"  paper / {FLOOR}: rotation {paper[0] / rms[FLOOR][0]:.1f}x, translation "
            f"{paper[1] / rms[FLOOR][1]:.1f}x (the most any target method can reach on average)"
        )
    if any(local.values()):
        print()
        print(
            f"at the targets: T_S1_Sk against T*_m per shared target, RMS over {count} "
            "session(s) x targets"
        )
        print(f"{'method':<28} {'rot RMS deg':>12} {'pos RMS cm':>11}")
        lrms = {}
        for name in [*names, "ideal rigid"]:
            e = np.array(local[name])
            lrms[name] = np.sqrt(np.mean(e**2, axis=0))
            print(f"{name:<28} {lrms[name][0]:>12.3f} {100 * lrms[name][1]:>11.2f}")
        for name in names[1:]:
            print(
                f"  paper / {name}: rotation {lrms[names[0]][0] / lrms[name][0]:.1f}x, "
                f"position {lrms[names[0]][1] / lrms[name][1]:.1f}x"
            )
    if sfm_names:
        print_sfm_table(sfm_names, maps, places, sfm_times)
    if any(shared.values()):
        print()
        print(
            "where the maps share structure: T_S1_Sk against T* per keyframe pair filming "
            "the same place (position error 2.5 m ahead of session k's camera), RMS"
        )
        print(f"{'method':<28} {'rot RMS deg':>12} {'pos RMS cm':>11} {'pairs':>6}")
        for name in [*names, "ideal rigid"]:
            if not shared[name]:
                continue
            e = np.array(shared[name])
            srms = np.sqrt(np.mean(e**2, axis=0))
            print(f"{name:<28} {srms[0]:>12.3f} {100 * srms[1]:>11.2f} {len(e):>6}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
