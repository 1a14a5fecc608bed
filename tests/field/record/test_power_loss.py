"""Power lost during a write: the archive cut at random byte offsets of every kind of
record, then `recover`, then an independent reader (the mcap library) on the result.

The recorder's durability policy (field/record/recorder.py): the chunk in progress is
written and fsynced every `flush_interval_s` (0.5 s), so after a power cut the file holds
every chunk up to the last flush; a cut can fall inside a chunk (being written), inside
the message indexes that follow each chunk, or in the summary and footer written on close.
"""

from __future__ import annotations

import random
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from field.record.recover import recover
from shared.archive import ArchiveReader, ArchiveWriter, Imu
from shared.errors import InputError

T0 = 1_700_000_000_000_000_000
RATE_HZ = 200
PER_FLUSH = 100  # samples between flushes: 0.5 s at 200 Hz
CUTS_PER_CLASS = 20

OP_CHUNK, OP_MESSAGE_INDEX, OP_DATA_END, OP_FOOTER = 0x06, 0x07, 0x0F, 0x02


def _closed_archive(path: Path, seconds: float) -> bytes:
    """A recorder-like archive (200 Hz IMU, a chunk every 0.5 s), closed cleanly."""
    with ArchiveWriter(path, chunk_size=1 << 30, metadata={"session_id": "power"}) as writer:
        for k in range(round(seconds * RATE_HZ)):
            stamp = T0 + k * 5_000_000
            imu = Imu(stamp, "imu0", np.array([k, 0.0, 0.0]), np.array([0.0, 0.0, 9.81]))
            writer.write("/imu0", imu, log_time_ns=stamp)
            if (k + 1) % PER_FLUSH == 0:
                writer.flush(fsync=True)
    return path.read_bytes()


def _record_spans(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of every record after the magic, up to the closing magic."""
    spans = []
    position = 8
    while position < len(data) - 8:
        opcode = data[position]
        length = struct.unpack_from("<Q", data, position + 1)[0]
        end = position + 9 + length
        spans.append((opcode, position, end))
        position = end
    return spans


def _offset_classes(data: bytes) -> dict[str, list[tuple[int, int]]]:
    spans = _record_spans(data)
    data_end = next(start for op, start, _ in spans if op == OP_DATA_END)
    classes: dict[str, list[tuple[int, int]]] = {
        "inside a chunk": [(s + 1, e) for op, s, e in spans if op == OP_CHUNK],
        "inside a message index": [(s + 1, e) for op, s, e in spans if op == OP_MESSAGE_INDEX],
        "inside the summary": [(data_end, next(s for op, s, _ in spans if op == OP_FOOTER))],
        "inside the footer": [(next(s for op, s, _ in spans if op == OP_FOOTER), len(data))],
    }
    return classes


def _messages_before(data: bytes, cut: int) -> int:
    """IMU samples in the chunks that lie wholly before `cut` (what must survive)."""
    whole = sum(1 for op, _, end in _record_spans(data) if op == OP_CHUNK and end <= cut)
    return whole * PER_FLUSH


def test_cut_at_random_offsets_of_every_kind_recovers_every_whole_chunk(tmp_path: Path) -> None:
    data = _closed_archive(tmp_path / "closed.mcap", seconds=6.0)
    total = 6 * RATE_HZ
    rng = random.Random(7)
    for kind, ranges in _offset_classes(data).items():
        assert ranges, kind
        for trial in range(CUTS_PER_CLASS):
            start, end = rng.choice(ranges)
            cut = rng.randrange(start, end)
            part = tmp_path / f"{kind.replace(' ', '_')}_{trial}.mcap.part"
            part.write_bytes(data[:cut])
            if _messages_before(data, cut) == 0:
                # Not even the first chunk was whole: nothing to recover, said so.
                with pytest.raises(InputError, match="nothing to recover"):
                    recover(part, tmp_path / f"out_{kind}_{trial}.mcap")
                continue
            report = recover(part, tmp_path / f"out_{kind}_{trial}.mcap")
            # The mcap library reads the result as a complete, indexed file.
            with report.output.open("rb") as f:
                reader = make_reader(f)
                summary = reader.get_summary()
                assert summary is not None and summary.statistics is not None
                read = sum(1 for _ in reader.iter_messages(topics=["/imu0"]))
            count = report.messages.get("/imu0", 0)
            assert read == count == summary.statistics.message_count
            with ArchiveReader(report.output) as ours:
                gyro_x = ours.read_imu("/imu0").gyro_rad_s[:, 0]
            np.testing.assert_array_equal(gyro_x, np.arange(count))  # a prefix, in order
            must_keep = _messages_before(data, cut)
            where = f"{kind}, cut at {cut} of {len(data)}"
            assert count >= must_keep, where  # every fsynced chunk before the cut
            assert count <= total and count % PER_FLUSH == 0, where  # whole chunks only
            if kind in ("inside the summary", "inside the footer"):
                assert count == total, where  # a cut after the data loses no message
