"""The boat's preview page: a local web server fed by the recorder's zenoh preview.

`wreckmap-field preview --connect tcp/127.0.0.1:7447` subscribes to `wreckmap/**` (read
only: it publishes nothing) and serves, from the standard library's http.server:

| path                              | what                                              |
|-----------------------------------|---------------------------------------------------|
| `/`, `/app.js`, `/style.css`      | the page (field/record/web/, no external asset)   |
| `/events`                         | server-sent events: frame, imu, depth, health     |
| `/frame/<rig>/<session>/<cam>.jpg`| the latest thumbnail of that camera               |
| `/state`                          | JSON snapshot (what is known now, for scripts)    |
| `/ack?frames=N`                   | the page reports N frames displayed (self-check)  |

No internet is needed on the boat: every asset is served from the package.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs

from field.record.preview_bus import zenoh_config
from shared.errors import DeviceError

log = logging.getLogger(__name__)

STATIC = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/app.js": ("app.js", "text/javascript; charset=utf-8"),
    "/style.css": ("style.css", "text/css; charset=utf-8"),
}
SSE_KEEPALIVE_S = 10.0


@dataclass(kw_only=True)
class PreviewServerOptions:
    """connect: the recorder's zenoh endpoints; http_host, http_port: where the page is
    served (loopback by default); key_expr: what to subscribe to; zenoh_config_file: a
    zenoh JSON5 config (TLS, access control); connect_timeout_s: how long to keep trying
    while the recorder is not up yet (the page is often opened before the recording starts)."""

    connect: list[str]
    http_host: str = "127.0.0.1"
    http_port: int = 8090
    key_expr: str = "wreckmap/**"
    zenoh_config_file: str | None = None
    connect_timeout_s: float = 30.0


class PreviewState:
    """What the page shows, updated from zenoh samples; a bounded log of events for SSE."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.version = 0
        self._events: collections.deque[tuple[int, str, str]] = collections.deque(maxlen=256)
        self.frames: dict[str, tuple[bytes, dict[str, Any]]] = {}
        self.latest: dict[str, dict[str, Any]] = {}
        self.received: collections.Counter[str] = collections.Counter()
        self.frames_shown = 0
        """Highest frame count a page reported as displayed (GET /ack?frames=N)."""

    def on_sample(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        """One zenoh sample on `wreckmap/<rig>/<session>/<stream...>`."""
        parts = key.split("/")
        if len(parts) < 4 or parts[0] != "wreckmap":
            return
        session = "/".join(parts[1:3])
        stream = "/".join(parts[3:])
        try:
            if stream.endswith("/thumb"):
                camera = stream.split("/")[0]
                info = json.loads(attachment) if attachment else {}
                with self._cond:
                    seq = self.frames.get(f"{session}/{camera}", (b"", {"seq": 0}))[1]["seq"] + 1
                    info.update({"seq": seq, "session": session, "camera": camera})
                    self.frames[f"{session}/{camera}"] = (payload, info)
                self._push("frame", info)
                kind = "frame"
            else:
                data = json.loads(payload)
                if not isinstance(data, dict):
                    return
                data["session"] = session
                data["stream"] = stream
                kind = (
                    "health" if stream == "health" else "imu" if "/summary" in stream else "depth"
                )
                with self._cond:
                    self.latest[f"{session}/{stream}"] = data
                self._push(kind, data)
        except (ValueError, UnicodeDecodeError, KeyError, TypeError):
            log.debug("preview: ignoring malformed sample on %s", key)
            return
        self.received[kind] += 1

    def _push(self, kind: str, data: dict[str, Any]) -> None:
        text = json.dumps(data)
        with self._cond:
            self.version += 1
            self._events.append((self.version, kind, text))
            self._cond.notify_all()

    def events_after(self, version: int, timeout_s: float) -> list[tuple[int, str, str]]:
        """Events newer than `version`, waiting up to `timeout_s` for one."""
        with self._cond:
            if self.version <= version:
                self._cond.wait(timeout_s)
            return [e for e in self._events if e[0] > version]

    def snapshot(self) -> dict[str, Any]:
        with self._cond:
            return {
                "frames": {k: info for k, (_, info) in self.frames.items()},
                "latest": dict(self.latest),
                "received": dict(self.received),
                "frames_shown": self.frames_shown,
            }

    def ack(self, frames: int) -> None:
        with self._cond:
            self.frames_shown = max(self.frames_shown, frames)

    def frame(self, name: str) -> bytes | None:
        with self._cond:
            entry = self.frames.get(name)
            return None if entry is None else entry[0]


def _make_handler(state: PreviewState) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "wreckmap-preview"

        def log_message(self, format: str, *args: Any) -> None:
            log.debug("http: " + format, *args)

        def _send(self, status: int, body: bytes, content_type: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:
            path = self.path.split("?", 1)[0]
            if path in STATIC:
                name, content_type = STATIC[path]
                body = resources.files("field.record").joinpath("web", name).read_bytes()
                self._send(HTTPStatus.OK, body, content_type)
            elif path == "/state":
                self._send(HTTPStatus.OK, json.dumps(state.snapshot()).encode(), "application/json")
            elif path.startswith("/frame/") and path.endswith(".jpg"):
                jpeg = state.frame(path[len("/frame/") : -len(".jpg")])
                if jpeg is None:
                    self._send(HTTPStatus.NOT_FOUND, b"no frame yet", "text/plain")
                else:
                    self._send(HTTPStatus.OK, jpeg, "image/jpeg")
            elif path == "/ack":
                query = parse_qs(self.path.partition("?")[2])
                try:
                    state.ack(int(query.get("frames", ["0"])[0]))
                except ValueError:
                    self._send(HTTPStatus.BAD_REQUEST, b"frames: expected an integer", "text/plain")
                    return
                self._send(HTTPStatus.NO_CONTENT, b"", "text/plain")
            elif path == "/events":
                self._events()
            else:
                self._send(HTTPStatus.NOT_FOUND, b"not found", "text/plain")

        def _events(self) -> None:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            # Start with what is known, then follow.
            version = max(state.version - 64, 0)
            try:
                while True:
                    events = state.events_after(version, SSE_KEEPALIVE_S)
                    if not events:
                        self.wfile.write(b": keepalive\n\n")
                    for number, kind, text in events:
                        self.wfile.write(f"event: {kind}\ndata: {text}\n\n".encode())
                        version = number
                    self.wfile.flush()
            except (BrokenPipeError, ConnectionResetError):
                return  # the browser went away

    return Handler


class PreviewServer:
    """The zenoh subscriber plus the HTTP server; `start()`, `serve_forever()`, `close()`."""

    def __init__(self, options: PreviewServerOptions) -> None:
        self.options = options
        self.state = PreviewState()
        self._session: Any = None
        self.httpd = ThreadingHTTPServer(
            (options.http_host, options.http_port), _make_handler(self.state)
        )
        self.httpd.daemon_threads = True
        self._serving = False

    @property
    def url(self) -> str:
        host, port = (str(part) for part in self.httpd.server_address[:2])
        return f"http://{host}:{port}/"

    def start(self) -> None:
        import zenoh

        config = zenoh_config(
            listen=[],
            connect=self.options.connect,
            config_file=self.options.zenoh_config_file,
            mode="client",
        )
        deadline = time.monotonic() + self.options.connect_timeout_s
        while True:
            try:
                self._session = zenoh.open(config)
                break
            except zenoh.ZError as error:
                if time.monotonic() >= deadline:
                    raise DeviceError(
                        f"preview: cannot connect to {', '.join(self.options.connect)} "
                        f"after {self.options.connect_timeout_s:g} s ({error})"
                    ) from None
                log.info("preview: waiting for the recorder at %s", self.options.connect)
                time.sleep(0.5)

        def on_sample(sample: Any) -> None:
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            self.state.on_sample(str(sample.key_expr), sample.payload.to_bytes(), attachment)

        self._session.declare_subscriber(self.options.key_expr, on_sample)

    def serve_forever(self) -> None:
        self._serving = True
        try:
            self.httpd.serve_forever(poll_interval=0.2)
        finally:
            self._serving = False

    def close(self) -> None:
        if self._serving:  # shutdown() waits for serve_forever: only when it runs
            self.httpd.shutdown()
        self.httpd.server_close()
        if self._session is not None:
            self._session.close()
            self._session = None


def serve(options: PreviewServerOptions) -> None:
    """Run the preview until interrupted (Ctrl-C / SIGTERM)."""
    import signal

    try:
        server = PreviewServer(options)
    except OSError as error:
        raise DeviceError(
            f"preview: cannot serve on {options.http_host}:{options.http_port} ({error.strerror})"
        ) from None
    try:
        server.start()
    except DeviceError:
        server.close()
        raise
    print(f"preview: {server.url} (from {', '.join(options.connect)})", flush=True)
    stop = threading.Event()

    def on_signal(_signum: int, _frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    thread = threading.Thread(target=server.serve_forever, name="http", daemon=True)
    thread.start()
    try:
        while not stop.is_set():
            time.sleep(0.2)
    finally:
        server.close()
