"""Rebuild a valid, indexed MCAP from a recording cut short (SIGKILL, power loss, full disk).

The recorder writes `recording_NNN.mcap.part` and flushes a complete chunk at least every
`flush_interval_s`, so everything up to the last flush is readable. `recover` copies every
readable message (undecoded CDR, same topics, same log times) and the session metadata
into a new file with a summary and indexes; damaged chunks and the cut tail are skipped
and listed. The `.part` is left as it was (delete it once the result is checked).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from shared.archive import ArchiveReader, ArchiveWriter
from shared.archive.writer import SESSION_METADATA_NAME
from shared.clock import seconds_from_ns
from shared.errors import InputError
from shared.fsutil import atomic_path


@dataclass
class RecoverReport:
    """What a recovery copied.

    messages: per topic; first_ns, last_ns: log-time span (ns since epoch); warnings: one
    line per skipped part of the input; skipped_bytes: input bytes that could not be read.
    """

    source: Path
    output: Path
    messages: dict[str, int]
    first_ns: int
    last_ns: int
    warnings: list[str] = field(default_factory=list)
    skipped_bytes: int = 0

    def summary(self) -> str:
        total = sum(self.messages.values())
        span = seconds_from_ns(self.last_ns - self.first_ns)
        lines = [
            f"{self.output}: {total} messages recovered from {self.source.name} "
            f"({span:.2f} s, {self.skipped_bytes} bytes skipped)"
        ]
        lines += [f"  {topic}: {count}" for topic, count in sorted(self.messages.items())]
        lines += [f"  warning: {w}" for w in self.warnings[:10]]
        return "\n".join(lines)


def default_output(path: Path) -> Path:
    """`X.mcap.part` -> `X.mcap`; `X.mcap` (damaged) -> `X.recovered.mcap`."""
    if path.name.endswith(".part"):
        return path.with_name(path.name[: -len(".part")])
    return path.with_name(f"{path.stem}.recovered.mcap")


def recover(
    path: Path | str, out: Path | str | None = None, *, overwrite: bool = False
) -> RecoverReport:
    """Rebuild `path` (a `.part` or damaged `.mcap`) into `out` (default: `default_output`).

    Raises InputError when `path` is not MCAP or holds no readable message,
    OutputExistsError when `out` exists and `overwrite` is false.
    """
    source = Path(path)
    if not source.is_file():
        raise InputError(f"{source}: no such file (expected a .mcap or .mcap.part recording)")
    output = Path(out) if out is not None else default_output(source)
    if output.resolve() == source.resolve():
        raise InputError(f"{source}: the output would replace the input; give another --out")
    counts: dict[str, int] = {}
    first = last = None
    with ArchiveReader(source, salvage=True) as reader:
        metadata = reader.metadata()
        with (
            atomic_path(output, overwrite=overwrite) as tmp,
            ArchiveWriter(
                tmp, overwrite=True, metadata=metadata.pop(SESSION_METADATA_NAME, None)
            ) as writer,
        ):
            for name, values in metadata.items():
                writer.add_metadata(name, values)
            for record in reader.raw_messages():
                writer.write_cdr(record.topic, record.data, log_time_ns=record.log_time_ns)
                counts[record.topic] = counts.get(record.topic, 0) + 1
                first = record.log_time_ns if first is None else min(first, record.log_time_ns)
                last = record.log_time_ns if last is None else max(last, record.log_time_ns)
            if first is None or last is None:
                writer.abort()
                writer.part_path.unlink(missing_ok=True)
                raise InputError(
                    f"{source}: nothing to recover (no readable message; "
                    f"{'; '.join(reader.warnings[:3]) or 'empty recording'})"
                )
        warnings = list(reader.warnings)
        skipped = reader.skipped_bytes
    return RecoverReport(
        source=source,
        output=output,
        messages=counts,
        first_ns=first,
        last_ns=last,
        warnings=warnings,
        skipped_bytes=skipped,
    )


def recover_path(
    path: Path | str, *, out: Path | str | None = None, overwrite: bool = False
) -> list[RecoverReport]:
    """Recover one file, or every `*.part` of a session folder (then `out` must be None)."""
    target = Path(path)
    if target.is_dir():
        if out is not None:
            raise InputError(f"{target}: --out needs a single file, not a folder")
        parts = sorted(target.glob("*.mcap.part"))
        if not parts:
            raise InputError(
                f"{target}: no .mcap.part file to recover (the recordings are complete)"
            )
        return [recover(p, overwrite=overwrite) for p in parts]
    return [recover(target, out, overwrite=overwrite)]
