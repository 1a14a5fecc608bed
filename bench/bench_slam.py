"""Accuracy and speed of `wreckmap-post slam` on simulated diver surveys.

Usage:
    .venv/bin/python bench/bench_slam.py [--work DIR] [--duration 60] [--sessions 2]
                                         [--width 640] [--seed 1]
                                         [--render-width 960 --render-height 540 --fps 30]
    .venv/bin/python bench/bench_slam.py --long [--long-minutes 45] [--window 300]

`--long`: a 45-minute feature-level dive (the diver sweeps the 40 m wreck side
back and forth, so features never run out); prints the process RSS and the
backend time per keyframe (wall and CPU) at the start, middle and end, to show
that the sliding-window smoother keeps both flat, then the ATE.

1. Feature-level sequences (postproc.slam.synthetic: exact tracks with pixel
   noise, simulated IMU): the backend alone, no images.
2. Rendered surveys (field.sim, the same simulator `wreckmap-field sim survey`
   runs; rendered once into --work and reused): the whole stage, images to
   trajectory, as the CLI runs it.

Printed per sequence: path length, ATE RMSE after SE(3) alignment (metres and
% of the distance travelled; target <= 1 %, goal 0.5 %), the Sim(3) scale,
keyframes, loop closures and the real-time factor (sequence time / run time).
The visual-only baseline (IMU off) is aligned with Sim(3) (its scale is arbitrary);
the VIO rows use SE(3), as the target asks.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from field.sim.survey import SurveyOptions
from field.sim.survey import run as render_survey
from postproc.slam.backend import BackendOptions
from postproc.slam.estimator import EstimatorOptions, SlamEstimator
from postproc.slam.frontend import FrontendOptions
from postproc.slam.stage import SlamOptions
from postproc.slam.stage import run as run_slam
from postproc.slam.synthetic import DiverMotion, Sinusoids, SyntheticOptions, simulate_sequence
from postproc.slam.visual_only import VisualOnlyEstimator
from shared.errors import StageError
from shared.formats.euroc import read_euroc
from shared.formats.tum import read_tum
from shared.trajectory import Trajectory, ate


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
            minute = (frame.stamp_ns - seq.frames[0].stamp_ns) * 1e-9 / 60
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
    print(f"-- rendered survey (field.sim), frontend width {width} px, {os.cpu_count()} CPUs")
    for folder in sorted(survey.glob("session_*")):
        euroc = folder / "euroc"
        data = read_euroc(euroc)
        assert data.groundtruth is not None and data.camera is not None
        shift_ns = round(data.camera.timeshift_cam_imu_s * 1e9)
        for use_imu in (True, False):
            out = work / f"slam_{survey.name}_{folder.name}_w{width}_{'vio' if use_imu else 'vo'}"
            options = SlamOptions(frontend=FrontendOptions(width_px=width), use_imu=use_imu)
            try:
                run_slam(options, euroc, out, overwrite=True)
            except StageError as error:
                print(f"{folder.name} {'VIO' if use_imu else 'visual-only'}: FAILED ({error})")
                continue
            stats = json.loads((out / "stats.json").read_text())
            estimate = read_tum(out / "trajectory.tum")
            # Ground truth is on the IMU clock; the trajectory on the camera clock.
            estimate = Trajectory(estimate.stamps_ns + shift_ns, estimate.poses)
            align = "se3" if use_imu else "sim3"
            error = ate(estimate, data.groundtruth, align=align, max_dt_ns=3_000_000)
            sim3 = ate(estimate, data.groundtruth, align="sim3", max_dt_ns=3_000_000)
            truth = data.groundtruth.slice_time(
                int(estimate.stamps_ns[0]), int(estimate.stamps_ns[-1])
            )
            name = folder.name if use_imu else f"{folder.name} visual-only (Sim3)"
            print(
                _row(
                    name,
                    truth.path_length_m(),
                    error.rmse_m,
                    sim3.scale,
                    stats["keyframes"],
                    stats["loop_closures"],
                    stats["real_time_factor"],
                )
            )
            print(
                f"{'':<28} max error {np.max(error.errors_m) * 1000:.1f} mm, "
                f"tracking failures {stats.get('tracking_failures')}, init {stats.get('init')}, "
                f"RTF per CPU second {stats.get('real_time_factor_cpu', float('nan')):.2f} "
                f"(load average {stats.get('load_average_1min')})"
            )


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
    parser.add_argument("--long-minutes", type=float, default=45.0)
    parser.add_argument("--window", type=int, default=300, help="smoother window, keyframes")
    args = parser.parse_args()
    os.environ.setdefault("WRECKMAP_PROGRESS", "0")
    if args.long:
        long_dive(args.long_minutes, args.window)
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
