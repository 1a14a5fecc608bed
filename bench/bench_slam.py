"""Accuracy and speed of `wreckmap-post slam` on simulated diver surveys.

Usage:
    .venv/bin/python bench/bench_slam.py [--work DIR] [--duration 60] [--sessions 2]
                                         [--width 640] [--seed 1]
                                         [--render-width 960 --render-height 540 --fps 30]
    .venv/bin/python bench/bench_slam.py --long [--long-minutes 45] [--window 300]
    .venv/bin/python bench/bench_slam.py --real [--only handheld_a karma ...] [--width PX]
    .venv/bin/python bench/bench_slam.py --speed [--duration 40] [--seed 1] [--width PX]
                                         [--speed-inputs euroc h264]
                                         [--estimator-process auto|on|off]

`--speed`: the stage at its defaults on one rendered 960x540, 30 fps session, from its
EuRoC copy (PNG) and from its MP4 imported as a session folder (H.264); prints the
real-time factor per wall second and per CPU second (load average beside it), the ATE
and the CPU seconds of each of the stage's threads (decode, frontend, estimator; with
the estimator in a second process also its start and the thread that takes its answers,
"estimator-link"). `--estimator-process` sets `SlamOptions.estimator_process`.

`--long`: a 45-minute feature-level dive (the diver sweeps the 40 m wreck side
back and forth, so features never run out); prints the process RSS and the
backend time per keyframe (wall and CPU) at the start, middle and end, to show
that the sliding-window smoother keeps both flat, then the ATE.

1. Feature-level sequences (sim.features: exact tracks with pixel
   noise, simulated IMU): the backend alone, no images.
2. Rendered surveys (sim, the same simulator `wreckmap-field sim survey`
   runs; rendered once into --work and reused): the whole stage, images to
   trajectory, as the CLI runs it.

`--real`: every real recording of ../shared/data (handheld_a, euroc_mh01_cam0
through the visual-only path, both GoPro clips, imported first) through the
slam stage's `run` with its default options. No truth for most, so it prints
consistency: images tracked (frames in trajectory.tum / images), keyframes,
tracking failures (frames below `min_tracks_ok` tracks) and whatever else
stats.json says about lost tracking, the real-time factor (wall clock and per
CPU second), the fastest keyframe-to-keyframe speed, and the Sim(3) ATE of
our keyframe camera centres against an independent COLMAP reconstruction of
the same keyframe images (pycolmap: intrinsics fixed to the SLAM's
calibration, SIFT, sequential matching, incremental mapper, largest model),
as a percentage of our keyframe path. For karma, also against the drone's own
position log in the file (GPMF LNED, local NED from its GPS/IMU filter), with
the scale factor our path needs. For euroc_mh01_cam0 also the Sim(3) ATE
of the visual-only body path against the Leica prism positions (the 15 cm
prism lever arm is not removed: the path's scale is arbitrary). A recording
that fails is a row with its error.

Printed per sequence: path length, ATE RMSE after SE(3) alignment (metres and
% of the distance travelled; target <= 1 %, goal 0.5 %), the Sim(3) scale,
keyframes, loop closures and the real-time factor (sequence time / run time).
The visual-only baseline (IMU off) is aligned with Sim(3) (its scale is arbitrary);
the VIO rows use SE(3), as the target asks.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from postproc.slam.backend import BackendOptions
from postproc.slam.estimator import EstimatorOptions, SlamEstimator
from postproc.slam.frontend import FrontendOptions
from postproc.slam.stage import SlamOptions
from postproc.slam.stage import run as run_slam
from postproc.slam.types import FloatArray
from postproc.slam.visual_only import VisualOnlyEstimator
from shared.clock import NS_PER_S, ns_from_seconds, seconds_from_ns
from shared.errors import StageError
from shared.folders import SessionFolder, SlamFolder
from shared.formats.euroc import read_euroc
from shared.formats.recordings import open_recording
from shared.trajectory import Trajectory, ate
from sim.features import DiverMotion, Sinusoids, SyntheticOptions, simulate_sequence
from sim.survey import SurveyOptions
from sim.survey import run as render_survey


def _row(
    name: str, path_m: float, se3: float, scale: float, kfs: int, loops: int, rtf: float
) -> str:
    pct = 100.0 * se3 / path_m if path_m > 0 else float("nan")
    return (
        f"{name:<28} {path_m:7.2f} m  ATE {se3 * 1000:7.1f} mm  {pct:6.3f} %  "
        f"scale {scale:.4f}  kf {kfs:4d}  loops {loops:2d}  RTF {rtf:5.2f}"
    )


def feature_level(duration_s: float, seeds: list[int]) -> None:
    print(f"-- feature-level synthetic ({duration_s:.0f} s, 30 Hz tracks, 200 Hz IMU)")
    for seed in seeds:
        seq = simulate_sequence(SyntheticOptions(duration_s=duration_s, seed=seed))
        started = time.monotonic()
        estimator = SlamEstimator(
            EstimatorOptions(),
            focal_px=seq.camera.fx,
            imu_from_cam=seq.imu_from_cam,
            imu=seq.imu,
            imu_noise=seq.imu_noise(),
        )
        for frame in seq.frames:
            estimator.process(frame)
        result = estimator.finish()
        run_s = time.monotonic() - started
        truth = Trajectory(seq.frame_stamps_ns, seq.world_from_body)
        estimate = Trajectory(result.frame_stamps_ns, result.session_from_body)
        se3 = ate(estimate, truth, align="se3")
        sim3 = ate(estimate, truth, align="sim3")
        print(
            _row(
                f"seed {seed}",
                truth.path_length_m(),
                se3.rmse_m,
                sim3.scale,
                int(result.stats["keyframes"]),  # type: ignore[arg-type]
                int(result.stats["loop_closures"]),  # type: ignore[arg-type]
                duration_s / run_s,
            )
        )
        started = time.monotonic()
        visual = VisualOnlyEstimator(
            EstimatorOptions(), focal_px=seq.camera.fx, imu_from_cam=seq.imu_from_cam
        )
        try:
            for frame in seq.frames:
                visual.process(frame)
            vo = visual.finish()
        except StageError as error:
            print(f"seed {seed} visual-only: FAILED ({error})")
            continue
        run_s = time.monotonic() - started
        vo_sim3 = ate(Trajectory(vo.frame_stamps_ns, vo.session_from_body), truth, align="sim3")
        print(
            _row(
                f"seed {seed} visual-only (Sim3)",
                truth.path_length_m(),
                vo_sim3.rmse_m,
                vo_sim3.scale,
                int(vo.stats["keyframes"]),  # type: ignore[arg-type]
                0,
                duration_s / run_s,
            )
        )


def _rss_mb() -> float:
    """Current resident set size of this process (MB; Linux /proc, else NaN)."""
    try:
        fields = Path("/proc/self/statm").read_text().split()
    except OSError:
        return float("nan")
    return int(fields[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def long_dive(minutes: float, window: int) -> None:
    """Memory and per-keyframe time over a long feature-level dive."""
    duration_s = minutes * 60.0
    # Sweep the 40 m wall back and forth (period 4 min, peak 0.37 m/s) so the
    # wall stays in view for the whole dive, as a survey of one wreck does.
    motion = DiverMotion(
        x=Sinusoids(
            offset=0.0,
            amplitudes=(14.0, 0.5),
            frequencies_rad_s=(2 * np.pi / 240.0, 0.27),
            phases_rad=(0.0, 0.0),
        )
    )
    started = time.monotonic()
    seq = simulate_sequence(SyntheticOptions(duration_s=duration_s, seed=0), motion=motion)
    print(
        f"-- long feature-level dive: {minutes:.0f} min, {len(seq.frames)} frames "
        f"(simulated in {time.monotonic() - started:.0f} s), window {window} keyframes"
    )
    rss_before = _rss_mb()
    estimator = SlamEstimator(
        EstimatorOptions(backend=BackendOptions(window_keyframes=window)),
        focal_px=seq.camera.fx,
        imu_from_cam=seq.imu_from_cam,
        imu=seq.imu,
        imu_noise=seq.imu_noise(),
    )
    report_at = {round(len(seq.frames) * f) - 1 for f in (0.1, 0.5, 1.0)}
    wall = cpu = 0.0
    kf_since = 0
    run_wall0, run_cpu0 = time.monotonic(), time.process_time()
    print(f"RSS with the simulated data in memory: {rss_before:.0f} MB")
    for n, frame in enumerate(seq.frames):
        w0, c0 = time.monotonic(), time.process_time()
        decision = estimator.process(frame)
        if decision.is_keyframe:
            wall += time.monotonic() - w0
            cpu += time.process_time() - c0
            kf_since += 1
        if n in report_at:
            minute = seconds_from_ns(frame.stamp_ns - seq.frames[0].stamp_ns) / 60
            print(
                f"minute {minute:5.1f}: keyframes {estimator.backend.num_keyframes:5d} "
                f"(in window {estimator.backend.active_keyframes:4d}), RSS {_rss_mb():7.0f} MB "
                f"(+{_rss_mb() - rss_before:.0f}), per keyframe "
                f"{1000 * wall / max(kf_since, 1):6.1f} ms "
                f"wall / {1000 * cpu / max(kf_since, 1):6.1f} ms CPU (last interval, incl. "
                "window rebuilds)"
            )
            wall = cpu = 0.0
            kf_since = 0
    result = estimator.finish()
    run_wall = time.monotonic() - run_wall0
    run_cpu = time.process_time() - run_cpu0
    truth = Trajectory(seq.frame_stamps_ns, seq.world_from_body)
    se3 = ate(Trajectory(result.frame_stamps_ns, result.session_from_body), truth, align="se3")
    stats = estimator.backend.stats
    print(
        f"finished: RSS {_rss_mb():.0f} MB, run {run_wall:.0f} s wall / {run_cpu:.0f} s CPU "
        f"(RTF {duration_s / run_wall:.1f}, backend only), path {truth.path_length_m():.0f} m, "
        f"ATE {se3.rmse_m * 1000:.0f} mm ({100 * se3.rmse_m / truth.path_length_m():.3f} %), "
        f"retired {stats.retired_keyframes}, rebuilds {stats.window_rebuilds}, "
        f"landmarks {result.stats['landmarks']}; load average {os.getloadavg()[0]:.1f}"
    )


def rendered(
    work: Path,
    *,
    duration_s: float,
    sessions: int,
    seed: int,
    width: int,
    render_size: tuple[int, int] = (640, 360),
    fps: float = 15.0,
) -> None:
    size = f"{render_size[0]}x{render_size[1]}@{fps:g}"
    suffix = "" if size == "640x360@15" else f"_{size}"
    survey = work / f"survey_{sessions}x{duration_s:.0f}s_seed{seed}{suffix}"
    if not survey.is_dir():
        print(f"-- rendering the survey into {survey} (once)")
        render_survey(
            SurveyOptions(
                sessions=sessions,
                duration_s=duration_s,
                seed=seed,
                video=False,
                workers=2,
                width=render_size[0],
                height=render_size[1],
                fps=fps,
            ),
            survey,
        )
    print(f"-- rendered survey (sim), frontend width {width} px, {os.cpu_count()} CPUs")
    for folder in sorted(survey.glob("session_*")):
        euroc = folder / "euroc"
        data = read_euroc(euroc)
        assert data.groundtruth is not None and data.camera is not None
        shift_ns = ns_from_seconds(data.camera.timeshift_cam_imu_s)
        for use_imu in (True, False):
            out = work / f"slam_{survey.name}_{folder.name}_w{width}_{'vio' if use_imu else 'vo'}"
            options = SlamOptions(frontend=FrontendOptions(width_px=width), use_imu=use_imu)
            try:
                run_slam(options, euroc, out, overwrite=True)
            except StageError as error:
                print(f"{folder.name} {'VIO' if use_imu else 'visual-only'}: FAILED ({error})")
                continue
            stats = SlamFolder(out).read_stats()
            estimate = SlamFolder(out).read_trajectory()
            # Ground truth is on the IMU clock; the trajectory on the camera clock.
            estimate = Trajectory(estimate.stamps_ns + shift_ns, estimate.poses)
            align: Literal["se3", "sim3"] = "se3" if use_imu else "sim3"
            result = ate(estimate, data.groundtruth, align=align, max_dt_ns=3_000_000)
            sim3 = ate(estimate, data.groundtruth, align="sim3", max_dt_ns=3_000_000)
            truth = data.groundtruth.slice_time(
                int(estimate.stamps_ns[0]), int(estimate.stamps_ns[-1])
            )
            name = folder.name if use_imu else f"{folder.name} visual-only (Sim3)"
            print(
                _row(
                    name,
                    truth.path_length_m(),
                    result.rmse_m,
                    sim3.scale,
                    stats["keyframes"],
                    stats["loop_closures"],
                    stats["real_time_factor"],
                )
            )
            print(
                f"{'':<28} max error {np.max(result.errors_m) * 1000:.1f} mm, "
                f"tracking failures {stats.get('tracking_failures')}, init {stats.get('init')}, "
                f"RTF per CPU second {stats.get('real_time_factor_cpu', float('nan')):.2f} "
                f"(load average {stats.get('load_average_1min')})"
            )


def speed(
    work: Path,
    *,
    duration_s: float,
    seed: int,
    inputs: list[str],
    estimator_process: Literal["auto", "on", "off"] | None = None,
    rates: dict[str, float | None] | None = None,
    width: int | None = None,
) -> None:
    """Real-time factor of the stage at its defaults (the frontend at `width` px when
    given) on one rendered 960x540, 30 fps session (the size and rate of issue #23),
    from its EuRoC copy (PNG images) and from its GoPro-like MP4 imported as a session
    folder (H.264): video seconds per wall second and per CPU second of the process
    (every thread), with the load average beside them, the CPU seconds of each thread
    and the ATE."""
    survey = work / f"survey_1x{duration_s:.0f}s_seed{seed}_960x540@30"
    if not survey.is_dir():
        print(f"-- rendering the survey into {survey} (once)")
        render_survey(
            SurveyOptions(
                sessions=1,
                duration_s=duration_s,
                seed=seed,
                video=True,
                workers=2,
                width=960,
                height=540,
                fps=30.0,
            ),
            survey,
        )
    euroc = survey / "session_00" / "euroc"
    data = read_euroc(euroc)
    assert data.groundtruth is not None and data.camera is not None
    shift_ns = ns_from_seconds(data.camera.timeshift_cam_imu_s)
    for kind in inputs:
        if kind == "euroc":
            recording, clock_ns = euroc, 0
        else:
            video = survey / "session_00" / "gopro" / "GX010001.MP4"
            if not video.is_file():
                print(f"-- speed, session (H.264): skipped, {survey} was rendered without video")
                continue
            recording = _import_rendered(video, survey / "calib", work / f"{survey.name}_h264")
            # The import stamps the frames on the GoPro's clock: move them onto the
            # EuRoC copy's (the same images, in the same order).
            clock_ns = _first_frame_ns(euroc) - _first_frame_ns(recording)
        out = work / f"slam_{survey.name}_speed_{kind}"
        options = _with_rates(SlamOptions(), rates)
        if width is not None:
            options.frontend = FrontendOptions(width_px=width)
        if estimator_process is not None:
            options.estimator_process = estimator_process
        run_slam(options, recording, out, overwrite=True)
        stats = SlamFolder(out).read_stats()
        estimate = SlamFolder(out).read_trajectory()
        # Ground truth is on the IMU clock; the trajectory on the camera clock.
        estimate = Trajectory(estimate.stamps_ns + clock_ns + shift_ns, estimate.poses)
        result = ate(estimate, data.groundtruth, align="se3", max_dt_ns=3_000_000)
        label = "EuRoC (PNG)" if kind == "euroc" else "session (H.264)"
        print(
            f"-- speed, {label}: 960x540 @ 30 fps, {stats['sequence_duration_s']:.1f} s of "
            f"video, frontend {stats['frontend_width_px']} px, {os.cpu_count()} CPUs, "
            f"estimator {'apart' if stats.get('estimator_process') else 'in-process'}\n"
            f"   wall {stats['run_time_s']:.1f} s (RTF {stats['real_time_factor']:.2f}), "
            f"CPU {stats['cpu_time_s']:.1f} s (RTF per CPU second "
            f"{stats['real_time_factor_cpu']:.2f}), load average "
            f"{stats['load_average_1min']:.1f}, ATE {result.rmse_m * 1000:.1f} mm, "
            f"keyframes {stats['keyframes']}, final batch "
            f"{stats.get('final_batch_iterations', '-')} iterations"
        )
        threads = stats.get("cpu_time_threads_s") or {}
        if threads:
            print(
                "   CPU per thread: "
                + ", ".join(f"{name} {seconds:.1f} s" for name, seconds in threads.items())
                + f" (all threads {sum(threads.values()):.1f} s)"
            )


def _import_rendered(video: Path, calib: Path, session: Path) -> Path:
    """The rendered MP4 as a session folder (`gopro import` with the render's calibration)."""
    calibration = ["--camchain", str(calib / "camchain.yaml")]
    return _gopro_import(video, session, [*calibration, "--imu-yaml", str(calib / "imu.yaml")])


def _gopro_import(video: Path, session: Path, options: list[str]) -> Path:
    """`wreckmap-field gopro import VIDEO --out SESSION OPTIONS...` unless it is done."""
    if SessionFolder(session).recording.is_file():
        return session
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    command = [sys.executable, "-m", "field.cli", "gopro", "import", str(video)]
    done = subprocess.run(
        [*command, "--out", str(session), *options],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise RuntimeError(f"gopro import failed: {done.stderr.strip().splitlines()[-1:]}")
    return session


def _first_frame_ns(recording: Path) -> int:
    """Stamp (ns) of the first image of a recording."""
    frames = open_recording(recording).frames(grayscale=True)
    try:
        return next(iter(frames)).stamp_ns
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()


# ------------------------------------------------------------------ real recordings

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@dataclass(frozen=True)
class RealRecording:
    """One real recording: what to run slam on and how (`prepare` imports GoPro clips)."""

    name: str
    source: Path
    use_imu: bool = True
    gopro: bool = False
    leica: Path | None = None


def real_recordings(shared: Path) -> list[RealRecording]:
    """Every real recording of ../shared/data that slam can be run on."""
    realvi = shared / "realvi"
    mh01 = realvi / "euroc_mh01_cam0"
    return [
        RealRecording("handheld_a", realvi / "handheld_a"),
        RealRecording(
            "euroc_mh01_cam0",
            mh01,
            use_imu=False,
            leica=mh01 / "groundtruth_leica_prism_position_window.txt",
        ),
        RealRecording("karma", shared / "gopro" / "karma.mp4", gopro=True),
        RealRecording("max-heromode", shared / "gopro" / "max-heromode.mp4", gopro=True),
    ]


def _import_gopro(video: Path, work: Path) -> Path:
    """Import a GoPro clip with the field CLI (both samples were filmed in air)."""
    return _gopro_import(video, work / f"session_{video.stem}", ["--medium", "air"])


def colmap_keyframe_poses(slam_dir: Path, work: Path) -> tuple[list[dict[int, FloatArray]], int]:
    """An independent COLMAP reconstruction of a SLAM result's keyframe images.

    Intrinsics fixed to the SLAM's calibration (calib/camchain.yaml), SIFT on the
    full images, sequential matching (20 neighbours, quadratic overlap), COLMAP's
    incremental mapper. Returns (one stamp_ns -> `T_W_C` dict per model, largest
    first; keyframes given). A sequence COLMAP cannot chain (dim, bare stretches)
    comes back as several models, each in its own frame and scale.
    """
    import shutil

    import pycolmap

    from postproc.sfm.database import KeyframeSet, write_database
    from postproc.sfm.features import FeatureOptions, extract_features
    from postproc.sfm.refine import camera_poses

    slam = SlamFolder(slam_dir)
    camera = slam.read_camchain()[0].camera
    if work.exists():
        shutil.rmtree(work)
    # `work` is a scratch COLMAP project (images/, database.db, sparse/: COLMAP's usual
    # names), not a hand-off folder.
    image_dir = work / "images"
    image_dir.mkdir(parents=True)
    width, height = int(camera.width), int(camera.height)
    names = []
    for path in sorted(slam.keyframes.glob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        # Decoded H.264 frames can keep the coded size (854 -> 864 px wide): the
        # calibrated image is the top-left width x height.
        if image is None or image.shape[0] < height or image.shape[1] < width:
            continue
        cv2.imwrite(str(image_dir / path.name), image[:height, :width])
        names.append(path.name)
    pycolmap.logging.minloglevel = 2  # errors only: the table is the output
    n = len(names)
    keyframes = KeyframeSet(
        names=names,
        sources=[image_dir / name for name in names],
        session=np.zeros(n, dtype=np.int64),
        camera=np.zeros(n, dtype=np.int64),
        stamps_ns=np.array([int(name.removesuffix(".png")) for name in names], dtype=np.int64),
        world_from_cam=np.tile(np.eye(4), (n, 1, 1)),
        placed=np.zeros(n, dtype=bool),
        prior_sigma_m=np.ones(n),
    )
    database = work / "database.db"
    write_database(database, [camera], keyframes, with_priors=False)
    longest = max(width, height)
    features = FeatureOptions(max_num_features=4096, max_image_size_px=longest)
    extract_features(database, image_dir, names, features, longest_side_px=longest)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 20
    pairing.loop_detection = False
    pycolmap.match_sequential(database, pairing_options=pairing, device=pycolmap.Device.cpu)
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.ba_refine_focal_length = False
    pipeline.ba_refine_principal_point = False
    pipeline.ba_refine_extra_params = False
    pipeline.random_seed = 0
    pipeline.extract_colors = False
    # Keyframes half a second apart see small baselines: start from a pair at 4 deg
    # (COLMAP's 16 deg finds no pair on a walk or a slow start), and forward motion.
    pipeline.mapper.init_min_tri_angle = 4.0
    pipeline.mapper.init_max_forward_motion = 1.0
    models = pycolmap.incremental_mapping(database, image_dir, work / "sparse", options=pipeline)
    ranked = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    poses = [
        {int(name.removesuffix(".png")): T for name, T in camera_poses(model).items()}
        for model in ranked
    ]
    return poses, n


def _leica(path: Path) -> Trajectory:
    """Leica prism positions (`t_s x y z`, seconds) as a trajectory with no rotation."""
    stamps: list[int] = []
    positions: list[list[float]] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        t, *xyz = line.split()
        seconds, _, fraction = t.partition(".")
        stamps.append(int(seconds) * NS_PER_S + int((fraction + "000000000")[:9]))
        positions.append([float(v) for v in xyz])
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, 3] = positions
    return Trajectory(np.array(stamps, dtype=np.int64), poses)


def _drone_positions(video: Path, session: Path) -> Trajectory | None:
    """A Karma drone's own position log (GPMF LNED) on the session clock; None when absent."""
    import yaml

    from field.gopro.telemetry import local_positions

    found = local_positions(video)
    if found is None:
        return None
    times_ns, ned_m = found
    document = yaml.safe_load(SessionFolder(session).session_yaml.read_text(encoding="utf-8"))
    start_ns = int(document["chapters"][0]["start_ns"])
    poses = np.tile(np.eye(4), (len(times_ns), 1, 1))
    poses[:, :3, 3] = ned_m
    return Trajectory(start_ns + times_ns, poses)


def _with_rates(options: SlamOptions, rates: dict[str, float | None] | None) -> SlamOptions:
    """`options` with the image rate fields of `rates` (max_rate_hz, min_rate_hz) set."""
    for name, value in (rates or {}).items():
        setattr(options, name, value)
    return options


def _path_m(positions: FloatArray) -> float:
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())


def run_real(
    recording: RealRecording,
    work: Path,
    *,
    width: int | None,
    rates: dict[str, float | None] | None = None,
) -> dict[str, object]:
    """slam (the stage's `run`), then the consistency figures; a failure is a row."""
    from postproc.slam.inputs import open_input

    row: dict[str, object] = {"recording": recording.name}
    try:
        source = _import_gopro(recording.source, work) if recording.gopro else recording.source
        row["images"] = open_input(source).frame_count
        out = work / f"slam_{recording.name}"
        frontend = FrontendOptions() if width is None else FrontendOptions(width_px=width)
        options = _with_rates(SlamOptions(frontend=frontend, use_imu=recording.use_imu), rates)
        started = time.monotonic()
        run_slam(options, source, out, overwrite=True)
        row["run_s"] = time.monotonic() - started
    except Exception as error:  # a bench row, not a crash
        row["error"] = f"{type(error).__name__}: {error}"
        return row
    stats = SlamFolder(out).read_stats()
    row.update(
        frames=stats.get("frames"),
        keyframes=stats.get("keyframes"),
        tracking_failures=stats.get("tracking_failures"),
        rtf=stats.get("real_time_factor"),
        rtf_cpu=stats.get("real_time_factor_cpu"),
        mode=stats.get("mode", "visual-inertial" if recording.use_imu else "visual-only"),
        gyro_check=stats.get("gyro_check"),
    )
    # Whatever else the stage says about losing and regaining track.
    for key in ("tracking_losses", "map_segments", "segments", "reinitialisations"):
        if key in stats:
            row[key] = stats[key]
    keyframes = SlamFolder(out).read_keyframes()
    trajectory = SlamFolder(out).read_trajectory()
    speeds = np.linalg.norm(np.diff(keyframes.positions, axis=0), axis=1) / np.maximum(
        seconds_from_ns(np.diff(keyframes.stamps_ns)), 1e-9
    )
    row["max_keyframe_speed_m_s"] = float(speeds.max()) if len(speeds) else float("nan")
    try:
        models, given = colmap_keyframe_poses(out, work / f"colmap_{recording.name}")
        colmap = models[0] if models else {}
        row["colmap_registered"] = f"{len(colmap)}/{given}"
        row["colmap_models"] = [len(m) for m in models]
        if len(colmap) >= 3:
            stamps = np.array(sorted(colmap), dtype=np.int64)
            theirs = Trajectory(stamps, np.array([colmap[s] for s in stamps]))
            result = ate(theirs, keyframes, align="sim3", max_dt_ns=1000)
            ours = keyframes.positions[np.searchsorted(keyframes.stamps_ns, result.stamps_ns)]
            row["colmap_ate_pct"] = 100.0 * result.rmse_m / _path_m(ours)
            row["colmap_ate_m"] = result.rmse_m
            # COLMAP can break on a few keyframes (a far scene, a slow start): the median
            # says whether the rest agrees.
            row["colmap_median_pct"] = 100.0 * float(np.median(result.errors_m)) / _path_m(ours)
    except Exception as error:  # a bench row, not a crash
        row["colmap_error"] = f"{type(error).__name__}: {error}"
    if recording.gopro:
        drone = _drone_positions(recording.source, source)
        if drone is not None:
            inside = drone.slice_time(int(trajectory.stamps_ns[0]), int(trajectory.stamps_ns[-1]))
            result = ate(trajectory.interpolate(inside.stamps_ns), inside, align="sim3")
            row["drone_ate_m"] = result.rmse_m
            row["drone_ate_pct"] = 100.0 * result.rmse_m / inside.path_length_m()
            row["drone_path_m"] = inside.path_length_m()
            row["drone_scale"] = result.scale
    if recording.leica is not None:
        leica = _leica(recording.leica).slice_time(
            int(trajectory.stamps_ns[0]), int(trajectory.stamps_ns[-1])
        )
        at_leica = trajectory.interpolate(leica.stamps_ns)
        result = ate(at_leica, leica, align="sim3", max_dt_ns=1000)
        row["leica_ate_m"] = result.rmse_m
        row["leica_ate_pct"] = 100.0 * result.rmse_m / leica.path_length_m()
        row["leica_path_m"] = leica.path_length_m()
    return row


def _format_real(row: dict[str, object]) -> str:
    def number(key: str, spec: str) -> str:
        value = row.get(key)
        return format(value, spec) if isinstance(value, (int, float)) else "-"

    if "error" in row:
        return f"{row['recording']:<16} FAILED: {row['error']}"
    frames, images = row.get("frames"), row.get("images")
    coverage = (
        f"{100.0 * frames / images:5.1f} %"
        if isinstance(frames, int) and isinstance(images, int) and images
        else "-"
    )
    mode = str(row.get("mode"))
    metric = not (mode.startswith("visual-only") or "not metres" in mode)
    text = (
        f"{row['recording']:<16} frames {frames}/{images} ({coverage})  kf {row.get('keyframes')}"
        f"  tracking failures {row.get('tracking_failures')}  RTF {number('rtf', '.2f')}"
        f" (per CPU s {number('rtf_cpu', '.2f')})  max kf speed "
        f"{number('max_keyframe_speed_m_s', '.2f')} {'m/s' if metric else 'units/s (not metres)'}"
        f"\n{'':<16} "
        f"COLMAP largest model {row.get('colmap_registered', '-')} keyframes "
        f"(models {row.get('colmap_models', '-')}), its Sim(3) ATE "
        f"{number('colmap_ate_pct', '.2f')} % of the path ({number('colmap_ate_m', '.3f')}; "
        f"median error {number('colmap_median_pct', '.2f')} %)"
    )
    if "colmap_error" in row:
        text += f" COLMAP FAILED: {row['colmap_error']}"
    if "drone_ate_m" in row:
        text += (
            f"\n{'':<16} drone's own position log (LNED) Sim(3) ATE "
            f"{number('drone_ate_m', '.2f')} m = {number('drone_ate_pct', '.2f')} % of "
            f"{number('drone_path_m', '.1f')} m (scale to the log {number('drone_scale', '.3f')})"
        )
    if "leica_ate_m" in row:
        text += (
            f"\n{'':<16} Leica prism Sim(3) ATE {number('leica_ate_m', '.3f')} m = "
            f"{number('leica_ate_pct', '.2f')} % of {number('leica_path_m', '.1f')} m"
        )
    extra = {k: row[k] for k in ("tracking_losses", "map_segments", "segments") if k in row}
    text += f"\n{'':<16} mode: {row.get('mode')}; gyro check {row.get('gyro_check')} {extra or ''}"
    return text


def real(
    work: Path,
    *,
    width: int | None,
    only: list[str] | None,
    rates: dict[str, float | None] | None = None,
) -> None:
    """The consistency table over every real recording (see the module docstring)."""
    print(
        f"-- real recordings (../shared/data), frontend width "
        f"{'stage default' if width is None else f'{width} px'}, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    for recording in real_recordings(SHARED_DATA):
        if only and recording.name not in only:
            continue
        row = run_real(recording, work / "real", width=width, rates=rates)
        print(_format_real(row), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--work", type=Path, default=Path(tempfile.gettempdir()) / "wreckmap_bench_slam"
    )
    parser.add_argument("--duration", type=float, default=60.0, help="seconds per sequence")
    parser.add_argument("--sessions", type=int, default=2, help="rendered sessions")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--width", type=int, default=640, help="frontend width, px")
    parser.add_argument("--skip-rendered", action="store_true")
    parser.add_argument("--render-width", type=int, default=640, help="rendered images, px")
    parser.add_argument("--render-height", type=int, default=360)
    parser.add_argument("--fps", type=float, default=15.0, help="rendered frame rate, Hz")
    parser.add_argument("--long", action="store_true", help="only the long-dive memory run")
    parser.add_argument("--real", action="store_true", help="only the real recordings")
    parser.add_argument(
        "--speed",
        action="store_true",
        help="only the real-time factor on one rendered 960x540, 30 fps session (--duration)",
    )
    parser.add_argument(
        "--speed-inputs",
        nargs="+",
        choices=("euroc", "h264"),
        default=["euroc", "h264"],
        help="with --speed: the EuRoC copy (PNG), the imported MP4 (H.264) or both",
    )
    parser.add_argument(
        "--estimator-process",
        choices=("auto", "on", "off"),
        help="with --speed: SlamOptions.estimator_process (default: the stage's default)",
    )
    parser.add_argument(
        "--max-rate-hz",
        type=float,
        help="with --speed or --real: SlamOptions.max_rate_hz (default: the stage's default)",
    )
    parser.add_argument(
        "--min-rate-hz",
        type=float,
        help="with --speed or --real: SlamOptions.min_rate_hz, 0 for none (every image; "
        "default: the stage's default)",
    )
    parser.add_argument(
        "--only", nargs="*", help="with --real: these recordings (handheld_a, karma, ...)"
    )
    parser.add_argument("--long-minutes", type=float, default=45.0)
    parser.add_argument("--window", type=int, default=300, help="smoother window, keyframes")
    args = parser.parse_args()
    os.environ.setdefault("WRECKMAP_PROGRESS", "0")
    rates: dict[str, float | None] = {}
    if args.max_rate_hz is not None:
        rates["max_rate_hz"] = args.max_rate_hz
    if args.min_rate_hz is not None:
        rates["min_rate_hz"] = args.min_rate_hz or None
    # --speed and --real run the stage's own frontend width unless --width is given.
    given_width = args.width if "--width" in sys.argv else None
    if args.long:
        long_dive(args.long_minutes, args.window)
        return
    if args.speed:
        args.work.mkdir(parents=True, exist_ok=True)
        speed(
            args.work,
            duration_s=args.duration,
            seed=args.seed,
            inputs=args.speed_inputs,
            estimator_process=args.estimator_process,
            rates=rates,
            width=given_width,
        )
        return
    if args.real:
        real(args.work, width=given_width, only=args.only, rates=rates)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    feature_level(args.duration, [0, 1, 2])
    if not args.skip_rendered:
        rendered(
            args.work,
            duration_s=args.duration,
            sessions=args.sessions,
            seed=args.seed,
            width=args.width,
            render_size=(args.render_width, args.render_height),
            fps=args.fps,
        )


if __name__ == "__main__":
    main()
