"""`wreckmap-post`: the lab batch (slam, depth, merge, sfm, dense, run, export)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from types import ModuleType

from postproc.commands import export as export_command
from postproc.commands import options as options_command
from postproc.commands import run as run_command
from postproc.pipeline.stages import STAGES
from shared import cli

DESCRIPTION = """\
wreckmap lab post-processing.

example:
  wreckmap-post slam sessions/dive1 --out results/dive1/slam
"""

# Command groups, in the order data flows through the stages: the subcommand module of
# every stage of the registry that has one, then the whole batch, the exports and the
# options (modules, not names: nothing is looked up by string).
COMMAND_MODULES: tuple[ModuleType, ...] = (
    *(stage.command for stage in STAGES.values() if stage.command is not None),
    run_command,
    export_command,
    options_command,
)


def main(argv: Sequence[str] | None = None) -> int:
    return cli.run("wreckmap-post", DESCRIPTION, COMMAND_MODULES, argv)


if __name__ == "__main__":
    sys.exit(main())
