"""Structure-aware fuzzing of every parser (a small, derandomized share of the campaign).

Each example is one mutation (tests/fuzz/mutators.py) of a real file from ../shared/data
or of a file our own writers made; the parser must return, or raise a WreckmapError that
names the file and the place (byte offset, line, record, key), within the wall-clock
limit. tests/fuzz/campaign.py runs the same targets with many more inputs.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from .harness import describe_failure
from .targets import TARGETS, mutated, run_input

pytestmark = pytest.mark.timeout(120)

# Inputs per parser in the default suite (the big XML logbooks cost ~50 ms an input).
EXAMPLES = {
    "gopro salvage": 6,  # ~0.5 s an input (a scan of 4 MB)
    "gopro import": 6,  # ~1 s an input (a whole import)
    "uddf": 12,
    "uddf (shearwater)": 15,
    "subsurface xml": 12,
    "subsurface xml (ostc)": 30,
    "shearwater csv": 30,
    "mp4": 40,
}
DEFAULT_EXAMPLES = 50
SLOW_DOWN = 1.0  # multiply the wall-clock limit on a loaded CI machine if needed


def _fuzz(name: str, tmp_path: Path, seed: int) -> None:
    target = TARGETS[name]
    label, data = mutated(target, seed)
    outcome = run_input(
        target, data, tmp_path / "case", time_limit_s=target.time_limit_s * SLOW_DOWN
    )
    if outcome.failed:
        # Replay: tests/fuzz/campaign.py --save-failures stores such inputs as regressions.
        pytest.fail(describe_failure(name, label, outcome, None))


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_seed_inputs_are_valid(name: str, tmp_path: Path) -> None:
    """The mutations start from inputs the parser accepts (else they prove little)."""
    target = TARGETS[name]
    for label, data in target.seeds():
        outcome = run_input(target, data, tmp_path / "case")
        assert outcome.kind == "ok", f"{name}: seed {label}: {outcome.kind}: {outcome.message}"


def _make_test(name: str):
    @settings(
        max_examples=EXAMPLES.get(name, DEFAULT_EXAMPLES),
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )
    @given(seed=st.integers(0, 2**32 - 1))
    def test(tmp_path: Path, seed: int) -> None:
        _fuzz(name, tmp_path, seed)

    test.__doc__ = f"Mutated {name} inputs end in a clear error or a result."
    return test


for _name in sorted(TARGETS):
    _slug = "".join(c if c.isalnum() else "_" for c in _name).strip("_")
    globals()[f"test_fuzz_{_slug}"] = _make_test(_name)
