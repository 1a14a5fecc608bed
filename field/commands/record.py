"""`wreckmap-field record | recover | inspect | preview`: the live logger and its tools."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

RECORD_EXAMPLE = """\
example:
  wreckmap-field record --source sim --out sessions/2024-06-15_a --duration 60
  wreckmap-field record --source oak --out /data/dive3 --preview tcp/127.0.0.1:7447
  wreckmap-field record --config deploy/logger.yaml --out /data/dive4 \\
      --source-option sim.cameras=2 --preview-lan 192.168.2.10

Writes SESSION_DIR/session.yaml, recording_NNN.mcap (rotated by size/time) and calib/.
Stop with Ctrl-C or SIGTERM: the files are closed and indexed. After a crash run
`wreckmap-field recover SESSION_DIR`. Below --min-free-mb of free disk (default 200 MiB)
the recording stops cleanly. Exit status: 0 stopped as asked, 2 the last file could not
be closed (recover it), 3 stopped because the disk is (nearly) full, files closed.
"""

EXIT_NOT_CLOSED = 2
EXIT_DISK_FULL = 3

RECOVER_EXAMPLE = """\
example:
  wreckmap-field recover sessions/dive3/recording_002.mcap.part
  wreckmap-field recover sessions/dive3            # every .part in the folder

Rebuilds a valid, indexed recording_NNN.mcap beside the .part (which is kept).
"""

INSPECT_EXAMPLE = """\
example:
  wreckmap-field inspect sessions/dive3/recording_000.mcap
  wreckmap-field inspect sessions/dive3 --json > report.json
"""

PREVIEW_EXAMPLE = """\
example:
  wreckmap-field preview --connect tcp/127.0.0.1:7447
  wreckmap-field preview --connect tcp/192.168.2.10:7447 --http 0.0.0.0:8090

Open http://127.0.0.1:8090/ in a browser on the boat (no internet needed).
"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    formatter = argparse.RawDescriptionHelpFormatter
    record = subparsers.add_parser(
        "record",
        help="record live camera/IMU (OAK or simulated) to a session folder of MCAP files",
        epilog=RECORD_EXAMPLE,
        formatter_class=formatter,
    )
    record.add_argument(
        "--source",
        action="append",
        metavar="KIND",
        help="source kind: oak or sim (repeat for several; default: the config's sources)",
    )
    record.add_argument(
        "--out", required=True, type=Path, metavar="SESSION_DIR", help="session folder"
    )
    record.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    record.add_argument(
        "--config", type=Path, metavar="YAML", help="logger config (deploy/logger.yaml)"
    )
    record.add_argument(
        "--source-option",
        action="append",
        default=[],
        metavar="KIND.KEY=VALUE",
        help="set one source option, e.g. sim.cameras=2 (value parsed as YAML)",
    )
    record.add_argument(
        "--preview",
        metavar="ENDPOINT",
        help="publish the live preview on zenoh, e.g. tcp/127.0.0.1:7447",
    )
    record.add_argument(
        "--preview-lan",
        metavar="ADDRESS",
        help="also listen for preview clients on this LAN address (same port as --preview)",
    )
    record.add_argument(
        "--min-free-mb",
        type=float,
        metavar="MIB",
        help="stop cleanly when the disk has less free space than this (MiB; default 200, "
        "0 turns the watermark off)",
    )
    record.add_argument("--rig", help="rig name (preview keys wreckmap/RIG/SESSION/...)")
    record.add_argument(
        "--overwrite", action="store_true", help="record into a folder that has one"
    )
    record.set_defaults(handler=_record)

    recover = subparsers.add_parser(
        "recover",
        help="rebuild a valid, indexed MCAP from a crashed recording (.part)",
        epilog=RECOVER_EXAMPLE,
        formatter_class=formatter,
    )
    recover.add_argument(
        "path", type=Path, metavar="PATH", help=".mcap(.part) file or session folder"
    )
    recover.add_argument("--out", type=Path, help="output file (one input only; default beside it)")
    recover.add_argument("--overwrite", action="store_true", help="replace an existing output")
    recover.set_defaults(handler=_recover)

    inspect = subparsers.add_parser(
        "inspect",
        help="topics, counts, rates, time span, gaps and clock consistency of a recording",
        epilog=INSPECT_EXAMPLE,
        formatter_class=formatter,
    )
    inspect.add_argument("path", type=Path, metavar="PATH", help=".mcap file or session folder")
    inspect.add_argument("--json", action="store_true", help="print JSON instead of text")
    inspect.set_defaults(handler=_inspect)

    preview = subparsers.add_parser(
        "preview",
        help="local web page with the live image, IMU plots and recorder health",
        epilog=PREVIEW_EXAMPLE,
        formatter_class=formatter,
    )
    preview.add_argument(
        "--connect", required=True, metavar="ENDPOINT", help="recorder's zenoh endpoint"
    )
    preview.add_argument(
        "--http", default="127.0.0.1:8090", metavar="HOST:PORT", help="where the page is served"
    )
    preview.add_argument("--key", default="wreckmap/**", help="zenoh key expression to show")
    preview.add_argument(
        "--connect-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="keep trying this many seconds while the recorder is not up yet (default 30)",
    )
    preview.add_argument(
        "--zenoh-config", type=Path, help="zenoh JSON5 config (TLS, access control)"
    )
    preview.set_defaults(handler=_preview)


