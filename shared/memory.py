"""Peak resident memory of a block of work (for the stamps and the benches).

Linux keeps a process's high-water mark of resident memory (VmHWM in
/proc/self/status) and lets a process reset it to the current size by writing "5" to
/proc/self/clear_refs; `PeakMemory` does that at the start of a block, so the figure at
its end is the block's own peak, not the process's since it started. Where the reset is
refused (another kernel, a locked-down container) it falls back to
`resource.getrusage(...).ru_maxrss`, the peak since the process started, and says so
(`since_start`). Child processes the block waited for (a subprocess stage) count with
their own peak, as the kernel records it for waited-for children.
"""

from __future__ import annotations

import resource
import sys
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


def _kib_to_mib(kib: float) -> float:
    return kib / 1024.0


def _maxrss_mib(who: int) -> float:
    # ru_maxrss is in KiB on Linux and in bytes on macOS.
    value = float(resource.getrusage(who).ru_maxrss)
    return value / 2**20 if sys.platform == "darwin" else _kib_to_mib(value)


def _status_kib(field: str) -> float | None:
    try:
        text = _STATUS.read_text(encoding="ascii")
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            parts = line.split()
            if len(parts) >= 2 and parts[1].isdigit():
                return float(parts[1])
    return None


def _reset_high_water_mark() -> bool:
    try:
        _CLEAR_REFS.write_text("5", encoding="ascii")
    except OSError:
        return False
    return True


@dataclass
class PeakMemory:
    """`with PeakMemory() as peak: ...` then `peak.mib`: the block's peak resident memory
    in MiB (this process, or a waited-for child if that was larger)."""

    mib: float = 0.0
    since_start: bool = False

    def __enter__(self) -> PeakMemory:
        self._children_before = _maxrss_mib(resource.RUSAGE_CHILDREN)
        self.since_start = not _reset_high_water_mark() or _status_kib("VmHWM") is None
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.mib = self.current_peak_mib()

    def current_peak_mib(self) -> float:
        """The peak so far inside the block."""
        hwm = _status_kib("VmHWM")
        if hwm is None or self.since_start:
            own = _maxrss_mib(resource.RUSAGE_SELF)
        else:
            own = _kib_to_mib(hwm)
        children = _maxrss_mib(resource.RUSAGE_CHILDREN)
        # The children's figure is the largest of every child ever waited for: it speaks
        # for this block only when it grew inside it.
        child = children if children > self._children_before else 0.0
        return max(own, child)
