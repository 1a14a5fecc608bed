"""The recorder and the preview as real subprocesses against the simulated rig."""

from __future__ import annotations

import inspect
import json
import random
import re
import shutil
import signal
import subprocess
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import yaml

import field.record.preview_bus as preview_bus
from field.record.recover import recover
from shared.archive import ArchiveReader


def _start_recorder(
    tools: Any, sim_options: dict[str, Any], out: Path, *extra: str
) -> subprocess.Popen[str]:
    return subprocess.Popen(
        tools.cli(
            "record", "--source", "sim", "--out", str(out), *tools.sim_args(sim_options), *extra
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=tools.env(),
    )


def _wait_for(predicate: Any, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM])
def test_record_stops_cleanly_on_signal(
    tmp_path: Path, tools: Any, sim_options: dict[str, Any], stop_signal: signal.Signals
) -> None:
    out = tmp_path / "dive"
    proc = _start_recorder(tools, sim_options, out, "--duration", "30")
    part = out / "recording_000.mcap.part"
    _wait_for(part.exists, 30, "the recording to start")
    time.sleep(1.5)
    proc.send_signal(stop_signal)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert f"stopped: signal {stop_signal.name}" in stdout
    assert not part.exists()
    doc = yaml.safe_load((out / "session.yaml").read_text())
    assert doc["recordings"] == ["recording_000.mcap"] and doc["clean"] is True
    assert (out / "calib" / "camchain.yaml").is_file() and (out / "calib" / "imu.yaml").is_file()
    with ArchiveReader(out / "recording_000.mcap") as reader:
        assert reader.indexed
        topics = reader.topics()
        assert set(topics) == {"/cam0/video", "/imu0", "/depth0", "/session"}
        stamps = reader.read_imu("/imu0").stamps_ns
        span_s = (stamps[-1] - stamps[0]) * 1e-9
        assert 1.2 < span_s < 3.5
        # Every IMU sample over the span is there (device clock: 2.5 ms steps).
        assert topics["/imu0"].message_count == round(400 * span_s / (1 + 25e-6)) + 1
        assert topics["/cam0/video"].message_count == pytest.approx(15 * span_s, abs=2)


