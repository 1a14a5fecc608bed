"""recover (truncated / damaged archives) and inspect (rates, gaps, clocks), library and CLI."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from field.record.inspect import format_report, inspect_path
from field.record.recover import default_output, recover, recover_path
from shared.archive import ArchiveReader, ArchiveWriter, DepthSample, Imu, part_path
from shared.errors import InputError, OutputExistsError

T0 = 1_700_000_000_000_000_000


def _write_crashed(path: Path, *, seconds: float, flush_every_s: float = 0.5) -> Path:
    """An archive like a recorder's: 200 Hz IMU, flushed every 0.5 s, never closed."""
    writer = ArchiveWriter(path, chunk_size=1 << 30, metadata={"session_id": "crash"})
    n = round(seconds * 200)
    for k in range(n):
        stamp = T0 + k * 5_000_000
        writer.write(
            "/imu0",
            Imu(stamp, "imu0", np.array([k, 0.0, 0.0]), np.array([0.0, 0.0, 9.81])),
            log_time_ns=stamp + 2_000_000,
        )
        if (k + 1) % round(flush_every_s * 200) == 0:
            writer.flush()
    # Simulate SIGKILL: the chunk in progress never reaches the file; no summary.
    writer._file.close()
    return part_path(path)


def test_recover_keeps_everything_flushed_and_indexes_it(tmp_path: Path) -> None:
    part = _write_crashed(tmp_path / "recording_000.mcap", seconds=2.3)
    with pytest.raises(InputError):
        ArchiveReader(part)  # not readable as a complete file
    report = recover(part)
    assert report.output == tmp_path / "recording_000.mcap" == default_output(part)
    assert report.messages == {"/imu0": 400}  # 4 flushes of 100; the last 0.3 s was in memory
    assert "400 messages recovered" in report.summary()
    with ArchiveReader(report.output) as reader:
        assert reader.indexed
        series = reader.read_imu("/imu0")
        assert reader.metadata()["wreckmap_session"]["session_id"] == "crash"
    np.testing.assert_array_equal(series.gyro_rad_s[:, 0], np.arange(400))
    np.testing.assert_array_equal(series.log_times_ns - series.stamps_ns, 2_000_000)
    assert part.is_file()  # the input is kept
    with pytest.raises(OutputExistsError):
        recover(part)
    assert recover(part, overwrite=True).messages == {"/imu0": 400}


@pytest.mark.parametrize("cut_fraction", [0.35, 0.6, 0.97])
def test_recover_a_file_cut_anywhere(tmp_path: Path, cut_fraction: float) -> None:
    part = _write_crashed(tmp_path / "r.mcap", seconds=3.0)
    data = part.read_bytes()
    part.write_bytes(data[: int(len(data) * cut_fraction)])  # power loss mid-write
    report = recover(part, tmp_path / "out.mcap")
    count = report.messages["/imu0"]
    # Whole flushed chunks survive: a multiple of 100 samples, at most one chunk lost.
    assert count % 100 == 0 and count >= 100 * int(cut_fraction * 6) - 100
    assert report.skipped_bytes > 0 and report.warnings


def test_recover_errors_and_folders(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        recover(tmp_path / "missing.mcap.part")
    empty = tmp_path / "empty.mcap"
    writer = ArchiveWriter(empty)
    writer._file.close()
    with pytest.raises(InputError, match="nothing to recover"):
        recover(part_path(empty))
    assert not list(tmp_path.glob("*.tmp*")), "no stray temporary after a failed recovery"
    (tmp_path / "not.mcap.part").write_bytes(b"hello")
    with pytest.raises(InputError):
        recover(tmp_path / "not.mcap.part")
    session = tmp_path / "session"
    session.mkdir()
    with pytest.raises(InputError, match=r"no \.mcap\.part"):
        recover_path(session)
    _write_crashed(session / "recording_000.mcap", seconds=1.0)
    _write_crashed(session / "recording_001.mcap", seconds=1.0)
    reports = recover_path(session)
    assert [r.output.name for r in reports] == ["recording_000.mcap", "recording_001.mcap"]
    with pytest.raises(InputError, match="single file"):
        recover_path(session, out=tmp_path / "x.mcap")
    with pytest.raises(InputError, match="replace the input"):
        recover(reports[0].output, reports[0].output)


def _write_inspectable(path: Path) -> None:
    """IMU at 200 Hz with a 0.5 s gap, device clock 40 ppm slow; depth at 1 Hz."""
    with ArchiveWriter(path) as writer:
        for k in range(2000):  # 10 s
            if 600 <= k < 700:
                continue  # a 0.5 s gap
            stamp = T0 + k * 5_000_000
            log_time = stamp + 3_000_000 + round(40e-6 * (stamp - T0))
            writer.write(
                "/imu0", Imu(stamp, "imu0", np.zeros(3), np.zeros(3)), log_time_ns=log_time
            )
        for k in range(10):
            stamp = T0 + k * 1_000_000_000
            writer.write(
                "/depth0",
                DepthSample(stamp, "depth0", depth_m=12.0),
                log_time_ns=stamp + 10_000_000,
            )


def test_inspect_rates_gaps_and_clock(tmp_path: Path) -> None:
    path = tmp_path / "recording_000.mcap"
    _write_inspectable(path)
    (report,) = inspect_path(path)
    assert report.complete and report.indexed
    imu = {t.topic: t for t in report.topics}["/imu0"]
    assert imu.count == 1900
    assert imu.period_s == pytest.approx(0.005)
    assert [round(g.length_s, 3) for g in imu.gaps] == [0.505]
    assert imu.gaps[0].after_ns == T0 + 599 * 5_000_000
    assert imu.latency_mean_ms == pytest.approx(3.2, abs=0.2)
    assert imu.clock_drift_ppm == pytest.approx(40.0, abs=0.01)
    depth = {t.topic: t for t in report.topics}["/depth0"]
    assert depth.rate_hz == pytest.approx(1.0) and depth.gaps == []
    text = format_report(report)
    assert "complete, indexed" in text and "/imu0" in text
    with pytest.raises(InputError, match="no such file"):
        inspect_path(tmp_path / "nothing.mcap")
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(InputError, match=r"no \.mcap recording"):
        inspect_path(tmp_path / "empty_dir")


def test_recover_and_inspect_clis(tmp_path: Path, tools: Any) -> None:
    part = _write_crashed(tmp_path / "recording_000.mcap", seconds=1.2)
    run = subprocess.run(
        tools.cli("recover", str(tmp_path)),
        capture_output=True,
        text=True,
        env=tools.env(),
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    assert "200 messages recovered from recording_000.mcap.part" in run.stdout
    run = subprocess.run(
        tools.cli("inspect", str(tmp_path), "--json"),
        capture_output=True,
        text=True,
        env=tools.env(),
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    reports = json.loads(run.stdout)
    # The folder holds the recovered file and the kept .part (marked incomplete).
    assert [(Path(r["path"]).name, r["complete"]) for r in reports] == [
        ("recording_000.mcap", True),
        (part.name, False),
    ]
    assert reports[0]["topics"][0]["count"] == 200
    run = subprocess.run(
        tools.cli("recover", str(tmp_path / "nope.mcap.part")),
        capture_output=True,
        text=True,
        env=tools.env(),
        timeout=60,
    )
    assert run.returncode == 1 and "error: " in run.stderr and "no such file" in run.stderr