def _load_config(path: Path | None) -> dict[str, Any]:
    import yaml

    from shared.errors import InputError

    if path is None:
        return {}
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as error:
        raise InputError(f"{path}: cannot read the logger config ({error})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected a mapping with recorder/sources/preview sections")
    unknown = sorted(set(doc) - {"recorder", "sources", "preview"})
    if unknown:
        raise InputError(
            f"{path}: unknown section(s) {', '.join(unknown)} (expected recorder, sources, preview)"
        )
    return doc


def _record(args: argparse.Namespace) -> int:
    import signal

    import yaml

    from field.record.preview_bus import PreviewOptions, PreviewPublisher
    from field.record.recorder import Recorder, RecorderOptions
    from field.record.sources.base import build_options, make_source
    from shared.errors import InputError

    config = _load_config(args.config)
    source_options: dict[str, dict[str, Any]] = {
        k: dict(v or {}) for k, v in (config.get("sources") or {}).items()
    }
    for item in args.source_option:
        name, sep, value = item.partition("=")
        kind, dot, key = name.partition(".")
        if not sep or not dot or not kind or not key:
            raise InputError(
                f"--source-option {item!r}: expected KIND.KEY=VALUE, e.g. sim.cameras=2"
            )
        source_options.setdefault(kind, {})[key] = yaml.safe_load(value)
    kinds = args.source or list((config.get("sources") or {}).keys())
    if not kinds:
        raise InputError("record: no source (give --source oak or --source sim, or a config)")
    sources = [make_source(kind, source_options.get(kind)) for kind in kinds]

    recorder_values = dict(config.get("recorder") or {})
    if args.duration is not None:
        recorder_values["duration_s"] = args.duration
    if args.rig:
        recorder_values["rig"] = args.rig
    if args.min_free_mb is not None:
        if args.min_free_mb < 0:
            raise InputError(f"--min-free-mb {args.min_free_mb}: expected MiB >= 0 (0: off)")
        recorder_values["min_free_mb"] = args.min_free_mb
    options = build_options(RecorderOptions, recorder_values, "recorder")

    preview = None
    preview_values = dict(config.get("preview") or {})
    enabled = bool(preview_values.pop("enabled", False)) or args.preview is not None
    if enabled:
        if args.preview is not None:
            preview_values["listen"] = [args.preview]
        if args.preview_lan:
            port = (preview_values.get("listen") or ["tcp/127.0.0.1:7447"])[0].rsplit(":", 1)[-1]
            preview_values["listen"] = [
                *preview_values.get("listen", []),
                f"tcp/{args.preview_lan}:{port}",
            ]
        preview_options = build_options(PreviewOptions, preview_values, "preview")
        session = options.session_id or args.out.resolve().name
        preview = PreviewPublisher(preview_options, rig=options.rig, session=session)

    recorder = Recorder(options, sources, args.out, preview=preview, overwrite=args.overwrite)

    def on_signal(signum: int, _frame: object) -> None:
        recorder.stop(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    if preview is not None:
        preview.start()
    try:
        report = recorder.run()
    finally:
        if preview is not None:
            preview.close()
    total = sum(report.messages.values())
    dropped = sum(report.dropped.values())
    print(
        f"{report.session_dir}: {total} messages in {len(report.files)} file(s) over "
        f"{report.duration_s:.1f} s, {dropped} dropped; stopped: {report.stop_reason}"
    )
    for topic, count in report.messages.items():
        extra = f", {report.dropped[topic]} dropped" if topic in report.dropped else ""
        print(f"  {topic}: {count}{extra}")
    if not report.clean:
        print("the last file was not closed: run `wreckmap-field recover` on its .part")
        return EXIT_NOT_CLOSED
    if report.stop_reason.startswith("disk"):
        print(f"{report.session_dir}: the disk is full; every file is closed, make room to go on")
        return EXIT_DISK_FULL
    return 0


def _recover(args: argparse.Namespace) -> int:
    from field.record.recover import recover_path

    reports = recover_path(args.path, out=args.out, overwrite=args.overwrite)
    for report in reports:
        print(report.summary())
    return 0


def _inspect(args: argparse.Namespace) -> int:
    import json

    from field.record.inspect import format_report, inspect_path

    reports = inspect_path(args.path)
    if args.json:
        print(json.dumps([r.as_dict() for r in reports], indent=2))
    else:
        print("\n\n".join(format_report(r) for r in reports))
    return 0


def _preview(args: argparse.Namespace) -> int:
    from field.record.preview_web import PreviewServerOptions, serve

    host, _, port = args.http.rpartition(":")
    from shared.errors import InputError

    if not host or not port.isdigit():
        raise InputError(f"--http {args.http!r}: expected HOST:PORT, e.g. 127.0.0.1:8090")
    options = PreviewServerOptions(
        connect=[args.connect],
        http_host=host,
        http_port=int(port),
        key_expr=args.key,
        zenoh_config_file=str(args.zenoh_config) if args.zenoh_config else None,
        connect_timeout_s=args.connect_timeout,
    )
    serve(options)
    return 0
