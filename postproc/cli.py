"""`wreckmap-post`: the lab batch (slam, depth, merge, sfm, dense, run, export)."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from postproc.pipeline.stages import STAGES
from shared import cli

DESCRIPTION = """\
wreckmap lab post-processing.

example:
  wreckmap-post slam sessions/dive1 --out results/dive1/slam
"""

# Command groups, in the order data flows through the stages: one per stage of the
# registry that has a command, then the whole batch and the exports.
COMMAND_MODULES: tuple[str, ...] = (
    *(stage.command.__name__ for stage in STAGES.values() if stage.command is not None),
    "postproc.commands.run",
    "postproc.commands.export",
    "postproc.commands.options",
)


def main(argv: Sequence[str] | None = None) -> int:
    return cli.run("wreckmap-post", DESCRIPTION, COMMAND_MODULES, argv)


if __name__ == "__main__":
    sys.exit(main())
