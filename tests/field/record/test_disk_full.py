"""A full card while recording, on a real, size-limited file system (tmpfs mounted here).

Two behaviours: with the free-space watermark the recorder stops before the disk is full
and closes its file cleanly (exit status 3); with the watermark off the write fails with
ENOSPC mid-chunk, and `recover` restores what was fsynced before (at most about a flush
interval, 0.5 s, plus the chunk being written is lost).
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shared.archive import ArchiveReader

IMU_RATE_HZ = 400.0  # the small rig's IMU (tests/field/record/conftest.py)


def _mount_tmpfs(folder: Path, size_kib: int) -> Iterator[Path]:
    folder.mkdir(parents=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a size-limited tmpfs needs root (CI runs as root)")
    subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kib}k,mode=0755", "tmpfs", str(folder)],
        check=True,
    )
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.fixture
def small_disk(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Path]:
    yield from _mount_tmpfs(tmp_path / "card", int(request.param))


def _record(tools: Any, sim_options: dict[str, Any], out: Path, *extra: str) -> Any:
    return subprocess.run(
        tools.cli(
            "record",
            "--source",
            "sim",
            "--out",
            str(out),
            "--duration",
            "120",
            *tools.sim_args(sim_options),
            *extra,
        ),
        capture_output=True,
        text=True,
        env=tools.env(),
        timeout=300,  # hang guard: the card fills in a few seconds
    )


def _reported_count(stdout: str, topic: str) -> int:
    match = re.search(rf"^\s+{re.escape(topic)}: (\d+)", stdout, re.MULTILINE)
    assert match, stdout
    return int(match.group(1))


@pytest.mark.parametrize("small_disk", [1536], indirect=True)
def test_watermark_stops_cleanly_before_the_card_is_full(
    small_disk: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    out = small_disk / "dive"
    run = _record(tools, sim_options, out, "--min-free-mb", "1")
    assert run.returncode == 3, run.stderr
    assert "stopped: disk nearly full" in run.stdout
    assert "the disk is full" in run.stdout
    assert "disk nearly full" in run.stderr  # the log says it too
    files = sorted(out.glob("recording_*.mcap"))
    assert files and not list(out.glob("*.part"))
    written = 0
    for path in files:
        with ArchiveReader(path) as reader:
            assert reader.indexed
            written += reader.topics()["/imu0"].message_count
    # Every message the recorder counted is in the closed files.
    assert written == _reported_count(run.stdout, "/imu0") > IMU_RATE_HZ


@pytest.mark.parametrize("small_disk", [768], indirect=True)
def test_enospc_without_watermark_leaves_a_recoverable_file(
    small_disk: Path, tmp_path: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    out = small_disk / "dive"
    run = _record(tools, sim_options, out, "--min-free-mb", "0")
    assert "stopped: disk full" in run.stdout, run.stdout + run.stderr
    reported = _reported_count(run.stdout, "/imu0")
    parts = list(out.glob("*.part"))
    if parts:
        # The usual case: no room left for the footer. Recover it elsewhere (the lab).
        assert run.returncode == 2 and "wreckmap-field recover" in run.stdout
        recovered = tmp_path / "recovered.mcap"
        rec = subprocess.run(
            tools.cli("recover", str(parts[0]), "--out", str(recovered)),
            capture_output=True,
            text=True,
            env=tools.env(),
            timeout=120,
        )
        assert rec.returncode == 0, rec.stderr
        path = recovered
    else:
        assert run.returncode == 3
        path = sorted(out.glob("recording_*.mcap"))[-1]
    with ArchiveReader(path) as reader:
        assert reader.indexed
        stamps = reader.read_imu("/imu0").stamps_ns
    # Up to the last complete chunk: contiguous samples, no hole, and what is missing
    # is at most the last flush interval plus the chunk that hit the full disk.
    steps_s = np.diff(stamps) * 1e-9
    assert steps_s.max() < 3 / IMU_RATE_HZ
    lost_s = (reported - len(stamps)) / IMU_RATE_HZ
    assert 0 <= lost_s <= 1.0, (reported, len(stamps))
    assert len(stamps) > IMU_RATE_HZ
