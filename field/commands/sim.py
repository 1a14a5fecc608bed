"""`wreckmap-field sim`: the simulated wreck survey (truth for every stage's tests)."""

from __future__ import annotations

import argparse
from pathlib import Path

SURVEY_EXAMPLE = """\
example:
  wreckmap-field sim survey --out sim/ --sessions 2 --duration 60 --seed 1
  wreckmap-field sim survey --out tiny/ --duration 5 --width 320 --height 180 --no-video
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    group = subparsers.add_parser("sim", help="simulated wreck survey with ground truth")
    commands = group.add_subparsers(dest="sim_command", metavar="SIM_COMMAND", required=True)
    survey = commands.add_parser(
        "survey",
        help="render a simulated multi-session survey (EuRoC, dive logs, GoPro MP4, truth)",
        epilog=SURVEY_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    survey.add_argument("--out", required=True, type=Path, help="survey folder to create")
    survey.add_argument("--sessions", type=int, default=2, help="dives to simulate")
    survey.add_argument("--duration", type=float, default=60.0, help="filmed seconds a session")
    survey.add_argument("--seed", type=int, default=1, help="same seed, same bytes")
    survey.add_argument("--width", type=int, default=640, help="image width, px (even)")
    survey.add_argument("--height", type=int, default=360, help="image height, px (even)")
    survey.add_argument("--fps", type=float, default=15.0, help="frame rate, Hz")
    survey.add_argument("--workers", type=int, default=2, help="render processes")
    survey.add_argument(
        "--texel-mm", type=float, default=5.0, help="texture resolution on the wreck, mm"
    )
    survey.add_argument("--no-video", action="store_true", help="skip the GoPro-like MP4")
    survey.add_argument(
        "--video-crf",
        type=int,
        help="x264 quality of the MP4 (lower: better; default SurveyOptions.video_crf)",
    )
    survey.add_argument(
        "--depth", action="store_true", help="also write depth maps (16-bit PNG, mm)"
    )
    survey.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    survey.set_defaults(handler=_survey)


def _survey(args: argparse.Namespace) -> int:
    from shared.errors import InputError
    from sim.survey import SurveyOptions, run

    try:
        options = SurveyOptions(
            sessions=args.sessions,
            duration_s=args.duration,
            seed=args.seed,
            width=args.width,
            height=args.height,
            fps=args.fps,
            video=not args.no_video,
            save_depth=args.depth,
            workers=args.workers,
            texel_m=args.texel_mm * 1e-3,
            seafloor_texel_m=max(args.texel_mm * 3e-3, 0.005),
            **({} if args.video_crf is None else {"video_crf": args.video_crf}),
        )
    except ValueError as error:
        raise InputError(f"sim survey: {error}") from error
    out = run(options, args.out, overwrite=args.overwrite)
    print(out)
    return 0
