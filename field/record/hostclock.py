"""Host time for recordings: the wall clock read once, then carried by the monotonic clock.

A laptop's wall clock steps when it finds GPS or NTP, forward or back, by seconds to
hours. Archive log times, the simulated rig's device clock and the recorder's pacing
must not step with it, or stamps would run backwards mid-recording. So host time is the
wall clock at process start plus the monotonic time elapsed since: close to UTC,
strictly monotonic. The recorder compares it with the wall clock every health interval
and records a `clock_step` event when the two part (the mapping between the recorded
times and the wall clock after the step is then `wall = host + wall_minus_host_ns`).
"""

from __future__ import annotations

import time

CLOCK_STEP_NS = 50_000_000
"""A change of `wall - host` larger than this between two checks is a step (NTP slews
at most 0.5 ms per second; a step is a jump)."""


class HostClock:
    """Monotonic nanoseconds since the epoch, anchored to the wall clock once."""

    def __init__(self) -> None:
        before = time.time_ns()
        self._monotonic_anchor_ns = time.monotonic_ns()
        after = time.time_ns()
        self._wall_anchor_ns = (before + after) // 2

    def now_ns(self) -> int:
        """Host time now: ns since the epoch as the wall clock read at the anchor, carried
        forward by the monotonic clock (never steps)."""
        return self._wall_anchor_ns + time.monotonic_ns() - self._monotonic_anchor_ns

    def wall_minus_host_ns(self) -> int:
        """How far the wall clock is from host time now (0 until the wall clock steps)."""
        return time.time_ns() - self.now_ns()


HOST_CLOCK = HostClock()
"""The one host clock of this process (sources and the recorder share it)."""


def host_now_ns() -> int:
    """`HOST_CLOCK.now_ns()`."""
    return HOST_CLOCK.now_ns()
