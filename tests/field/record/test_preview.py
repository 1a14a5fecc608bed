"""Preview pieces in-process: keys, thumbnails, the page's state, and connection errors."""

from __future__ import annotations

import json
import socket
import urllib.request
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from field.record.preview_bus import (
    PreviewOptions,
    PreviewPublisher,
    key_part,
    key_prefix,
    thumbnail_jpeg,
)
from field.record.preview_web import PreviewServer, PreviewServerOptions, PreviewState, serve
from field.record.sources.sim import SimOptions, clip_path
from shared.archive import ArchiveReader, CompressedVideo
from shared.errors import DeviceError


def test_keys_are_safe_chunks() -> None:
    assert key_part("dive 3/a*b$c#d?") == "dive_3_a_b_c_d"
    assert key_part("///") == "unnamed"
    assert key_prefix("boat-1", "2024-06-15T09:30") == "wreckmap/boat-1/2024-06-15T09_30"


def test_thumbnails_from_key_frames_and_jpeg(sim_options: dict[str, Any]) -> None:
    import cv2

    with ArchiveReader(clip_path(SimOptions(**sim_options))) as reader:
        packets = [m for _, _, m in reader.messages(["/cam0/video"])]
    assert all(isinstance(m, CompressedVideo) for m in packets)
    videos = cast("list[CompressedVideo]", packets)  # checked just above
    thumb = thumbnail_jpeg(videos[0].data, "h264", width_px=160, quality=70)
    assert thumb is not None
    jpeg, w, h = thumb
    assert (w, h) == (160, 100)
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    assert image.shape == (100, 160, 3) and image.std() > 5  # a real picture, not a flat one
    assert thumbnail_jpeg(videos[1].data, "h264", width_px=160, quality=70) is None  # P frame
    assert thumbnail_jpeg(b"garbage", "h264", width_px=160, quality=70) is None
    ok, still = cv2.imencode(".jpg", np.full((40, 60, 3), 128, np.uint8))
    assert ok
    assert thumbnail_jpeg(still.tobytes(), "jpeg", width_px=320, quality=70)[1:] == (30, 20)  # type: ignore[index]
    assert thumbnail_jpeg(b"\xff\xd8 not a jpeg", "jpeg", width_px=320, quality=70) is None


def test_page_state_ignores_malformed_samples() -> None:
    state = PreviewState()
    state.on_sample("wreckmap/r/s/cam0/thumb", b"\xff\xd8jpeg", b'{"stamp_ns": 5}')
    state.on_sample("wreckmap/r/s/cam0/thumb", b"\xff\xd8jpeg2", b"not json")
    state.on_sample("wreckmap/r/s/health", b"[1, 2]", None)
    state.on_sample("wreckmap/r/s/health", b"{bad", None)
    state.on_sample("other/r/s/health", b"{}", None)
    state.on_sample("wreckmap/r/s/imu0/summary", b'{"rate_hz": 400}', None)
    snapshot = state.snapshot()
    assert snapshot["frames"]["r/s/cam0"]["seq"] == 1 and state.frame("r/s/cam0") == b"\xff\xd8jpeg"
    assert snapshot["received"] == {"frame": 1, "imu": 1}
    assert snapshot["latest"]["r/s/imu0/summary"]["rate_hz"] == 400
    events = state.events_after(0, 0.0)
    assert [kind for _, kind, _ in events] == ["frame", "imu"]
    assert json.loads(events[1][2])["stream"] == "imu0/summary"
    assert state.events_after(state.version, 0.01) == []


def test_http_server_serves_the_page_and_frames(tools: Any) -> None:
    server = PreviewServer(PreviewServerOptions(connect=[], http_port=0))
    import threading

    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        server.state.on_sample("wreckmap/r/s/cam0/thumb", b"\xff\xd8x", b"{}")
        base = server.url
        with urllib.request.urlopen(base) as response:
            assert b"<canvas" in response.read()
        for path, kind in (("app.js", "javascript"), ("style.css", "css")):
            with urllib.request.urlopen(base + path) as response:
                assert kind in response.headers["Content-Type"]
        with urllib.request.urlopen(base + "frame/r/s/cam0.jpg") as response:
            assert response.read() == b"\xff\xd8x"
        with urllib.request.urlopen(base + "ack?frames=3") as response:
            assert response.status == 204
        with urllib.request.urlopen(base + "state") as response:
            assert json.loads(response.read())["frames_shown"] == 3
        for bad, code in (("frame/r/s/cam9.jpg", 404), ("nothing", 404), ("ack?frames=x", 400)):
            with pytest.raises(urllib.error.HTTPError) as error:
                urllib.request.urlopen(base + bad)
            assert error.value.code == code
    finally:
        server.close()


def test_connection_errors_are_device_errors(tools: Any, tmp_path: Path) -> None:
    port = tools.free_port()
    first = PreviewPublisher(PreviewOptions(listen=[f"tcp/127.0.0.1:{port}"]), rig="r", session="s")
    first.start()
    try:
        second = PreviewPublisher(
            PreviewOptions(listen=[f"tcp/127.0.0.1:{port}"]), rig="r", session="s"
        )
        with pytest.raises(DeviceError, match="cannot open zenoh"):
            second.start()
    finally:
        first.close()
    nobody = PreviewServer(
        PreviewServerOptions(
            connect=[f"tcp/127.0.0.1:{tools.free_port()}"], http_port=0, connect_timeout_s=1.0
        )
    )
    try:
        with pytest.raises(DeviceError, match="cannot connect"):
            nobody.start()
    finally:
        nobody.close()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        with pytest.raises(DeviceError, match="cannot serve on"):
            serve(
                PreviewServerOptions(
                    connect=["tcp/127.0.0.1:1"], http_port=taken, connect_timeout_s=0.5
                )
            )
