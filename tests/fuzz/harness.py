"""Running one hostile input through a parser and judging the outcome.

A target (see `targets.py`) turns bytes into files in a scratch folder and
calls the parser on them. The outcome is acceptable when the parser returns,
or raises a `WreckmapError` whose message names the input file (and, for
targets that promise it, a byte offset or a line). Anything else (another
exception type, running past the wall-clock limit, a message that does not
say where) is a failure. Used by the default tests and by
tests/fuzz/campaign.py.
"""

from __future__ import annotations

import contextlib
import re
import signal
import time
import tracemalloc
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from shared.errors import WreckmapError

# A location in a message: "at byte 123", "offset 456", "file.csv:12", "line 7",
# "waypoint 3", "dive 2 divecomputer 1 sample at 1:00", "record 4", a YAML/JSON key
# ('tagSize', dives[3].start), "position 17", "top level"...
_LOCATION = re.compile(
    r"(byte \d+|offset \d+|:\d+(:\d+)?\b|line \d+|row \d+|waypoint \d+|sample at|dives\[\d+\]"
    r"|cam\d+|track \d+|dive \S+|record \d+|position \d+|top level|'[A-Za-z_][\w.]*'|GPMF '\w+)",
    re.IGNORECASE,
)

# Errors about the file as a whole have no narrower place to name.
_WHOLE_FILE = re.compile(
    r"(no <dive>|neither Subsurface|root element|empty file|an empty file|no poses|no cameras"
    r"|not an MCAP file|not an MP4 file|no 'moov'|no GPMF|no such|has no samples|no video track"
    r"|cannot find the frame size)",
    re.IGNORECASE,
)


class InputTimeoutError(Exception):
    """Raised inside the parser by the wall-clock alarm (never by the parser itself)."""


@dataclass(frozen=True)
class Outcome:
    """What one input did: `kind` is "ok", "error" (a WreckmapError), or a failure kind
    ("crash", "timeout", "no-file-name", "no-location", "memory")."""

    kind: str
    message: str
    elapsed_s: float
    peak_bytes: int | None = None

    @property
    def failed(self) -> bool:
        return self.kind not in ("ok", "error")


@contextlib.contextmanager
def _alarm(limit_s: float) -> Iterator[None]:
    """Interrupt Python code that runs past `limit_s` (main thread only; C loops finish first).

    pytest-timeout may have its own SIGALRM timer running: it is re-armed afterwards with
    the time it had left, so the per-test limit still holds.
    """

    def on_alarm(_signum: int, _frame: object) -> None:
        raise InputTimeoutError(f"still running after {limit_s} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    outer_delay, outer_interval = signal.setitimer(signal.ITIMER_REAL, limit_s)
    if 0 < outer_delay < limit_s:
        signal.setitimer(signal.ITIMER_REAL, outer_delay)
    start = time.monotonic()
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        if outer_delay > 0:
            left = max(outer_delay - (time.monotonic() - start), 0.001)
            signal.setitimer(signal.ITIMER_REAL, left, outer_interval)


def judge(
    call: Callable[[], object],
    *,
    names: tuple[str, ...],
    needs_location: bool,
    time_limit_s: float,
    peak_limit_bytes: int | None = None,
) -> Outcome:
    """Run `call` once and classify it (see the module docstring).

    `names`: strings of which at least one must appear in an error message (the
    file's name, or for wire protocols a word such as "frame"). With
    `peak_limit_bytes`, Python/numpy allocations are traced and a peak above it is
    a "memory" failure.
    """
    if peak_limit_bytes is not None:
        tracemalloc.start()
    start = time.perf_counter()
    kind, message = "ok", ""
    try:
        with _alarm(time_limit_s):
            call()
    except InputTimeoutError as error:
        kind, message = "timeout", str(error)
    except WreckmapError as error:
        message = str(error)
        if not any(name in message for name in names):
            kind = "no-file-name"
        elif needs_location and not (_LOCATION.search(message) or _WHOLE_FILE.search(message)):
            kind = "no-location"
        else:
            kind = "error"
    except Exception as error:
        kind, message = "crash", f"{type(error).__name__}: {error}"[:500]
    elapsed = time.perf_counter() - start
    peak = None
    if peak_limit_bytes is not None:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        if peak > peak_limit_bytes and kind in ("ok", "error"):
            kind, message = "memory", f"peak {peak} bytes > {peak_limit_bytes} ({message})"
    if kind in ("ok", "error") and elapsed > time_limit_s:
        kind, message = "timeout", f"took {elapsed:.2f} s > {time_limit_s} s ({message})"
    return Outcome(kind=kind, message=message, elapsed_s=elapsed, peak_bytes=peak)


def describe_failure(target: str, label: str, outcome: Outcome, saved: Path | None) -> str:
    where = f" (input saved to {saved})" if saved is not None else ""
    return f"{target}: {label}: {outcome.kind}: {outcome.message}{where}"
