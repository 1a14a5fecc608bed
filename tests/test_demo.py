"""`make demo`, reduced (a short, low-resolution survey), as a real subprocess.

Runs bench/demo.py end to end: the survey simulator, the simulated Shearwater downloaded
over a pseudo-terminal, the GoPro import through the pipeline, every stage, the summary.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow(seconds=180)
@pytest.mark.timeout(3700)
def test_reduced_demo(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    env = {**os.environ, "WRECKMAP_PROGRESS": "0", "PYTHONPATH": str(REPO)}
    command = [
        sys.executable, str(REPO / "bench" / "demo.py"), "--out", str(out),
        "--duration", "60", "--width", "480", "--height", "270", "--fps", "10",
        "--dense-image-px", "160", "--depth-min-range-m", "0.2",
    ]  # fmt: skip
    # Its own process group, so that a timeout stops the simulator and the pipeline too.
    # 480x270 keeps every stage's path (a 45 s dive is too short for the depth sync) at
    # two thirds of the 640x360 cost. The limit is a hang guard, never a speed check: the
    # 60 s dives take about 4 minutes quiet, 6 with the rest of the suite beside them (the
    # 90 s ones of `make demo` at 960x540: 4 quiet, 9 at load 9); under `nice` at load 11
    # the simulation alone ran 7x slower than quiet; an hour (20x) means something is stuck.
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True,
    )  # fmt: skip
    try:
        stdout, stderr = process.communicate(timeout=3600)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        stdout, stderr = process.communicate()
        pytest.fail(f"the reduced demo did not end within 3600 s:\n{stdout[-3000:]}")
    result = subprocess.CompletedProcess(command, process.returncode, stdout, stderr)
    log = result.stdout + result.stderr
    # The real intake paths ran: the dive computer over a pty, the GoPro import.
    assert (out / "dives" / "dives.json").is_file(), log
    assert (out / "run" / "imports" / "dive1" / "session.yaml").is_file(), log
    assert (out / "run" / "imports" / "dive2" / "recording.mcap").is_file(), log
    # The summary lists every stage of both sessions with a status.
    for stage, session in [("import", "dive1"), ("slam", "dive2"), ("depth", "dive1")]:
        assert re.search(rf"^{stage}\s+{session}\s+\S+", result.stdout, re.M), log
    for stage in ("merge", "sfm", "dense"):
        assert re.search(rf"^{stage}\s+-\s+\S+", result.stdout, re.M), log
    report = out / "run" / "report.html"
    assert f"report: {report}" in result.stdout and report.is_file()
    text = report.read_text()
    assert "http://" not in text and "https://" not in text
    assert "Errors against truth" in text
    # Exit 0 exactly when nothing failed.
    failed = re.findall(r"^(\S+)\s+(\S+)\s+(failed/not run|exit \d+)", result.stdout, re.M)
    assert (result.returncode == 0) == (not failed), log
    assert result.returncode == 0, f"stages failed: {failed}\n{log[-4000:]}"
