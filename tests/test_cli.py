"""Both command lines: instant --help (no heavy imports), one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ["gtsam", "pycolmap", "depthai", "zenoh", "cv2", "av", "scipy", "matplotlib", "mcap"]


@pytest.mark.parametrize("module", ["field.cli", "postproc.cli"])
def test_help_imports_nothing_heavy(module: str) -> None:
    """`--help` of every command group must not pull the heavy libraries."""
    code = f"""
import json, sys, importlib, contextlib, io
cli = importlib.import_module({module!r})
names = ["--help"]
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        cli.main(["--help"])
    except SystemExit:
        pass
parser = cli.cli.build_parser("x", "", cli.COMMAND_MODULES)
for action in parser._subparsers._group_actions:
    for name, sub in action.choices.items():
        with contextlib.redirect_stdout(io.StringIO()):
            try:
                cli.main([name, "--help"])
            except SystemExit:
                pass
print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))
"""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert json.loads(result.stdout.strip().splitlines()[-1]) == []


def test_known_error_is_one_line(tmp_path, capsys) -> None:
    """A WreckmapError raised by a handler prints one line and returns 1."""
    import argparse

    from shared import cli
    from shared.errors import InputError

    def handler(args: argparse.Namespace) -> int:
        raise InputError(f"{tmp_path / 'x.mp4'}: no GPMF track")

    class Module:
        @staticmethod
        def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
            subparsers.add_parser("boom").set_defaults(handler=handler)

    sys.modules["_wreckmap_test_boom"] = Module  # type: ignore[assignment]
    try:
        code = cli.run("prog", "", ["_wreckmap_test_boom"], ["boom"])
    finally:
        del sys.modules["_wreckmap_test_boom"]
    err = capsys.readouterr().err
    assert code == 1
    assert err.count("\n") == 1
    assert "x.mp4: no GPMF track" in err
