"""A cable pulled at a random byte of a download, then the download run again.

Each trial: the dive folder already holds an earlier download; the unit holds those dives
and three newer ones; the link is cut after a random number of bytes (anywhere: the
identity exchange, the manifest, mid-dive, mid-frame). What was in the folder must be
untouched, the dives completed before the cut must be whole, and the next run must fetch
only the rest, with no duplicate.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from field.divecomputer.download import DownloadOptions, download_dives
from field.divecomputer.simulator import (
    FaultOptions,
    LineFaults,
    SimulatedShearwater,
    synthetic_dives,
)
from shared.errors import DeviceError
from shared.formats.diveprofile import read_dive_index, write_dive
from tests.field.divecomputer.test_download import assert_same_dives, simulator_thread

QUICK = DownloadOptions(
    settle_s=0.02, read_timeout_s=0.2, backoff_s=0.0, backoff_max_s=0.0, session_retries=1
)
TRIALS = 20


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _unit() -> SimulatedShearwater:
    # The same two dives as the earlier download (same seed), then three newer ones.
    return SimulatedShearwater("perdix-ai", synthetic_dives(5, seed=21, duration_s=120))


@pytest.fixture(scope="module")
def earlier(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dive folder holding the unit's two oldest dives, downloaded before."""
    folder = tmp_path_factory.mktemp("earlier") / "dives"
    older = SimulatedShearwater("perdix-ai", synthetic_dives(2, seed=21, duration_s=120))
    with simulator_thread(older) as port:
        assert len(download_dives(port, folder, QUICK).written) == 2
    return folder


@pytest.fixture(scope="module")
def full_download_bytes(tmp_path_factory: pytest.TempPathFactory, earlier: Path) -> int:
    """How many bytes the unit sends for the three new dives when nothing goes wrong."""
    folder = tmp_path_factory.mktemp("full") / "dives"
    _copy(earlier, folder)
    line = LineFaults(FaultOptions())
    with simulator_thread(_unit(), line) as port:
        assert len(download_dives(port, folder, QUICK).written) == 3
    return line.bytes_sent


def _copy(source: Path, target: Path) -> None:
    target.mkdir(parents=True)
    for name, data in _snapshot(source).items():
        (target / name).write_bytes(data)


def test_cut_at_random_bytes_keeps_the_folder_and_resumes_without_duplicates(
    tmp_path: Path, earlier: Path, full_download_bytes: int
) -> None:
    truth = tmp_path / "truth"
    for profile, raw in _unit().held_dives():
        write_dive(truth, profile, raw=raw)
    before = _snapshot(earlier)
    old_index = read_dive_index(earlier)
    rng = random.Random(2026)
    completed_counts = []
    for trial in range(TRIALS):
        folder = tmp_path / f"trial{trial}" / "dives"
        _copy(earlier, folder)
        cut = rng.randrange(1, full_download_bytes)
        line = LineFaults(FaultOptions(disconnect_after_bytes=cut))
        with simulator_thread(_unit(), line) as port:
            try:
                download_dives(port, folder, QUICK)
            except DeviceError as error:
                assert "re-run" in str(error) or "saved" in str(error) or "failed" in str(error)
            else:
                pytest.fail(f"cut at byte {cut} of {full_download_bytes}: no error")
        # The folder as it was, plus whole dives only.
        after = _snapshot(folder)
        index = read_dive_index(folder)
        assert index[: len(old_index)] == old_index, f"cut {cut}: earlier entries changed"
        for name, data in before.items():
            if name != "dives.json":
                assert after[name] == data, f"cut {cut}: {name} changed"
        new_entries = index[len(old_index) :]
        completed_counts.append(len(new_entries))
        named = {e[k] for e in new_entries for k in ("csv", "raw")}
        assert set(after) == set(before) | named, (
            f"cut {cut}: stray files {set(after) - set(before) - named}"
        )
        truth_by_fingerprint = {e["fingerprint"]: e for e in read_dive_index(truth)}
        for entry in new_entries:
            want = truth_by_fingerprint[entry["fingerprint"]]
            for key in ("csv", "raw"):
                assert (folder / entry[key]).read_bytes() == (truth / want[key]).read_bytes()
        # The next run fetches only what is missing, and the folder ends complete.
        with simulator_thread(_unit()) as port:
            result = download_dives(port, folder, QUICK)
        assert len(result.written) == 3 - len(new_entries), f"cut {cut}"
        fingerprints = [e["fingerprint"] for e in read_dive_index(folder)]
        assert len(fingerprints) == len(set(fingerprints)) == 5
        assert_same_dives(truth, folder)
    # The cuts fell before the first new dive, between dives and after some: all classes.
    print("completed before the cut:", completed_counts, "of", full_download_bytes, "bytes")
    assert min(completed_counts) == 0 and max(completed_counts) >= 2
