"""`wreckmap-post <stage> --help` builds its flags from the light options modules: no
NumPy, OpenCV, GTSAM, SciPy or pycolmap is imported to print help."""

from __future__ import annotations

import json
import subprocess
import sys
from typing import get_args, get_type_hints

import pytest

HEAVY = ["numpy", "cv2", "gtsam", "scipy", "pycolmap"]


@pytest.mark.parametrize(
    "command",
    [
        ["slam"],
        ["depth"],
        ["merge"],
        ["sfm"],
        ["dense"],
        ["export"],
        ["run"],
        ["calibrate", "camera"],
        ["calibrate", "imu"],
        ["calibrate", "rig"],
    ],
    ids=lambda c: "-".join(c),
)
def test_help_imports_nothing_heavy(command: list[str]) -> None:
    code = f"""
import contextlib, io, json, sys
from postproc import cli
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        cli.main({[*command, "--help"]!r})
    except SystemExit:
        pass
assert "--help" in out.getvalue(), out.getvalue()
print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=False, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []


def test_depth_trajectory_formats_match_the_reader() -> None:
    """The depth options spell the reader's formats (the reader's module imports NumPy)."""
    from postproc.depth.options import DepthOptions
    from shared.formats.svin import TrajectoryFormat

    spelled = get_type_hints(DepthOptions)["trajectory_format"]
    assert get_args(spelled) == get_args(TrajectoryFormat)
