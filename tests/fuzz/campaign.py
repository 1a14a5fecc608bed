"""Longer fuzz campaign over every parser; prints the README table.

    .venv/bin/python -m tests.fuzz.campaign                 # 400 inputs per parser
    .venv/bin/python -m tests.fuzz.campaign --inputs 5000 --targets mcap gpmf
    .venv/bin/python -m tests.fuzz.campaign --save-failures  # store new failing inputs

It lives beside the fuzz targets it drives (a testing tool, not a benchmark: bench/
imports nothing from tests/).

Each input is a structure-aware mutation (tests/fuzz/mutators.py) of a real file from
../shared/data or of a file our own writers produced, replayed through the parser with
a wall-clock limit; an outcome other than "returned" or "raised a WreckmapError naming
the file (and the byte offset or line)" is a failure. With --save-failures each failing
input is written to tests/fuzz/regressions/<parser>/ (big GoPro files as patches).
The default tests replay those files and run a small derandomized share of this campaign.

atheris (libFuzzer for Python) is used for `--atheris TARGET` when it is installed; it
is not a dependency (no atheris 3.1.0 wheel installs on this Python 3.11 machine).
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from tests.fuzz.targets import TARGETS, mutated, run_input, save_regression

# Bugs found by this campaign (or by the crafted inputs of tests/fuzz/test_huge_lengths.py)
# and fixed in issue 14, per table row; each has a regression case or a test.
FIXED: dict[str, list[str]] = {
    "mp4": [
        "stts/stsc/ctts runs of 2^32 samples expanded with np.repeat (32 GiB MemoryError)",
        "stsz of 2^32 fixed-size samples allocated 16 GiB",
        "mvhd creation time past year 9999 (OverflowError)",
        "short stz2 (IndexError)",
        "mdhd timescale 0 (division by zero)",
        "ctts v1 with a negative sample count (ValueError)",
    ],
    "uddf": ["temperature 1e999 K (OverflowError in kelvin_to_c)"],
    "uddf (shearwater)": ["bad datetime in a Shearwater UDDF (ValueError in start_fingerprint)"],
    "subsurface xml": ["temperature beyond float range in K (OverflowError)"],
    "shearwater csv": ["cell over the csv field limit (csv.Error)"],
    "shearwater pnf": ["legacy-layout message now names byte 0"],
    "mcap": [
        "corrupt zstd chunk raised ZstdError",
        "zstd frame or chunk declaring a huge size was inflated in full",
        "corrupt lengths made read() allocate them (MemoryError)",
        "empty chunk/metadata record (IndexError)",
        "message on an undefined channel id (KeyError)",
    ],
    "mcap salvage": [
        "same crashes as mcap",
        "damaged message index or unknown channel in it: now scans instead of failing",
    ],
    "kalibr camchain": [
        "integer beyond float range (OverflowError)",
        "'cam²' key (ValueError when sorting cameras)",
    ],
    "kalibr imu": [
        "YAML alias bomb: error message repr'd the expanded tree (hang, GBs)",
        "integer beyond float range (OverflowError)",
        "deep flow nesting: seconds of parsing then RecursionError",
    ],
    "kalibr target": ["YAML alias bomb (hang)", "integer beyond float range (OverflowError)"],
    "tum": [
        "quaternion near 1e300 (norm overflow, ValueError)",
        "stamp 1e999999999 (decimal.Overflow) or beyond int64 ns (OverflowError)",
    ],
    "euroc cam0/data.csv": [
        "image name too long (OSError)",
        "'--1' or '²' stamp (ValueError)",
        "stamp beyond int64 (OverflowError)",
    ],
    "euroc imu0/data.csv": ["stamp beyond int64 (OverflowError)"],
    "euroc state_groundtruth_estimate0/data.csv": ["quaternion norm overflow (ValueError)"],
    "euroc imu0/sensor.yaml": ["integer beyond float range (OverflowError)"],
    "euroc cam0/sensor.yaml": ["integer beyond float range (OverflowError)"],
    "dive csv": [
        "stamp inf or 1e20 (OverflowError printing the start)",
        "cell over the csv field limit (csv.Error)",
    ],
    "dives.json": [
        "sample_interval_s not a number (TypeError/ValueError)",
        "csv '' naming the folder (IsADirectoryError)",
        "deep nesting (RecursionError)",
        "1000-character fingerprint made a file name too long (OSError in write_dive)",
    ],
    "gopro import": ["codec-config error now names the track"],
}


def regression_count(name: str) -> int:
    from tests.fuzz.targets import regression_dir

    folder = regression_dir(TARGETS[name])
    return sum(1 for p in folder.iterdir() if p.is_file()) if folder.is_dir() else 0


def campaign(
    names: list[str], inputs: int, first_seed: int, save: bool
) -> dict[str, dict[str, Any]]:
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            target = TARGETS[name]
            kinds: collections.Counter[str] = collections.Counter()
            failures: list[str] = []
            slowest = 0.0
            start = time.perf_counter()
            for seed in range(first_seed, first_seed + inputs):
                label, data = mutated(target, seed)
                outcome = run_input(target, data, Path(tmp) / "case")
                kinds[outcome.kind] += 1
                slowest = max(slowest, outcome.elapsed_s)
                if outcome.failed:
                    failures.append(f"{label}: {outcome.kind}: {outcome.message[:200]}")
                    if save:
                        save_regression(target, f"{outcome.kind}-{seed}", data, label)
            results[name] = {
                "inputs": inputs,
                "kinds": kinds,
                "failures": failures,
                "seconds": time.perf_counter() - start,
                "slowest_s": slowest,
            }
            print(
                f"{name}: {inputs} inputs in {results[name]['seconds']:.1f} s, "
                f"{dict(kinds)}, slowest {slowest:.3f} s",
                file=sys.stderr,
            )
            for line in failures[:10]:
                print(f"  FAIL {line}", file=sys.stderr)
    return results


def table(results: dict[str, dict[str, Any]]) -> str:
    lines = [
        "| parser | inputs tried | rejected with a clear error | failures now | "
        "regression cases | bugs found and fixed |",
        "|---|---|---|---|---|---|",
    ]
    for name, result in results.items():
        fixed = "; ".join(FIXED.get(name, [])) or "none"
        lines.append(
            f"| {name} | {result['inputs']} | {result['kinds'].get('error', 0)} | "
            f"{len(result['failures'])} | {regression_count(name)} | {fixed} |"
        )
    return "\n".join(lines)


def run_atheris(name: str) -> None:  # pragma: no cover - optional tool
    import atheris  # type: ignore[import-not-found, import-untyped, unused-ignore]

    target = TARGETS[name]
    work = Path(tempfile.mkdtemp())

    def one(data: bytes) -> None:
        outcome = run_input(target, data, work / "case")
        if outcome.failed:
            raise RuntimeError(f"{name}: {outcome.kind}: {outcome.message}")

    atheris.Setup([sys.argv[0]], one)
    atheris.Fuzz()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inputs", type=int, default=400, help="inputs per parser")
    parser.add_argument("--first-seed", type=int, default=1_000_000, help="first input number")
    parser.add_argument("--targets", nargs="*", default=list(TARGETS), help="parsers to fuzz")
    parser.add_argument("--save-failures", action="store_true")
    parser.add_argument("--atheris", metavar="TARGET", help="run atheris on one parser instead")
    args = parser.parse_args()
    if args.atheris:
        run_atheris(args.atheris)
        return
    results = campaign(args.targets, args.inputs, args.first_seed, args.save_failures)
    print(table(results))


if __name__ == "__main__":
    main()
