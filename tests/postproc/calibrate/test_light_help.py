"""`wreckmap-post calibrate camera|imu|rig --help` builds its flags from the light options
modules: no NumPy, OpenCV or GTSAM is imported to print help."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ["numpy", "cv2", "gtsam", "scipy"]


@pytest.mark.parametrize("command", ["camera", "imu", "rig"])
def test_calibrate_help_imports_no_numpy(command: str) -> None:
    code = f"""
import contextlib, io, json, sys
from postproc import cli
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        cli.main(["calibrate", {command!r}, "--help"])
    except SystemExit:
        pass
assert "--help" in out.getvalue(), out.getvalue()
print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=False, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []
