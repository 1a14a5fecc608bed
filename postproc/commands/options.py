"""`wreckmap-post options`: every stage option of a project file, with its default and unit."""

from __future__ import annotations

import argparse
from pathlib import Path

EXAMPLE = """\
example:
  wreckmap-post options                  # the stages: section of a project file
  wreckmap-post options --write-example deploy/project.example.yaml

Prints the `stages:` section of a project file with every key of every stage's
options at its default, commented with its help and unit, as the options
dataclasses declare them. --write-example rewrites that section of an example
project file (the rest of the file is kept).
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "options",
        help="the stage options of a project file (keys, defaults, units)",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--write-example",
        type=Path,
        metavar="YAML",
        help="rewrite the stages: section of this example project file",
    )
    parser.set_defaults(handler=_options)


def _options(args: argparse.Namespace) -> int:
    from postproc.pipeline.options import stages_example, update_example

    if args.write_example is None:
        print(stages_example(), end="")
        return 0
    changed = update_example(args.write_example)
    print(f"{args.write_example}: {'updated' if changed else 'already current'}")
    return 0
