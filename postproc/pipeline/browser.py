"""Headless Chromium driven over the DevTools protocol on a pipe: open a page, wait for
a condition, click, take a screenshot, list the requests the page made.

I/O only. Used to check report.html's viewer (tests) and to take the README's
screenshots. `--remote-debugging-pipe` speaks NUL-terminated JSON on file descriptors
3 (commands in) and 4 (replies and events out): no port, no websocket library. WebGL
runs on SwiftShader (no GPU needed).
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from types import TracebackType
from typing import Any

from shared.errors import WreckmapError

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--hide-scrollbars",
    "--mute-audio",
)


class BrowserError(WreckmapError):
    """Chromium missing, exited, or a page condition not met in time."""


class HeadlessChromium:
    """One headless Chromium with one page (a context manager).

    width_px, height_px: the window; profile_dir: a new empty folder for the profile
    (default: a temporary one, removed on exit); offline: resolve no host name (a page
    that tries to fetch from the network fails to, and `requests` shows it tried)."""

    def __init__(
        self,
        *,
        width_px: int = 1280,
        height_px: int = 900,
        profile_dir: Path | None = None,
        offline: bool = True,
        chromium: str | None = None,
    ) -> None:
        binary = chromium or shutil.which("chromium") or shutil.which("chromium-browser")
        if binary is None:
            raise BrowserError(
                "chromium is not installed (it is in deploy/system-packages.txt; run "
                "deploy/setup.sh)"
            )
        self._own_profile = profile_dir is None
        self.profile_dir = Path(profile_dir or tempfile.mkdtemp(prefix="wreckmap-chromium-"))
        args = [binary, *FLAGS, f"--window-size={width_px},{height_px}",
                f"--user-data-dir={self.profile_dir}", "--remote-debugging-pipe"]  # fmt: skip
        if offline:
            args.append("--host-resolver-rules=MAP * ~NOTFOUND")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()

        def fds() -> None:  # in the child: the protocol's fds 3 and 4
            # Through copies above 9 first: either pipe end may already be 3 or 4, and
            # dup2 onto the same number would keep it close-on-exec.
            reading = fcntl.fcntl(to_child_r, fcntl.F_DUPFD, 10)
            writing = fcntl.fcntl(from_child_w, fcntl.F_DUPFD, 10)
            os.dup2(reading, 3)
            os.dup2(writing, 4)

        self.process = subprocess.Popen(
            args,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=fds,
            close_fds=False,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict[str, Any]] = []
        self.requests: list[str] = []
        self.console: list[str] = []
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})[
            "sessionId"
        ]
        for domain in ("Page", "Runtime", "Network"):
            self.send(f"{domain}.enable", session=True)

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Stop the browser (politely, then by force) and remove a temporary profile."""
        if self.process.poll() is None:
            with contextlib.suppress(BrowserError, OSError):
                self.send("Browser.close", timeout_s=5.0)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for fd in (self._to_child, self._from_child):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self._own_profile:
            shutil.rmtree(self.profile_dir, ignore_errors=True)

    def _read_message(self, deadline: float) -> dict[str, Any]:
        import select

        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError("chromium: no reply from the DevTools pipe in time")
            ready, _, _ = select.select([self._from_child], [], [], min(left, 1.0))
            if ready:
                chunk = os.read(self._from_child, 1 << 20)
                if not chunk:
                    raise BrowserError(f"chromium exited (status {self.process.poll()})")
                self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        parsed: dict[str, Any] = json.loads(message)
        return parsed

    def _note(self, event: dict[str, Any]) -> None:
        method = event.get("method", "")
        params = event.get("params", {})
        if method == "Network.requestWillBeSent":
            self.requests.append(str(params.get("request", {}).get("url", "")))
        elif method == "Runtime.consoleAPICalled":
            self.console.append(" ".join(str(a.get("value", "")) for a in params.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            self.console.append(
                "exception: " + json.dumps(params.get("exceptionDetails", {}))[:500]
            )
        self.events.append(event)

    def send(
        self,
        method: str,
        params: dict[str, Any] | None = None,
        *,
        session: bool = False,
        timeout_s: float = 60.0,
    ) -> dict[str, Any]:
        """One DevTools command (to the page's session with `session`); its result."""
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self.session
        os.write(self._to_child, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"chromium: {method}: {reply['error']}")
                result: dict[str, Any] = reply.get("result", {})
                return result
            self._note(reply)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (awaited when a promise)."""
        result = self.send(
            "Runtime.evaluate",
            {"expression": expression, "returnByValue": True, "awaitPromise": True},
            session=True,
        )
        if "exceptionDetails" in result:
            raise BrowserError(f"page: {expression}: {result['exceptionDetails']}")
        return result.get("result", {}).get("value")

    def open(self, url: str) -> None:
        """Navigate to `url` (wait for a condition with `wait_for` afterwards)."""
        self.send("Page.navigate", {"url": url}, session=True)

    def wait_for(self, expression: str, *, timeout_s: float = 60.0) -> Any:
        """Poll until the expression is truthy; its value. BrowserError on timeout (a hang
        guard: the condition, not the time, is what is waited for)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                value = self.evaluate(expression)
            except BrowserError:
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                raise BrowserError(
                    f"page: {expression!r} still false after {timeout_s:.0f} s; console: "
                    + " | ".join(self.console[-5:])
                )
            time.sleep(0.1)

    def click(self, x_px: float, y_px: float) -> None:
        """A left click at page pixel (x, y)."""
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.send(
                "Input.dispatchMouseEvent",
                {"type": kind, "x": x_px, "y": y_px, "button": "left", "clickCount": 1,
                 "buttons": 1 if kind == "mousePressed" else 0},
                session=True,
            )  # fmt: skip

    def screenshot(self, *, clip: tuple[float, float, float, float] | None = None) -> bytes:
        """The page as PNG bytes (a clip: x, y, width, height in page pixels)."""
        params: dict[str, Any] = {"format": "png"}
        if clip is not None:
            x, y, w, h = clip
            params["clip"] = {"x": x, "y": y, "width": w, "height": h, "scale": 1}
        data = self.send("Page.captureScreenshot", params, session=True)["data"]
        return base64.b64decode(data)


def screenshot_element(
    url: str,
    out_png: Path,
    *,
    element_id: str = "wm-viewer",
    ready: str = "window.wreckmapViewer && window.wreckmapViewer.ready",
    width_px: int = 1280,
    height_px: int = 900,
    timeout_s: float = 120.0,
) -> Path:
    """Open `url`, wait for `ready`, write the element's screenshot to `out_png`."""
    with HeadlessChromium(width_px=width_px, height_px=height_px) as browser:
        browser.open(url)
        browser.wait_for(ready, timeout_s=timeout_s)
        rect = browser.evaluate(
            f"(() => {{ const r = document.getElementById({json.dumps(element_id)})"
            ".getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; })()"
        )
        png = browser.screenshot(clip=(rect[0], rect[1], rect[2], rect[3]))
    out_png.write_bytes(png)
    return out_png


def main(argv: list[str] | None = None) -> int:
    """`python -m postproc.pipeline.browser REPORT.html[#hash] --out PNG`: a screenshot
    of the report's viewer (how the README's figure was taken)."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("page", help="report.html (a path, optionally with #hash) or a URL")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--element", default="wm-viewer", help="element id to capture")
    parser.add_argument("--width", type=int, default=1280, help="window width, px")
    parser.add_argument("--height", type=int, default=900, help="window height, px")
    args = parser.parse_args(argv)
    page = args.page
    if "://" not in page:
        path, _, fragment = page.partition("#")
        page = Path(path).resolve().as_uri() + (f"#{fragment}" if fragment else "")
    screenshot_element(page, args.out, element_id=args.element, width_px=args.width,
                       height_px=args.height)  # fmt: skip
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
