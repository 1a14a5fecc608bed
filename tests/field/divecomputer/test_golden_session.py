"""Replay the golden dctool session of shearwater-example-session.md, byte for byte.

The downloader talks to a fake serial transport that plays the device's side of the
trace: every frame the downloader sends must equal the doc's `>>` line, and what it
writes must match the doc's dives. The simulated unit, holding the same two dives,
must answer with the doc's `<<` frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from field.divecomputer import protocol
from field.divecomputer.download import DownloadOptions, download_dives
from field.divecomputer.simulator import SimulatedShearwater
from shared.errors import DeviceError
from shared.formats.diveprofile import read_dive_folder, read_dive_index

from .golden import load
from .test_logformat import doc_samples

GOLDEN = load()
SHUTDOWN = protocol.encode_request(protocol.shutdown_request())


def device_frames() -> list[bytes]:
    """The `<<` frames in full: cut manifest lines rebuilt from the doc's manifest page."""
    page = GOLDEN.manifest_prefix + b"\xff" * (0x600 - len(GOLDEN.manifest_prefix))
    manifest_blocks = [page[i : i + 250] for i in range(0, 0x600, 250)]
    frames = []
    for direction, shown, total in GOLDEN.trace:
        if direction != "<<":
            continue
        if total is None:
            frames.append(shown)
            continue
        counter = shown[5]
        if shown[4] == 0x76 and len(frames) and total == 257:
            frame = protocol.encode_response(
                protocol.transfer_response(counter, manifest_blocks[counter - 1])
            )
        else:
            frame = {0x93: GOLDEN.block_a, 0xA5: GOLDEN.block_b}[shown[2]]
        assert frame.startswith(shown) and len(frame) == total
        frames.append(frame)
    return frames


class ScriptedShearwater:
    """A fake pyserial port: checks each host frame against the trace, queues the reply."""

    def __init__(self) -> None:
        self.expected = [shown for direction, shown, _ in GOLDEN.trace if direction == ">>"]
        replies = iter(device_frames())
        self.replies = {}
        position = 0
        for direction, _, _ in GOLDEN.trace:
            if direction == ">>":
                position += 1
            else:
                self.replies[position - 1] = next(replies)
        self.sent: list[bytes] = []
        self.position = 0
        self.pending = bytearray()
        self.outgoing = bytearray()
        self.timeout: float | None = 0.01
        self.closed = False

    @property
    def in_waiting(self) -> int:
        return len(self.outgoing)

    def read(self, size: int = 1) -> bytes:
        data = bytes(self.outgoing[:size])
        del self.outgoing[:size]
        return data

    def write(self, data: bytes) -> int:
        self.pending += data
        while protocol.END in self.pending:
            end = self.pending.index(protocol.END) + 1
            frame = bytes(self.pending[:end])
            del self.pending[:end]
            self.sent.append(frame)
            if frame == SHUTDOWN:
                continue  # the session may end early (nothing new, wrong model)
            index = self.position
            self.position += 1
            assert index < len(self.expected), f"extra frame {frame.hex(' ')}"
            assert frame == self.expected[index], f"frame {index}: {frame.hex(' ')}"
            self.outgoing += self.replies.get(index, b"")
        return len(data)

    def reset_input_buffer(self) -> None:
        self.outgoing.clear()

    def reset_output_buffer(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def test_downloader_replays_golden_session(tmp_path: Path) -> None:
    port = ScriptedShearwater()
    options = DownloadOptions(settle_s=0.0, read_timeout_s=0.5)
    result = download_dives("golden", tmp_path, options, open_transport=lambda _: port)
    assert port.sent == port.expected and port.closed
    assert result.identity is not None
    assert (result.identity.serial, result.identity.firmware) == (305441741, 92)
    assert result.identity.model_name == "Shearwater Perdix AI"
    assert len(result.written) == 2
    dives = {d.fingerprint: d for d in read_dive_folder(tmp_path)}
    entries = {e["fingerprint"]: e for e in read_dive_index(tmp_path)}
    for fingerprint, raw, number in (
        ("65554280", GOLDEN.dive_a, 1),
        ("6553F100", GOLDEN.dive_b, 2),
    ):
        assert (tmp_path / entries[fingerprint]["raw"]).read_bytes() == raw
        dive = dives[fingerprint]
        expected = np.array(doc_samples(GOLDEN.xml, number))
        np.testing.assert_array_equal(dive.stamps_s - dive.start_s, expected[:, 0])
        np.testing.assert_allclose(dive.depth_m, expected[:, 1], atol=0.005)
        np.testing.assert_array_equal(dive.temperature_c, expected[:, 2])
        assert dive.serial == "1234ABCD" and dive.model == "Shearwater Perdix AI"
    assert entries["65554280"]["start"] == "2023-11-15T22:13:20"
    assert entries["6553F100"]["start"] == "2023-11-14T22:13:20"
    assert entries["6553F100"]["duration_s"] == 60.0 and entries["6553F100"]["max_depth_m"] == 15.3


def test_rerun_downloads_nothing_new(tmp_path: Path) -> None:
    options = DownloadOptions(settle_s=0.0, read_timeout_s=0.5)
    download_dives("golden", tmp_path, options, open_transport=lambda _: ScriptedShearwater())
    # The remembered fingerprint is the newest dive: the manifest scan stops at record 0.
    port = ScriptedShearwater()
    result = download_dives("golden", tmp_path, options, open_transport=lambda _: port)
    assert result.written == [] and result.listed == 0
    # Identity (4 frames) and one manifest page (init, 7 blocks, exit), then no dive.
    assert port.sent[-1] == SHUTDOWN and port.position == 13
    assert len(read_dive_index(tmp_path)) == 2


def test_simulator_answers_like_the_golden_device() -> None:
    device = SimulatedShearwater(
        "perdix-ai", [], firmware_text="V92", raw_logs=[GOLDEN.dive_b, GOLDEN.dive_a]
    )
    assert device.manifest_pages()[0][:64] == GOLDEN.manifest_prefix
    answers = []
    for direction, shown, _ in GOLDEN.trace:
        if direction == ">>":
            answers += device.feed(shown)
    assert answers == device_frames()


def test_wrong_model_is_refused(tmp_path: Path) -> None:
    options = DownloadOptions(settle_s=0.0, read_timeout_s=0.5, expected_model="petrel2")
    with pytest.raises(DeviceError, match=r"expected a Shearwater Petrel 2 .* Perdix AI"):
        download_dives("golden", tmp_path, options, open_transport=lambda _: ScriptedShearwater())
