"""`wreckmap-field`: import, record, preview and download on the boat."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from shared import cli

DESCRIPTION = """\
wreckmap field tools (dive-boat laptop, embedded logger).

example:
  wreckmap-field gopro import DCIM/ --out sessions/
"""

# Command groups, in the order data flows through the field side.
COMMAND_MODULES: tuple[str, ...] = (
    "field.commands.sim",
    "field.commands.gopro",
    "field.commands.record",
    "field.commands.dc",
    "field.commands.export",
)


def main(argv: Sequence[str] | None = None) -> int:
    return cli.run("wreckmap-field", DESCRIPTION, COMMAND_MODULES, argv)


if __name__ == "__main__":
    sys.exit(main())
