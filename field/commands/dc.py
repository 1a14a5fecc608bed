"""`wreckmap-field dc`: dive computers (download, simulated unit, logbook import)."""

from __future__ import annotations

import argparse
from pathlib import Path

DOWNLOAD_EXAMPLE = """\
example:
  wreckmap-field dc download --port /dev/ttyUSB0 --model perdix-ai --out dives/
  wreckmap-field dc download --port socket://192.168.4.1:7000 --out dives/
"""
SIMULATE_EXAMPLE = """\
example:
  wreckmap-field dc simulate --model petrel2 --dives 3 --truth-out truth/
  (prints the pty path on its first line; stop with Ctrl-C)
"""
IMPORT_EXAMPLE = """\
example:
  wreckmap-field dc import logbook.ssrf --out dives/
  wreckmap-field dc import dive88.csv --out dives/
"""

MODEL_KEYS = ("petrel", "petrel2", "perdix", "perdix-ai", "teric", "petrel3", "perdix2")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    group = subparsers.add_parser("dc", help="dive computer: download, simulate, import")
    commands = group.add_subparsers(dest="dc_command", metavar="DC_COMMAND", required=True)
    raw = argparse.RawDescriptionHelpFormatter

    download = commands.add_parser(
        "download",
        help="download new dives from a Shearwater into a dive folder",
        epilog=DOWNLOAD_EXAMPLE,
        formatter_class=raw,
    )
    download.add_argument("--port", required=True, help="device path or pyserial URL")
    download.add_argument("--model", choices=MODEL_KEYS, help="expected model (checked)")
    download.add_argument("--out", required=True, type=Path, help="dive folder")
    download.add_argument("--timeout-s", type=float, default=3.0, help="reply timeout, seconds")
    download.add_argument("--retries", type=int, default=3, help="new sessions before failing")
    download.add_argument("--backoff-s", type=float, default=0.25, help="first retry pause, s")
    download.add_argument("--settle-s", type=float, default=0.3, help="wait after opening, s")
    download.add_argument(
        "--verify", action="store_true", help="read every reply until two agree (noisy links)"
    )
    download.add_argument("--fingerprint", help="only dives newer than this one (8 hex digits)")
    download.set_defaults(handler=_download)

    simulate = commands.add_parser(
        "simulate",
        help="a simulated Shearwater on a pseudo-terminal",
        epilog=SIMULATE_EXAMPLE,
        formatter_class=raw,
    )
    simulate.add_argument("--model", choices=("perdix-ai", "petrel2"), default="perdix-ai")
    simulate.add_argument("--dives", type=int, default=3, help="synthetic dives to hold")
    simulate.add_argument("--seed", type=int, default=0)
    simulate.add_argument(
        "--profile", type=Path, nargs="+", default=[], help="dive CSVs or folders to hold too"
    )
    simulate.add_argument("--units", choices=("metric", "imperial"), default="metric")
    simulate.add_argument("--duration-s", type=float, default=1800.0, help="synthetic dives, s")
    simulate.add_argument("--interval-s", type=float, default=10.0, help="sample interval, s")
    simulate.add_argument("--deleted", type=int, default=0, help="deleted-dive records to list")
    simulate.add_argument("--serial", default="1234ABCD", help="8 hex digits")
    simulate.add_argument("--truth-out", type=Path, help="write the held dives as a dive folder")
    simulate.add_argument("--drop-rate", type=float, default=0.0, help="bytes dropped, 0..1")
    simulate.add_argument("--corrupt-rate", type=float, default=0.0, help="bytes corrupted, 0..1")
    simulate.add_argument("--stall-after", type=int, help="go silent before this reply packet")
    simulate.add_argument("--stall-s", type=float, default=5.0, help="length of the stall, s")
    simulate.add_argument("--disconnect-after", type=int, help="close the pty after N replies")
    simulate.add_argument(
        "--disconnect-after-bytes",
        type=int,
        metavar="N",
        help="pull the cable after N bytes sent, even mid-reply",
    )
    simulate.set_defaults(handler=_simulate)

    importer = commands.add_parser(
        "import",
        help="import a logbook (Subsurface XML, UDDF, Shearwater CSV) into a dive folder",
        epilog=IMPORT_EXAMPLE,
        formatter_class=raw,
    )
    importer.add_argument("file", type=Path, help="logbook file")
    importer.add_argument("--out", required=True, type=Path, help="dive folder")
    importer.add_argument("--format", help="force a format (default: from the file)")
    importer.set_defaults(handler=_import)


def _download(args: argparse.Namespace) -> int:
    from field.divecomputer.download import DownloadOptions, download_dives

    options = DownloadOptions(
        expected_model=args.model,
        read_timeout_s=args.timeout_s,
        session_retries=args.retries,
        backoff_s=args.backoff_s,
        settle_s=args.settle_s,
        verify=args.verify,
        fingerprint=args.fingerprint,
    )
    result = download_dives(args.port, args.out, options)
    identity = result.identity
    if identity is not None:
        print(
            f"{identity.model_name} serial {identity.serial_text} firmware "
            f"{identity.firmware_text!r}: {result.listed} new in the list, "
            f"{result.already_present} already here, {len(result.written)} downloaded"
        )
    for path in result.written:
        print(path)
    return 0


def _simulate(args: argparse.Namespace) -> int:
    import signal
    import sys

    from field.divecomputer.simulator import (
        FaultOptions,
        SimulatedShearwater,
        serve_pty,
        synthetic_dives,
    )
    from shared.errors import InputError
    from shared.formats.diveprofile import read_dive_folder, read_profile, write_dive

    try:
        serial = int(args.serial, 16)
    except ValueError:
        raise InputError(f"--serial {args.serial!r}: expected 8 hex digits") from None
    profiles = synthetic_dives(
        args.dives, seed=args.seed, duration_s=args.duration_s, sample_interval_s=args.interval_s
    )
    for path in args.profile:
        if path.is_dir():
            profiles += read_dive_folder(path)
        else:
            profiles.append(read_profile(path))
    deleted = [2 * i + 1 for i in range(args.deleted)]
    device = SimulatedShearwater(
        args.model,
        profiles,
        units=args.units,
        serial=serial,
        sample_interval_s=args.interval_s,
        deleted=deleted,
    )
    if args.truth_out is not None:
        for profile, raw in device.held_dives():
            write_dive(args.truth_out, profile, raw=raw)
    faults = FaultOptions(
        drop_rate=args.drop_rate,
        corrupt_rate=args.corrupt_rate,
        stall_after_packets=args.stall_after,
        stall_s=args.stall_s,
        disconnect_after_packets=args.disconnect_after,
        disconnect_after_bytes=args.disconnect_after_bytes,
        seed=args.seed,
    )

    def ready(path: str) -> None:
        print(path, flush=True)

    # SIGINT (also when started in the background, where it may be ignored) and SIGTERM
    # end the simulator like Ctrl-C does.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        serve_pty(device, faults=faults, ready=ready)
    except KeyboardInterrupt:
        print("simulated unit stopped", file=sys.stderr)
    return 0


def _import(args: argparse.Namespace) -> int:
    from field.divecomputer.importers import import_logbook

    written = import_logbook(args.file, args.out, format_name=args.format)
    for path in written:
        print(path)
    return 0
