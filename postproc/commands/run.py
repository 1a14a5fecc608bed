"""`wreckmap-post run` and `wreckmap-post report`: the whole lab batch of a project file."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from postproc.pipeline.runner import RunResult

RUN_EXAMPLE = """\
examples:
  wreckmap-post run project.yaml
  wreckmap-post run project.yaml --workers 2                  # local process pool
  wreckmap-post run project.yaml --scheduler tcp://lab1:8786  # Dask distributed
  wreckmap-post run project.yaml --scheduler slurm --workers 4
  wreckmap-post run project.yaml --quick      # between dives: path, depth, coverage

Runs import (GoPro files), slam, depth, merge, sfm and dense for every session of
the project (deploy/project.example.yaml documents every key), skipping stages whose
inputs and options have not changed, then writes report.html. Exit status: 0 all
done or up to date, 1 a stage failed (what did not depend on it ran).
"""

REPORT_EXAMPLE = """\
example:
  wreckmap-post report project.yaml      # -> <output>/report.html
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run every stage of a project file (local, Dask or SLURM)",
        epilog=RUN_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("project", type=Path, metavar="PROJECT", help="project YAML file")
    parser.add_argument(
        "--scheduler",
        default="local",
        help="local (default, no server), slurm, or a Dask scheduler address tcp://HOST:PORT",
    )
    parser.add_argument(
        "--workers", type=int, default=1, help="local processes or SLURM jobs (default 1)"
    )
    parser.add_argument("--force", action="store_true", help="rerun stages even when up to date")
    parser.add_argument("--no-report", action="store_true", help="skip report.html")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="quick look for the boat: calibrate, import, slam at reduced width and depth "
        "only, into <output>/quick with quick/quick.html (path, depth, sparse map, coverage)",
    )
    parser.add_argument(
        "--quick-width",
        type=int,
        default=480,
        metavar="PX",
        help="SLAM image width of the quick look (default 480)",
    )
    parser.set_defaults(handler=_run)

    report = subparsers.add_parser(
        "report",
        help="write report.html of a project (self-contained, opens offline)",
        epilog=REPORT_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    report.add_argument("project", type=Path, metavar="PROJECT", help="project YAML file")
    report.add_argument("--out", type=Path, help="report file (default: <output>/report.html)")
    report.set_defaults(handler=_report)


def _run(args: argparse.Namespace) -> int:
    from postproc.pipeline.dask_backend import make_backend
    from postproc.pipeline.project import load_project
    from postproc.pipeline.report import write_report
    from postproc.pipeline.runner import run_project
    from shared.errors import InputError

    project = load_project(args.project)
    if args.quick_width < 64:
        raise InputError(f"--quick-width {args.quick_width}: expected at least 64 px")
    backend = make_backend(args.scheduler, workers=args.workers, cluster=project.cluster)
    try:
        if args.quick:
            from postproc.pipeline.quick import run_quick

            result, page = run_quick(
                project, backend=backend, width_px=args.quick_width, force=args.force, echo=print
            )
        else:
            result = run_project(project, backend=backend, force=args.force, echo=print)
    finally:
        backend.close()
    print(format_outcomes(result))
    if args.quick:
        print(f"quick look: {page}")
        return int(result.exit_code())
    if not args.no_report:
        print(f"report: {write_report(project, result=result)}")
    code: int = result.exit_code()
    return code


def _report(args: argparse.Namespace) -> int:
    from postproc.pipeline.project import load_project
    from postproc.pipeline.report import write_report

    project = load_project(args.project)
    print(write_report(project, out_path=args.out))
    return 0


def format_outcomes(result: RunResult) -> str:
    """A plain table of every task: stage, session, status, seconds, message."""
    lines = [f"{'stage':<8} {'session':<14} {'status':<8} {'time_s':>8}  note"]
    for o in result.outcomes:
        lines.append(
            f"{o.stage:<8} {o.session or '-':<14} {o.status:<8} {o.seconds:>8.1f}  {o.message}"
        )
    lines += [f"note: {n}" for n in result.notes]
    return "\n".join(lines)