def test_record_from_a_cold_cache_starts_and_stops_on_sigterm(tmp_path: Path, tools: Any) -> None:
    """The way a user starts it: no rendered clip yet, so the recorder builds the scene
    (a forked pool) after its SIGTERM handler is installed. It used to hang for good in
    `Pool.terminate` because the workers inherited that handler."""
    from tests.field.record.conftest import SMALL_SIM

    out = tmp_path / "dive"
    env = {**tools.env(), "WRECKMAP_CACHE": str(tmp_path / "empty-cache")}
    proc = subprocess.Popen(
        tools.cli(
            "record",
            "--source",
            "sim",
            "--out",
            str(out),
            "--duration",
            "30",
            *tools.sim_args(SMALL_SIM),
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    part = out / "recording_000.mcap.part"
    try:
        # A hang guard, many times the normal start (a few seconds to render the clip).
        _wait_for(lambda: part.exists() or proc.poll() is not None, 240, "the first archive")
        assert proc.poll() is None, proc.communicate()[1]
        assert list((tmp_path / "empty-cache").glob("sim-clip-*.mcap"))
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert "stopped: signal SIGTERM" in stdout
    assert (out / "recording_000.mcap").is_file() and not part.exists()


def _kill_trial(
    tools: Any, sim_options: dict[str, Any], out: Path, delay_s: float
) -> dict[str, Any]:
    proc = _start_recorder(tools, sim_options, out, "--duration", "10")
    part = out / "recording_000.mcap.part"
    try:
        _wait_for(lambda: part.exists() and part.stat().st_size > 0, 60, "the recording to start")
        time.sleep(delay_s)
        killed_ns = time.time_ns()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
    report = recover(part)
    with ArchiveReader(report.output) as reader:
        assert reader.indexed
        imu = reader.read_imu("/imu0") if "/imu0" in reader.topics() else None
    return {"delay_s": delay_s, "killed_ns": killed_ns, "report": report, "imu": imu}


@pytest.mark.slow
def test_sigkill_at_random_moments_loses_at_most_one_second(
    tmp_path: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    rng = random.Random(20240615)
    delays = [rng.uniform(0.05, 3.0) for _ in range(20)]
    results: list[dict[str, Any]] = []
    errors: list[BaseException] = []

    def worker(indices: list[int]) -> None:
        for i in indices:
            try:
                results.append(
                    _kill_trial(tools, sim_options, tmp_path / f"trial{i:02d}", delays[i])
                )
            except BaseException as error:  # collected and re-raised in the test thread
                errors.append(error)

    # Three recorders at a time keep the wall time down on a small machine.
    threads = [threading.Thread(target=worker, args=(list(range(k, 20, 3)),)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    assert len(results) == 20
    for r in results:
        report = r["report"]
        lost_s = (r["killed_ns"] - report.last_ns) * 1e-9
        assert lost_s <= 1.0, f"killed {r['delay_s']:.2f} s in: lost {lost_s:.2f} s"
        if r["delay_s"] > 0.8:
            imu = r["imu"]
            assert imu is not None
            # No hole inside what was kept: 400 Hz all along.
            assert np.max(np.diff(imu.stamps_ns)) < 5_000_000
            assert {"/cam0/video", "/depth0", "/imu0"} <= set(report.messages)


def _zenoh_client(port: int, host: str = "127.0.0.1") -> Any:
    import zenoh

    return zenoh.open(
        preview_bus.zenoh_config(listen=[], connect=[f"tcp/{host}:{port}"], mode="client")
    )


def test_preview_publishes_and_ignores_peers(
    tmp_path: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    port = tools.free_port()
    out = tmp_path / "dive7"
    proc = _start_recorder(
        tools,
        sim_options,
        out,
        "--duration",
        "5",
        "--rig",
        "boat",
        "--preview",
        f"tcp/127.0.0.1:{port}",
        "--preview-lan",
        "127.0.0.2",
    )
    received: dict[str, list[tuple[bytes, bytes | None]]] = {}

    def on_sample(sample: Any) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        received.setdefault(str(sample.key_expr), []).append(
            (sample.payload.to_bytes(), attachment)
        )

    try:
        _wait_for((out / "recording_000.mcap.part").exists, 30, "the recording to start")
        # The viewer comes in through the "LAN" listener (--preview-lan; 127.0.0.2 is on lo).
        viewer = _zenoh_client(port, "127.0.0.2")
        viewer.declare_subscriber("wreckmap/**", on_sample)
        # A peer that publishes on the recorder's own keys, and on would-be control keys.
        intruder = _zenoh_client(port)
        prefix = "wreckmap/boat/dive7"
        for _ in range(40):
            intruder.put(f"{prefix}/health", b'{"stop": true}')
            intruder.put(f"{prefix}/control/stop", b"1")
            intruder.put(f"{prefix}/cam0/thumb", b"not a jpeg")
            intruder.put(f"{prefix}/recorder/duration_s", b"0.1")
            time.sleep(0.05)
        _wait_for(
            lambda: f"{prefix}/cam0/thumb" in received and f"{prefix}/imu0/summary" in received,
            20,
            "preview",
        )
        stdout, stderr = proc.communicate(timeout=30)
        intruder.close()
        viewer.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert "stopped: duration reached" in stdout and "dropped" in stdout
    doc = yaml.safe_load((out / "session.yaml").read_text())
    assert doc["stop_reason"] == "duration reached" and doc["dropped"] == {} and doc["events"] == []
    with ArchiveReader(out / "recording_000.mcap") as reader:
        imu = reader.read_imu("/imu0")
    span_s = (imu.stamps_ns[-1] - imu.stamps_ns[0]) * 1e-9
    assert span_s > 4.5 and np.max(np.diff(imu.stamps_ns)) < 5_000_000
    # What the recorder published: real JPEG thumbnails with their stamps, IMU, depth, health.
    import cv2

    thumbs = [(p, a) for p, a in received[f"{prefix}/cam0/thumb"] if a is not None]
    assert len(thumbs) >= 3
    image = cv2.imdecode(np.frombuffer(thumbs[-1][0], np.uint8), cv2.IMREAD_COLOR)
    info = json.loads(thumbs[-1][1] or b"{}")
    assert image is not None and image.shape == (info["height"], info["width"], 3) == (200, 320, 3)
    summary = json.loads(received[f"{prefix}/imu0/summary"][-1][0])
    assert summary["rate_hz"] == pytest.approx(400, rel=0.05)
    assert np.linalg.norm(summary["accel_m_s2"], axis=1).mean() == pytest.approx(9.8, abs=0.7)
    assert json.loads(received[f"{prefix}/depth0"][-1][0])["depth_m"] > 0
    health = [json.loads(p) for p, _ in received[f"{prefix}/health"] if p.startswith(b'{"t_ns"')]
    assert health and health[-1]["topics"]["/imu0"]["rate_hz"] == pytest.approx(400, rel=0.1)
    assert health[-1]["disk_free_bytes"] > 0 and health[-1]["sources"] == {"sim": "up"}


def test_recorder_session_only_publishes() -> None:
    """Read-only by construction: the recorder's zenoh code declares nothing that receives."""
    source = inspect.getsource(preview_bus)
    for receiving in ("declare_subscriber", "declare_queryable", ".get(", "liveliness"):
        assert receiving not in source.replace("self._imu.get(", "").replace(
            "self._publishers.get(", ""
        ).replace("self._last_frame_ns.get(", ""), receiving


def test_web_preview_in_headless_chromium(
    tmp_path: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.fail(
            "chromium is not installed (it is in deploy/system-packages.txt; run deploy/setup.sh)"
        )
    # Every asset is local: no URL to another host in the page.
    web = Path(preview_bus.__file__).parent / "web"
    for asset in web.iterdir():
        assert not re.search(r"(https?:)?//[a-z0-9]", asset.read_text().replace("// ", "")), asset
    zport, hport = tools.free_port(), tools.free_port()
    out = tmp_path / "dive9"
    recorder = _start_recorder(
        tools, sim_options, out, "--duration", "20", "--preview", f"tcp/127.0.0.1:{zport}"
    )
    page = subprocess.Popen(
        tools.cli("preview", "--connect", f"tcp/127.0.0.1:{zport}", "--http", f"127.0.0.1:{hport}"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=tools.env(),
    )
    browser = None
    profile = tempfile.mkdtemp(dir=tmp_path)
    base = f"http://127.0.0.1:{hport}"

    def state() -> dict[str, Any]:
        with urllib.request.urlopen(base + "/state", timeout=2) as response:
            return cast("dict[str, Any]", json.loads(response.read()))

    def page_up() -> bool:
        for proc, name in ((recorder, "recorder"), (page, "preview")):
            if proc.poll() is not None:
                raise AssertionError(f"the {name} exited: {proc.communicate()[1][-2000:]}")
        try:
            return bool(state()["frames"])
        except OSError:
            return False

    try:
        _wait_for(page_up, 40, "the preview server to receive a frame")
        with urllib.request.urlopen(base + "/", timeout=2) as response:
            html = response.read().decode()
        assert "<canvas" in html and "/app.js" in html
        browser = subprocess.Popen(
            [
                chromium,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                f"--user-data-dir={profile}",
                base + "/",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        # The page reports each frame it displayed (img onload -> GET /ack?frames=N).
        _wait_for(lambda: state()["frames_shown"] >= 2, 30, "the page to show frames")
        snapshot = state()
        assert snapshot["received"]["frame"] >= 2 and snapshot["received"]["imu"] >= 2
    finally:
        for proc in (browser, page, recorder):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in (browser, page, recorder):
            if proc is not None:
                try:
                    proc.communicate(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.communicate()
    assert page.returncode == 0, page.stderr
    assert recorder.returncode == 0
    assert (out / "recording_000.mcap").is_file()


def test_unplugged_device_is_logged_and_recording_resumes(
    tmp_path: Path, tools: Any, sim_options: dict[str, Any]
) -> None:
    out = tmp_path / "dive3"
    options = {**sim_options, "device_lost_at_s": 1.0, "device_lost_for_s": 0.8}
    proc = _start_recorder(tools, options, out, "--duration", "3")
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    assert "sim: lost" in stderr and "sim: reconnected" in stderr
    doc = yaml.safe_load((out / "session.yaml").read_text())
    assert any("reconnected" in e for e in doc["events"])
    run = subprocess.run(
        tools.cli("inspect", str(out / "recording_000.mcap"), "--json"),
        capture_output=True,
        text=True,
        env=tools.env(),
        timeout=60,
        check=True,
    )
    topics = {t["topic"]: t for t in json.loads(run.stdout)[0]["topics"]}
    for topic in ("/imu0", "/cam0/video"):
        (gap,) = topics[topic]["gaps"]  # the outage, and only it
        assert 0.7 < gap["length_s"] < 1.3
    assert topics["/imu0"]["rate_hz"] == pytest.approx(400 * (1 + 25e-6) * 0.7, rel=0.2)


@pytest.mark.hardware
def test_record_from_a_real_oak(tmp_path: Path, tools: Any) -> None:
    out = tmp_path / "oak"
    run = subprocess.run(
        tools.cli("record", "--source", "oak", "--out", str(out), "--duration", "5"),
        capture_output=True,
        text=True,
        env=tools.env(),
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    with ArchiveReader(out / "recording_000.mcap") as reader:
        topics = reader.topics()
    assert topics["/imu0"].message_count > 5 * 300
    assert topics["/cam0/video"].message_count > 5 * 25
