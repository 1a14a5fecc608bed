"""`make demo`: a simulated survey taken in through the real paths and processed end to end.

    .venv/bin/python bench/demo.py --out demo-output            # what `make demo` runs
    .venv/bin/python bench/demo.py --out demo-output/quick --dense-image-px 160

Dives shorter than about 90 s hold too few 10 s dive-computer samples for the depth
sync to be sure of the clock offset (it then refuses the dive), and images smaller than
640x360 leave the AprilGrids undetected (merge cannot place the second dive).

Steps, each a real command line run as a subprocess:

1. `wreckmap-field sim survey`: two dives over a simulated wreck with exact truth
   (GoPro-like MP4s with GPMF IMU, dive-computer logs on their own clocks, truth mesh).
2. `wreckmap-field dc simulate --profile <the survey's dive logs>`: a simulated
   Shearwater on a pseudo-terminal, downloaded with `wreckmap-field dc download`.
3. `wreckmap-post run project.yaml`: the GoPro files imported (`wreckmap-field gopro
   import`, run by the pipeline), then slam, depth, merge, sfm and dense, and report.html.
4. A summary: the time of every step and stage and its error against the truth.

Exit status 0 only when every step and every stage succeeded. Steps already done in `--out` are kept
(delete the folder to start over); the pipeline skips stages whose inputs are unchanged.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def _command(module: str, *args: str | Path) -> list[str]:
    return [sys.executable, "-m", module, *[str(a) for a in args]]


def _env() -> dict[str, str]:
    path = os.environ.get("PYTHONPATH", "")
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), path) if p),
        # COLMAP's per-image INFO lines would bury the summary (warnings still show).
        "GLOG_minloglevel": os.environ.get("GLOG_minloglevel", "1"),  # noqa: SIM112 (glog spells it so)
    }


def _step(name: str, command: list[str], log_path: Path, *, echo: bool) -> tuple[int, float]:
    """Run one command; its output goes to `log_path` (and the console with echo)."""
    print(f"== {name}: {' '.join(Path(c).name if c == sys.executable else c for c in command)}")
    started = time.monotonic()
    with log_path.open("w", encoding="utf-8") as log_file:
        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env()
        )
        assert process.stdout is not None
        for line in process.stdout:
            log_file.write(line)
            if echo:
                print("   " + line.rstrip())
        code = process.wait()
    seconds = time.monotonic() - started
    if code != 0 and not echo:
        print("   " + "\n   ".join(log_path.read_text(encoding="utf-8").splitlines()[-5:]))
    print(f"   exit {code} in {seconds:.1f} s (log: {log_path})")
    return code, seconds


def download_dives(sim: Path, dives: Path, log_path: Path) -> tuple[int, float]:
    """Serve the survey's dive logs from a simulated Shearwater and download them over a pty."""
    print("== dive computer: simulated Perdix AI on a pseudo-terminal, then dc download")
    started = time.monotonic()
    profiles = sorted(sim.glob("session_*/dive"))
    simulator = subprocess.Popen(
        _command(
            "field.cli",
            "dc",
            "simulate",
            "--model",
            "perdix-ai",
            "--dives",
            "1",
            "--seed",
            "7",
            "--profile",
            *profiles,
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        assert simulator.stdout is not None
        port = simulator.stdout.readline().strip()
        if not port:
            print(
                "   the simulator printed no pty path: "
                + (simulator.stderr.read() if simulator.stderr else "")
            )
            return 1, time.monotonic() - started
        print(f"   simulator on {port}")
        code, _ = _step(
            "dc download",
            _command(
                "field.cli",
                "dc",
                "download",
                "--port",
                port,
                "--model",
                "perdix-ai",
                "--out",
                dives,
            ),
            log_path,
            echo=True,
        )
    finally:
        simulator.send_signal(signal.SIGINT)
        try:
            simulator.wait(timeout=10)
        except subprocess.TimeoutExpired:
            simulator.kill()
            simulator.wait()
    return code, time.monotonic() - started


def write_project(
    out: Path,
    sim: Path,
    dives: Path,
    *,
    dense_image_px: int,
    intake: str = "gopro",
    depth_min_range_m: float = 0.5,
) -> Path:
    """The demo's project file: GoPro sessions (or the simulator's EuRoC folders with
    intake="euroc"), the downloaded dives, the simulator's calibration and truth."""
    from shared.folders import SessionFolder

    calib = SessionFolder(sim)  # the survey's calib/ is laid out as a session's (sim.survey)
    sessions = sorted(p for p in sim.glob("session_*") if p.is_dir())
    lines = [
        "# Written by bench/demo.py (see deploy/project.example.yaml for every key).",
        "name: wreckmap demo (simulated two-dive survey)",
        f"output: {'run' if intake == 'gopro' else 'run-' + intake}",
        f"truth: {os.path.relpath(sim / 'truth.json', out)}",
        "calibration:",
        f"  camchain: {os.path.relpath(calib.camchain, out)}",
        f"  imu: {os.path.relpath(calib.imu_yaml, out)}",
        "targets:",
        *[f"  - {os.path.relpath(t, out)}" for t in sorted((sim / "targets").glob("*.yaml"))],
        "sessions:",
    ]
    for k, session in enumerate(sessions):
        lines += [
            f"  - name: dive{k + 1}",
            f"    gopro: [{os.path.relpath(session / 'gopro' / 'GX010001.MP4', out)}]"
            if intake == "gopro"
            else f"    euroc: {os.path.relpath(session / 'euroc', out)}",
            f"    dive: {os.path.relpath(dives, out)}",
            f"    truth_session: {k}",
        ]
    lines += [
        "stages:",
        # A dive of a minute or two spans less than the default 1 m of depth where it
        # overlaps the video; a smaller range still gives a clock offset, poor when few
        # 10-s dive samples fall in the video (its error is in the summary).
        "  depth:",
        f"    min_depth_range_m: {depth_min_range_m}",
        "  dense:",
        f"    max_image_size_px: {dense_image_px}",
    ]
    path = out / ("project.yaml" if intake == "gopro" else f"project-{intake}.yaml")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def summary(project_path: Path, steps: dict[str, tuple[int, float]]) -> tuple[str, bool]:
    """The table of steps and stages (time, error against truth) and whether all succeeded."""
    from postproc.pipeline.project import load_project
    from postproc.pipeline.runner import STAMP_NAME, plan
    from postproc.pipeline.stages import RunFolders

    project = load_project(project_path)
    evaluation: dict[str, Any] = {}
    evaluation_path = project.output / "evaluation.json"
    if evaluation_path.is_file():
        evaluation = json.loads(evaluation_path.read_text(encoding="utf-8"))
    rows = [("step / stage", "session", "status", "time_s", "error against truth")]
    ok = True
    for name, (code, seconds) in steps.items():
        rows.append((name, "-", "done" if code == 0 else f"exit {code}", f"{seconds:.1f}", ""))
        ok = ok and code == 0
    tasks, _ = plan(project)
    for task in tasks:
        stamp = None
        if (task.out / STAMP_NAME).is_file():
            stamp = json.loads((task.out / STAMP_NAME).read_text(encoding="utf-8"))
        status = "done" if stamp else "failed/not run"
        ok = ok and stamp is not None
        took = f"{stamp['seconds']:.1f}" if stamp else "-"
        rows.append((task.stage, task.session or "-", status, took, _error(task, evaluation)))
    width = [max(len(r[i]) for r in rows) for i in range(5)]
    text = "\n".join("  ".join(c.ljust(w) for c, w in zip(r, width, strict=True)) for r in rows)
    text += f"\nreport: {project.output / 'report.html'}"
    mesh = RunFolders(project.output).dense().mesh
    text += f"\nmesh: {mesh if mesh.is_file() else 'not made'}"
    return text, ok


def _error(task: Any, evaluation: dict[str, Any]) -> str:
    session = evaluation.get("sessions", {}).get(task.session or "", {})
    if task.stage == "slam" and "slam_ate_m" in session:
        return f"ATE {session['slam_ate_m']:.3f} m"
    if task.stage == "depth" and "depth_time_offset_error_s" in session:
        return (
            f"clock offset error {session['depth_time_offset_error_s']:+.2f} s, "
            f"depth offset error {session.get('depth_offset_error_m', float('nan')):+.3f} m"
        )
    if task.stage in ("merge", "sfm") and task.stage in evaluation:
        return f"keyframe position RMS {evaluation[task.stage]['rms_m']:.3f} m"
    if task.stage == "dense" and "dense" in evaluation:
        d = evaluation["dense"]
        at = next((s for s in d["scores"] if abs(s["threshold_m"] - 0.10) < 1e-9), d["scores"][0])
        return (
            f"median {d['median_distance_m']:.3f} m; at {at['threshold_m']:.2f} m accuracy "
            f"{at['accuracy']:.2f}, completeness {at['completeness']:.2f}"
            + (
                " (of the filmed surface)"
                if "filmed" in d.get("completeness_basis", "")
                else " (of the truth inside the mesh's box)"
            )
        )
    return ""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("demo-output"), help="demo folder")
    parser.add_argument("--sessions", type=int, default=2, help="simulated dives")
    parser.add_argument("--duration", type=float, default=90.0, help="filmed seconds a dive")
    parser.add_argument("--width", type=int, default=640, help="image width, px")
    parser.add_argument("--height", type=int, default=360, help="image height, px")
    parser.add_argument("--fps", type=float, default=10.0, help="frame rate, Hz")
    parser.add_argument("--seed", type=int, default=1, help="simulation seed")
    parser.add_argument("--dense-image-px", type=int, default=320, help="dense depth map size")
    parser.add_argument(
        "--depth-min-range-m", type=float, default=0.5, help="stages.depth.min_depth_range_m"
    )
    parser.add_argument("--workers", type=int, default=1, help="wreckmap-post run --workers")
    parser.add_argument(
        "--intake",
        choices=("gopro", "euroc"),
        default="gopro",
        help="gopro: the MP4s through `gopro import` (the real path); euroc: the simulator's "
        "EuRoC folders (bypasses the import, to look at the later stages alone)",
    )
    args = parser.parse_args(argv)

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    sim = out / "sim"
    dives = out / "dives"
    steps: dict[str, tuple[int, float]] = {}
    started = time.monotonic()

    if (sim / "truth.json").is_file():
        print(f"== simulate: {sim} exists, kept")
        steps["simulate"] = (0, 0.0)
    else:
        steps["simulate"] = _step(
            "simulate",
            _command("field.cli", "sim", "survey", "--out", sim, "--sessions", args.sessions,
                     "--duration", args.duration, "--width", args.width, "--height",
                     args.height, "--fps", args.fps, "--seed", args.seed, "--workers", "2"),
            logs / "simulate.log",
            echo=False,
        )  # fmt: skip
    if steps["simulate"][0] != 0:
        print("the simulation failed; nothing else can run")
        return 1

    if (dives / "dives.json").is_file():
        print(f"== dive computer: {dives} exists, kept")
        steps["dc-download"] = (0, 0.0)
    else:
        steps["dc-download"] = download_dives(sim, dives, logs / "dc-download.log")

    project = write_project(
        out,
        sim,
        dives,
        dense_image_px=args.dense_image_px,
        intake=args.intake,
        depth_min_range_m=args.depth_min_range_m,
    )
    steps["post-run"] = _step(
        "wreckmap-post run",
        _command("postproc.cli", "run", project, "--workers", args.workers),
        logs / "run.log",
        echo=True,
    )
    text, ok = summary(project, steps)
    print("\n" + text)
    print(
        f"total {time.monotonic() - started:.0f} s; {'all succeeded' if ok else 'FAILURES above'}"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
