"""What both command lines share: argument parsing, dispatch and error reporting.

Each command group lives in its own light module (`field/commands/*.py`,
`postproc/commands/*.py`) exposing `register(subparsers)`; heavy libraries are
imported inside the handlers so `--help` stays instant.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from types import ModuleType

from shared.errors import WreckmapError


def build_parser(
    prog: str, description: str, modules: Sequence[str | ModuleType]
) -> argparse.ArgumentParser:
    """A parser with one sub-command group per module in `modules` (modules or names)."""
    parser = argparse.ArgumentParser(
        prog=prog,
        description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in modules:
        found = importlib.import_module(module) if isinstance(module, str) else module
        found.register(subparsers)
    return parser


def run(
    prog: str,
    description: str,
    modules: Sequence[str | ModuleType],
    argv: Sequence[str] | None = None,
) -> int:
    """Parse `argv`, run the chosen handler; known errors print one line and return 1."""
    parser = build_parser(prog, description, modules)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        result = args.handler(args)
    except WreckmapError as error:
        print(f"{prog}: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)
