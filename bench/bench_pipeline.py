"""End-to-end speed of `wreckmap-post run` on a simulated dive, per stage.

    .venv/bin/python bench/bench_pipeline.py                       # 10 min at 960x540
    .venv/bin/python bench/bench_pipeline.py --minutes 1 --width 640 --height 360

Simulates the survey (`--minutes`), runs the whole chain on it (GoPro import, slam,
depth, merge, sfm, dense; in this process), and runs the chain again on a shorter length
(`--minutes * --scale-fraction`) to measure how each stage scales. It prints, per stage:
seconds, seconds per hour of video, the scaling exponent k (time ~ length^k, from the two
lengths) and the time extrapolated to a 45-minute dive. The simulation time is printed
apart (it is not part of the chain).

The shorter length is, by default, the first part of the same dive (`--prefix`, the
default), so both runs see the same wreck, motion and haze, and no second render is
needed. It is cut from the whole dive's imported session (`--prefix-source video`, the
default: its archive up to that time, the H.264 packets copied undecoded), so both runs
decode the same video; `--prefix-source euroc` cuts the EuRoC copy instead (PNG frames,
linked), as this bench did up to stop 43 (PNG decoding costs another amount per image
than H.264, so the SLAM's k then mixed two inputs). Either way that run starts from a
recording, so its import time is 0 and import is scaled linearly (k = 1, marked
"assumed"). `--no-prefix` simulates the second length instead.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

TARGET_MIN = 45.0


def simulate(out: Path, *, minutes: float, args: argparse.Namespace) -> float:
    if (out / "truth.json").is_file():
        return 0.0
    command = [
        sys.executable, "-m", "field.cli", "sim", "survey", "--out", str(out),
        "--sessions", str(args.sessions), "--duration", str(minutes * 60.0),
        "--width", str(args.width), "--height", str(args.height), "--fps", str(args.fps),
        "--seed", "1", "--workers", "2",
    ]  # fmt: skip
    if args.euroc:
        command.append("--no-video")
    if args.video_crf is not None:
        command += ["--video-crf", str(args.video_crf)]
    started = time.monotonic()
    env = {**os.environ, "PYTHONPATH": str(REPO), "WRECKMAP_PROGRESS": "0"}
    subprocess.run(command, check=True, env=env)
    return time.monotonic() - started


def _sessions(sim: Path) -> list[Path]:
    """The session folders of the survey `sim`, in order."""
    return sorted(p for p in sim.glob("session_*") if p.is_dir())


def _new_survey(sim: Path, out: Path) -> Path | None:
    """A fresh `<out>.tmp` with everything of `sim` but its sessions linked (to be filled,
    then renamed to `out`); None when `out` is already complete."""
    import shutil

    if (out / "truth.json").exists():
        return None
    tmp = out.with_name(out.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    for item in sim.iterdir():
        if not item.name.startswith("session_"):
            (tmp / item.name).symlink_to(item.resolve())
    return tmp


def make_prefix(sim: Path, out: Path, *, minutes: float) -> None:
    """The first `minutes` of every session of `sim` as a survey folder at `out`.

    EuRoC CSVs are cut at the first camera stamp + `minutes`; images are linked; the
    GoPro file is left out (the prefix runs from EuRoC); everything else is linked.
    """
    tmp = _new_survey(sim, out)
    if tmp is None:
        return
    for item in _sessions(sim):
        session = tmp / item.name
        session.mkdir()
        for part in item.iterdir():
            if part.name == "gopro":
                continue
            if part.name != "euroc":
                (session / part.name).symlink_to(part.resolve())
                continue
            mav = part / "mav0"
            first_ns = int(_csv_rows(mav / "cam0" / "data.csv")[1].split(",")[0])
            end_ns = first_ns + round(minutes * 60e9)
            for sensor in mav.iterdir():
                target = session / "euroc" / "mav0" / sensor.name
                target.mkdir(parents=True)
                for entry in sensor.iterdir():
                    if entry.name == "data.csv":
                        rows = _csv_rows(entry)
                        kept = [
                            r for r in rows if r.startswith("#") or int(r.split(",")[0]) <= end_ns
                        ]
                        (target / "data.csv").write_text("\n".join(kept) + "\n")
                        if (sensor / "data").is_dir():
                            (target / "data").mkdir()
                            for row in kept:
                                if not row.startswith("#"):
                                    name = row.split(",")[1].strip()
                                    (target / "data" / name).symlink_to(
                                        (sensor / "data" / name).resolve()
                                    )
                    elif entry.name != "data":
                        (target / entry.name).symlink_to(entry.resolve())
    tmp.rename(out)


def make_session_prefix(long_root: Path, sim: Path, out: Path, *, minutes: float) -> None:
    """The first `minutes` of every imported session of the run at `long_root` as a
    survey folder at `out`, each session a field session folder (`<out>/session_NN/
    session`), so the prefix runs from the same H.264 packets as the whole dive.

    The session's messages up to its first video packet + `minutes` are copied
    undecoded, archive by archive (the video is cut after a packet: decoding starts at
    the first keyframe, as for the whole dive; an archive that starts later is left
    out); each archive's Metadata records are copied, the keyframe list cut at the same
    time; calib/ and session.yaml are copied and metadata.yaml written again.
    Everything else of `sim` is linked, as in `make_prefix`.
    """
    import shutil

    from shared.archive import ArchiveReader, ArchiveWriter
    from shared.archive.rosbag2 import write_rosbag2_metadata
    from shared.archive.video import KEYFRAME_METADATA, SessionVideo, session_archives
    from shared.formats.recordings import SessionRecording

    tmp = _new_survey(sim, out)
    if tmp is None:
        return
    for k, item in enumerate(_sessions(sim)):
        source = long_root / "run" / "imports" / f"dive{k + 1}"
        target = tmp / item.name / "session"
        target.mkdir(parents=True)
        for part in item.iterdir():
            if part.name not in ("gopro", "euroc"):
                (tmp / item.name / part.name).symlink_to(part.resolve())
        shutil.copytree(source / "calib", target / "calib")
        shutil.copy2(source / "session.yaml", target / "session.yaml")
        topic = SessionRecording(source).camera_topic
        with SessionVideo(source, topic=topic) as video:
            end_ns = video.time_span_ns()[0] + round(minutes * 60e9)
        for archive in session_archives(source):
            with ArchiveReader(archive) as reader:
                if reader.time_span_ns()[0] > end_ns:
                    continue
                with ArchiveWriter(target / archive.name) as writer:
                    for name, values in reader.metadata().items():
                        if name == KEYFRAME_METADATA:
                            values = {
                                channel: ",".join(
                                    v for v in text.split(",") if v and int(v) <= end_ns
                                )
                                for channel, text in values.items()
                            }
                        writer.add_metadata(name, values)
                    for record in reader.raw_messages(end_ns=end_ns + 1):
                        writer.write_cdr(record.topic, record.data, log_time_ns=record.log_time_ns)
        write_rosbag2_metadata(target)
    tmp.rename(out)


def _csv_rows(path: Path) -> list[str]:
    return [r for r in path.read_text().splitlines() if r.strip()]


def project_file(root: Path, sim: Path, *, source: str) -> Path:
    """The project of the survey `sim` in `root`, its sessions read from `source`:
    "gopro" (the simulator's MP4, imported), "euroc" (its PNG copy) or "session" (a
    field session folder, as `make_session_prefix` writes)."""
    from shared.folders import SessionFolder

    sessions = _sessions(sim)
    lines = [
        f"name: bench {sim.name}",
        "output: run",
        f"truth: {sim / 'truth.json'}",
        # The survey's calib/ is laid out as a session's (sim.survey).
        f"calibration: {{camchain: {SessionFolder(sim).camchain}, "
        f"imu: {SessionFolder(sim).imu_yaml}}}",
        "targets:",
        *[f"  - {t}" for t in sorted((sim / "targets").glob("*.yaml"))],
        "sessions:",
    ]
    for k, session in enumerate(sessions):
        where = {
            "euroc": f"euroc: {session / 'euroc'}",
            "session": f"session: {session / 'session'}",
            "gopro": f"gopro: [{session / 'gopro' / 'GX010001.MP4'}]",
        }[source]
        lines += [f"  - name: dive{k + 1}", f"    {where}", f"    dive: {session / 'dive'}"]
    path = root / "project.yaml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def run_chain(
    root: Path, sim: Path, *, source: str
) -> tuple[dict[str, float | str], dict[str, float]]:
    """Stage -> seconds (summed over sessions), or a status word when it did not finish;
    and stage -> peak resident memory in MiB (the largest over sessions)."""
    from postproc.pipeline.project import load_project
    from postproc.pipeline.runner import STAMP_NAME, plan, run_project

    project = load_project(project_file(root, sim, source=source))
    result = run_project(project, echo=print)
    describe(project)
    outputs = {t.key: t.out for t in plan(project)[0]}
    per_stage: dict[str, float | str] = {}
    peaks: dict[str, float] = {}
    for outcome in result.outcomes:
        if outcome.status in ("done", "skipped"):
            seconds, peak = outcome.seconds, outcome.peak_rss_mib
            if outcome.status == "skipped":  # up to date from an earlier run: its own figures
                stamp = json.loads((outputs[outcome.key] / STAMP_NAME).read_text())
                seconds = float(stamp["seconds"])
                peak = float(stamp.get("peak_rss_mib", 0.0))
            peaks[outcome.stage] = max(peaks.get(outcome.stage, 0.0), peak)
            previous = per_stage.get(outcome.stage, 0.0)
            if isinstance(previous, float):
                per_stage[outcome.stage] = previous + seconds
        else:
            per_stage[outcome.stage] = outcome.status
    return per_stage, peaks


def run_quick_look(root: Path, sim: Path, *, source: str, width_px: int) -> dict[str, Any]:
    """The quick look (`wreckmap-post run --quick`) on the project of `root` (after its
    full run, so the import is already there): seconds per stage (summed over
    sessions), the page's seconds, the SLAM errors against the truth, what the page
    shows."""
    from postproc.pipeline.evaluate import evaluate_project
    from postproc.pipeline.project import load_project
    from postproc.pipeline.quick import quick_project, quick_stages, run_quick
    from postproc.pipeline.stages import STAGES

    project = load_project(project_file(root, sim, source=source))
    started = time.monotonic()
    result, page = run_quick(project, width_px=width_px, force=True, echo=lambda _line: None)
    total = time.monotonic() - started
    per_stage: dict[str, float] = {}
    for outcome in result.outcomes:
        if outcome.status == "done":
            per_stage[outcome.stage] = per_stage.get(outcome.stage, 0.0) + outcome.seconds
    figures: dict[str, Any] = {
        "stages_s": per_stage,
        "page_s": total - sum(per_stage.values()),
        "total_s": total,
        "ok": result.ok,
        "page": str(page),
    }
    try:
        # The full registry, with the quick look's places (its imports are the full run's).
        errors = evaluate_project(
            quick_project(project, width_px=width_px),
            stages={**STAGES, **quick_stages(project)},
        )
        figures["slam_ate_m"] = {
            name: s.get("slam_ate_m") for name, s in errors.get("sessions", {}).items()
        }
        figures["depth_clock_error_s"] = {
            name: s.get("depth_time_offset_error_s")
            for name, s in errors.get("sessions", {}).items()
        }
    except Exception as error:  # the timing is still worth printing
        figures["evaluation_error"] = f"{type(error).__name__}: {error}"
    text = page.read_text(encoding="utf-8")
    figures["page_images"] = text.count("<img")
    figures["page_has_viewer"] = "wm-viewer" in text
    figures["page_mb"] = len(text.encode()) / 1e6
    return figures


def describe(project: object) -> None:
    """Print what drives the SfM and dense time (keyframes, track length, reference views)
    and the errors of the outputs against the simulator's truth."""
    from postproc.pipeline.evaluate import evaluate_project
    from postproc.pipeline.stages import RunFolders

    folders = RunFolders(project.output)  # type: ignore[attr-defined]
    sfm_stats, dense_stats = folders.sfm().stats, folders.dense().report
    if sfm_stats.is_file():
        sfm = folders.sfm().read_stats()
        print(
            f"  sfm: {sfm['keyframes']} keyframes, {sfm['points3D']} points, mean track length "
            f"{sfm['mean_track_length']:.1f}, {len(sfm['rounds'])} rounds"
        )
    if dense_stats.is_file():
        dense = folders.dense().read_report()
        chosen = f"{dense['reference_images']} of {dense['images']}"
        print(f"  dense: {chosen} keyframes get a depth map")
    errors = evaluate_project(project)
    for name, session in errors.get("sessions", {}).items():
        print(
            f"  truth, {name}: slam ATE {100 * session.get('slam_ate_m', math.nan):.1f} cm, "
            f"depth clock error {1000 * session.get('depth_time_offset_error_s', math.nan):.0f} ms"
        )
    for stage in ("merge", "sfm"):
        if stage in errors:
            print(f"  truth, {stage}: keyframe position RMS {100 * errors[stage]['rms_m']:.1f} cm")
    if "dense" in errors:
        d = errors["dense"]
        scores = ", ".join(
            f"{100 * s['accuracy']:.1f} / {100 * s['completeness']:.1f} % at {s['threshold_m']:g} m"
            for s in d["scores"]
        )
        print(
            f"  truth, mesh: median error {1000 * d['median_distance_m']:.1f} mm; "
            f"accuracy / completeness {scores} ({d['completeness_basis']})"
        )


