"""A camera unplugged while the IMU flows, and a laptop clock that steps forward then back,
during one recording of the simulated rig: the archive stays monotonic, the gap and the
steps are on /health, and `inspect` reports them."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from field.record.hostclock import HOST_CLOCK
from field.record.inspect import format_report, inspect_file
from field.record.recorder import Recorder, RecorderOptions
from field.record.sources.base import make_source
from shared.archive import HEALTH_TOPIC, ArchiveReader, iter_records_salvage

FORWARD_S = 3600.0  # the laptop finds GPS: one hour forward
BACK_S = -30.0  # then NTP pulls it back to 30 s behind


def _stepping_wall_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    real = time.time_ns
    start = real()

    def wall_ns() -> int:
        now = real()
        elapsed_s = (now - start) * 1e-9
        if elapsed_s < 1.2:
            return now
        return now + round((FORWARD_S if elapsed_s < 2.4 else BACK_S) * 1e9)

    monkeypatch.setattr(time, "time_ns", wall_ns)


def test_clock_steps_and_a_camera_gap_are_recorded_not_followed(
    tmp_path: Path, sim_options: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    source = make_source(
        "sim", {**sim_options, "camera_unplug_at_s": 0.8, "camera_unplug_for_s": 1.5}
    )
    options = RecorderOptions(duration_s=4.0, health_interval_s=0.2, min_free_mb=0.0)
    # This process's host time may already be off the wall clock (the machine's clock
    # stepped since the process started): the recorded mapping includes that.
    before_s = HOST_CLOCK.wall_minus_host_ns() * 1e-9
    _stepping_wall_clock(monkeypatch)
    report = Recorder(options, [source], tmp_path / "s").run()
    monkeypatch.undo()
    assert report.clean
    (path,) = report.files

    # Log times in file order never go backwards, and span the recording, not an hour.
    log_times = np.array([r.log_time_ns for r in iter_records_salvage(path)], dtype=np.int64)
    assert np.all(np.diff(log_times) >= 0)
    assert (log_times[-1] - log_times[0]) * 1e-9 < 10
    with ArchiveReader(path) as reader:
        imu = reader.read_imu("/imu0").stamps_ns
        video = np.array([m.stamp_ns for _, _, m in reader.messages(["/cam0/video"])])
    steps_s = np.diff(imu) * 1e-9
    assert steps_s.min() > 0 and steps_s.max() < 3 / 400  # the IMU went on, unbroken
    assert 1.2 < np.diff(video).max() * 1e-9 < 1.9  # the camera's outage

    inspected = inspect_file(path)
    steps = [e.details["step_s"] for e in inspected.clock_steps]
    assert steps == pytest.approx([FORWARD_S, BACK_S - FORWARD_S], abs=0.1)
    gaps = {e.source: e.details["gap_s"] for e in inspected.source_gaps}
    assert set(gaps) == {"/cam0/video"} and 1.2 < gaps["/cam0/video"] < 1.9
    lost = [e for e in inspected.events if e.kind == "source_lost"]
    assert [e.source for e in lost] == ["/cam0/video"]
    text = format_report(inspected)
    assert "clock step: host wall clock +3600.0" in text
    assert "gap: /cam0/video back after" in text
    assert HEALTH_TOPIC not in {t.topic for t in inspected.topics}

    # session.yaml keeps the mapping after each step.
    import yaml

    doc = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    mapping = [s["wall_minus_host_s"] - before_s for s in doc["clock_steps"]]
    assert mapping == pytest.approx([FORWARD_S, BACK_S], abs=0.5)


def test_inspect_cli_prints_the_gap_of_an_unplugged_device(
    tmp_path: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    out = tmp_path / "dive"
    options = {**sim_options, "device_lost_at_s": 1.0, "device_lost_for_s": 0.8}
    run = subprocess.run(
        tools.cli(
            "record", "--source", "sim", "--out", str(out), "--duration", "3",
            *tools.sim_args(options),
        ),
        capture_output=True, text=True, env=tools.env(), timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    shown = subprocess.run(
        tools.cli("inspect", str(out)), capture_output=True, text=True, env=tools.env(), timeout=60
    )
    assert shown.returncode == 0, shown.stderr
    assert "lost: sim at" in shown.stdout
    (line,) = [ln for ln in shown.stdout.splitlines() if ln.startswith("gap: sim back after")]
    assert 0.6 < float(line.split("after ")[1].split(" s")[0]) < 1.4
