"""PeakMemory: a block's own peak resident memory, this process's or a child's."""

from __future__ import annotations

import resource
import subprocess
import sys

import numpy as np

from shared.memory import PeakMemory

MIB = 2**20


def test_a_block_that_allocates_shows_its_peak_and_the_next_one_does_not() -> None:
    with PeakMemory() as before:
        pass
    with PeakMemory() as busy:
        block = np.ones(300 * MIB // 8)  # touched pages: resident
        block += 1.0
        del block
    with PeakMemory() as after:
        pass
    assert busy.mib >= before.mib + 250
    if not busy.since_start:  # the kernel let us reset the high-water mark
        assert after.mib < busy.mib - 250


def test_a_child_process_counts_with_its_own_peak() -> None:
    # The kernel keeps one figure for all children ever waited for: outgrow the largest
    # child this test process has had so far.
    earlier_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    size_mib = int(max(400, earlier_mib + 200))
    code = f"import numpy as np; a = np.ones({size_mib} * 2**20 // 8); a += 1"
    with PeakMemory() as peak:
        subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    assert peak.mib >= size_mib - 20