def print_quick(
    quick: list[dict[str, Any]],
    results: list[dict[str, float | str]],
    lengths: list[float],
    args: argparse.Namespace,
) -> dict[str, Any]:
    """The quick look's table: per stage the two lengths, k and the 45-minute projection
    (the import is the full run's: the quick look shares it)."""
    print(
        f"\nquick look (run --quick, SLAM at {args.quick_width} px wide), scaling from "
        f"{lengths[1]:g} min; import from the full run (shared)"
    )
    print(f"{'part':<8} {'seconds':>9} {'short s':>9} {'k':>6} {'45-min dive s':>14}")
    rows: dict[str, tuple[float, float]] = {}
    for stage in ("import", "slam", "depth"):
        if stage == "import":
            long, short = results[0].get(stage), results[1].get(stage)
        else:
            long, short = quick[0]["stages_s"].get(stage), quick[1]["stages_s"].get(stage)
        if isinstance(long, float):
            rows[stage] = (long, short if isinstance(short, float) else math.nan)
    rows["page"] = (float(quick[0]["page_s"]), float(quick[1]["page_s"]))
    total_45 = 0.0
    table: dict[str, Any] = {}
    for part, (long, short) in rows.items():
        k = math.nan
        if math.isfinite(short) and short > 0 and long > 0:
            k = math.log(long / short) / math.log(lengths[0] / lengths[1])
        at_45 = long * (TARGET_MIN / lengths[0]) ** (k if math.isfinite(k) else 1.0)
        total_45 += at_45
        table[part] = {"seconds": long, "short_s": short, "k": k, "at_45_min_s": at_45}
        k_text = f"{k:.2f}" if math.isfinite(k) else "(1)"
        print(f"{part:<8} {long:>9.1f} {short:>9.1f} {k_text:>6} {at_45:>14.0f}")
    print(f"quick look of a 45-minute dive: {total_45 / 60:.1f} min (goal <= 10 min)")
    for name, ate in (quick[0].get("slam_ate_m") or {}).items():
        clock = (quick[0].get("depth_clock_error_s") or {}).get(name)
        clock_text = "-" if clock is None else f"{1000 * clock:.0f} ms"
        print(f"  quick truth, {name}: slam ATE {100 * (ate or math.nan):.1f} cm, "
              f"depth clock error {clock_text}")  # fmt: skip
    if "evaluation_error" in quick[0]:
        print(f"  quick truth: not evaluated ({quick[0]['evaluation_error']})")
    print(
        f"  page: {quick[0]['page_images']} images, 3D viewer "
        f"{'yes' if quick[0]['page_has_viewer'] else 'no'}, {quick[0]['page_mb']:.1f} MB "
        f"({quick[0]['page']})"
    )
    return {"parts": table, "at_45_min_s": total_45, "runs": quick}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="filmed minutes per dive")
    parser.add_argument("--scale-fraction", type=float, default=0.5, help="second length, x")
    parser.add_argument("--sessions", type=int, default=1, help="dives in the survey")
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate (GoPro: 30)")
    parser.add_argument("--euroc", action="store_true", help="skip the GoPro video and import")
    parser.add_argument(
        "--no-prefix",
        dest="prefix",
        action="store_false",
        help="simulate the second length instead of cutting the first part of the dive",
    )
    parser.add_argument(
        "--prefix-source",
        choices=("video", "euroc"),
        default="video",
        help="cut the prefix from the whole dive's imported session (video, the default) "
        "or from its EuRoC copy (PNG); with --euroc always the EuRoC copy",
    )
    parser.add_argument(
        "--video-crf",
        type=int,
        help="the simulator's x264 quality (default: the simulator's); the folders get a "
        "_crfN suffix",
    )
    parser.add_argument("--out", type=Path, default=REPO / "bench-output" / "pipeline")
    parser.add_argument(
        "--quick-width",
        type=int,
        default=480,
        help="also time the quick look (`run --quick`) at this SLAM width on both lengths "
        "(0: skip it)",
    )
    args = parser.parse_args(argv)
    os.environ.setdefault("WRECKMAP_PROGRESS", "0")
    os.environ.setdefault("GLOG_minloglevel", "1")  # COLMAP INFO lines off

    lengths = [args.minutes, args.minutes * args.scale_fraction]
    results: list[dict[str, float | str]] = []
    peaks: list[dict[str, float]] = []
    quick: list[dict[str, Any]] = []
    size = f"{args.width}x{args.height}" + (
        f"_crf{args.video_crf}" if args.video_crf is not None else ""
    )
    long_root = args.out / f"{lengths[0]:g}min_{size}"
    for index, minutes in enumerate(lengths):
        if index == 1 and args.prefix:
            from_video = args.prefix_source == "video" and not args.euroc
            source = "session" if from_video else "euroc"
            suffix = "" if from_video else "_euroc"
            root = args.out / f"{minutes:g}min_of_{lengths[0]:g}_{size}{suffix}"
            root.mkdir(parents=True, exist_ok=True)
            if from_video:
                make_session_prefix(long_root, long_root / "sim", root / "sim", minutes=minutes)
                what = "its imported session, the H.264 packets copied"
            else:
                make_prefix(long_root / "sim", root / "sim", minutes=minutes)
                what = "EuRoC, linked"
            print(f"first {minutes:g} min of the {lengths[0]:g}-min dive ({what})")
            times, peak = run_chain(root, root / "sim", source=source)
            results.append(times)
            peaks.append(peak)
            if args.quick_width:
                quick.append(run_quick_look(root, root / "sim", source=source,
                                            width_px=args.quick_width))  # fmt: skip
            continue
        root = args.out / f"{minutes:g}min_{size}"
        root.mkdir(parents=True, exist_ok=True)
        sim_s = simulate(root / "sim", minutes=minutes, args=args)
        print(
            f"simulated {minutes:g} min x {args.sessions} at {args.width}x{args.height}: "
            f"{sim_s:.0f} s"
        )
        source = "euroc" if args.euroc else "gopro"
        times, peak = run_chain(root, root / "sim", source=source)
        results.append(times)
        peaks.append(peak)
        if args.quick_width:
            quick.append(run_quick_look(root, root / "sim", source=source,
                                        width_px=args.quick_width))  # fmt: skip

    video_h = lengths[0] * args.sessions / 60.0
    print(
        f"\nwreckmap-post run, {args.sessions} dive(s) of {lengths[0]:g} min "
        f"({args.width}x{args.height} @ {args.fps:g} Hz); scaling from {lengths[1]:g} min"
    )
    header = (
        f"{'stage':<8} {'seconds':>9} {'s / video h':>12} {'k':>6} {'45-min dive s':>14} "
        f"{'peak MiB':>9} {'short MiB':>10}"
    )
    print(header)
    stages = ["import", "slam", "depth", "merge", "sfm", "dense"]
    total = 0.0
    total_45 = 0.0
    figures = {}
    for stage in stages:
        long, short = results[0].get(stage), results[1].get(stage)
        if long is None:
            print(f"{stage:<8} {'not planned':>9}")
            continue
        if not isinstance(long, float):
            print(f"{stage:<8} {long:>9}")
            continue
        k = math.nan
        if isinstance(short, float) and short > 0 and long > 0 and lengths[0] != lengths[1]:
            k = math.log(long / short) / math.log(lengths[0] / lengths[1])
        exponent = k if math.isfinite(k) else 1.0
        at_45 = long * (TARGET_MIN / lengths[0]) ** exponent
        total += long
        total_45 += at_45
        # Peak resident memory of the stage's run at both lengths: flat over the dive when
        # the two agree (the import runs as a subprocess: its own peak).
        peak_long, peak_short = peaks[0].get(stage, math.nan), peaks[1].get(stage, math.nan)
        figures[stage] = {
            "seconds": long,
            "per_video_hour_s": long / video_h,
            "k": k,
            "at_45_min_s": at_45,
            "peak_rss_mib": peak_long,
            "short_peak_rss_mib": peak_short,
        }
        k_text = f"{k:.2f}" if math.isfinite(k) else "(1)"  # not measured: taken as linear
        print(
            f"{stage:<8} {long:>9.1f} {long / video_h:>12.0f} {k_text:>6} {at_45:>14.0f} "
            f"{peak_long:>9.0f} {peak_short:>10.0f}"
        )
    print(f"{'total':<8} {total:>9.1f} {total / video_h:>12.0f} {'':>6} {total_45:>14.0f}")
    print(f"45-minute dive, import to mesh: {total_45 / 3600:.2f} h (goal <= 1 h)")
    print(f"load average now: {os.getloadavg()[0]:.1f} (2-core machine: timings rise with it)")
    missing = [s for s in stages if not isinstance(results[0].get(s, 0.0), float)]
    print("stages not finished or not built: " + (", ".join(missing) or "none"))
    if quick:
        figures["quick"] = print_quick(quick, results, lengths, args)
    (args.out / "bench_pipeline.json").write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
