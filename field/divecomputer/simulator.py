"""A simulated Shearwater (Petrel family) that speaks the serial protocol on a pty.

`SimulatedShearwater` is the device state machine (bytes in, bytes out, no I/O): it
answers identity reads, serves the manifest page by page and the dives compressed,
exactly as ../shared/docs/shearwater-protocol.md describes, using the same encoders as
the downloader (`protocol.py`, `logformat.py`). `serve_pty` puts it on a pseudo-terminal
with optional line faults (dropped or corrupted bytes, a stall, a disconnect).

Assumption marked [?] in the doc: a repeated TransferData request with the same block
counter gets the same block again (as UDS specifies); the downloader relies on it only
to retry a block.
"""

from __future__ import annotations

import logging
import math
import os
import random
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from field.divecomputer import logformat, protocol
from shared.formats.diveprofile import DiveProfile, stamp_s_to_iso

log = logging.getLogger(__name__)

PNF_BASE = 0x80000000
DIVE_OFFSET_STEP = 0x00010000
MANIFEST_BLOCK_BYTES = 250  # as the reference fake did: 6 x 250 + 36 for a page
MAX_BLOCK_BYTE = 0xFC


@dataclass(frozen=True)
class ShearwaterModel:
    """A unit as the protocol shows it: model number (RDBI 0x8060) and hardware type."""

    key: str
    name: str
    number: int
    hardware_type: int
    firmware_text: str


MODELS: dict[str, ShearwaterModel] = {
    model.key: model
    for model in (
        ShearwaterModel("petrel", "Shearwater Petrel", 3, 0x0404, "V88 Classic"),
        ShearwaterModel("petrel2", "Shearwater Petrel 2", 3, 0x0505, "V92 Classic"),
        ShearwaterModel("perdix", "Shearwater Perdix", 5, 0x0707, "V92 Classic"),
        ShearwaterModel("perdix-ai", "Shearwater Perdix AI", 6, 0x0C0D, "V92 Classic"),
        ShearwaterModel("teric", "Shearwater Teric", 8, 0x0F0F, "V92 Classic"),
        ShearwaterModel("petrel3", "Shearwater Petrel 3", 10, 0xB407, "V97 Classic"),
        ShearwaterModel("perdix2", "Shearwater Perdix 2", 11, 0x704C, "V100 Classic"),
    )
}
SIMULATED_MODELS = ("perdix-ai", "petrel2")


def model_by_key(key: str) -> ShearwaterModel:
    if key not in MODELS:
        raise ValueError(f"unknown Shearwater model {key!r} (known: {', '.join(MODELS)})")
    return MODELS[key]


@dataclass(kw_only=True)
class FaultOptions:
    """Line faults applied to what the simulated unit sends (device -> host).

    drop_rate / corrupt_rate: probability per byte of dropping it / replacing it with a
    random other byte. stall_after_packets: before that response packet (1-based count)
    the unit goes silent for stall_s seconds, once. disconnect_after_packets: after that
    many response packets the pty is closed (the unit is gone until restarted).
    disconnect_after_bytes: the cable is pulled after that many bytes sent (device ->
    host), wherever it falls: mid-frame, the rest of that frame is never sent.
    """

    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    stall_after_packets: int | None = None
    stall_s: float = 0.0
    disconnect_after_packets: int | None = None
    disconnect_after_bytes: int | None = None
    seed: int = 0


def profile_to_log(
    profile: DiveProfile,
    *,
    model: ShearwaterModel,
    serial: int,
    imperial: bool = False,
    sample_interval_s: float | None = None,
) -> bytes:
    """The PNF log a unit would hold for `profile` (resampled to its sample interval).

    The unit logs whole-second start times and one sample per interval, the k-th at
    `start + k * interval` (k = 1, 2, ...), up to the profile's last stamp. Depth and
    temperature are linearly interpolated from the profile (NaNs ignored; temperature
    20 °C when none is logged) and quantized as the unit stores them.
    """
    interval_s = sample_interval_s or profile.sample_interval_s or 10.0
    interval_ms = round(interval_s * 1000)
    if interval_ms <= 0 or interval_ms > 0xFFFF:
        raise ValueError(f"sample interval {interval_s} s out of range (0.001..65.535 s)")
    start_s = math.floor(profile.start_s)
    count = 0
    if profile.stamps_s.size:
        count = math.floor((profile.stamps_s[-1] - start_s) * 1000 / interval_ms + 1e-9)
    times = start_s + np.arange(1, count + 1) * (interval_ms / 1000.0)

    def resample(values: np.ndarray, default: float) -> list[float]:
        good = ~np.isnan(values)
        if not good.any():
            return [default] * count
        return [float(v) for v in np.interp(times, profile.stamps_s[good], values[good])]

    settings = logformat.PnfSettings(
        start_s=start_s,
        sample_interval_ms=interval_ms,
        imperial=imperial,
        serial=serial,
        firmware=protocol_firmware(model.firmware_text),
        model_number=model.number,
    )
    return logformat.build_pnf(
        settings, resample(profile.depth_m, 0.0), resample(profile.temperature_c, 20.0)
    )


def protocol_firmware(text: str) -> int:
    return protocol.decode_firmware(text.encode("ascii"))


def synthetic_dives(
    count: int,
    *,
    seed: int = 0,
    duration_s: float = 1800.0,
    sample_interval_s: float = 10.0,
    first_start_iso: str = "2024-06-01T09:00:00",
) -> list[DiveProfile]:
    """`count` plausible recreational dives, oldest first, about a day apart.

    Each descends at 18 m/min to 8..40 m, stays, ascends at 9 m/min with a 3-minute stop
    at 5 m when the dive is long enough; water is 24 °C at the surface, colder deeper.
    """
    rng = np.random.default_rng(seed)
    base = DiveProfile(
        stamps_s=np.zeros(0),
        depth_m=np.zeros(0),
        temperature_c=np.zeros(0),
        start_iso=first_start_iso,
    ).start_s
    dives = []
    for index in range(count):
        start_s = math.floor(base + index * 86_400 + rng.integers(0, 6 * 3600))
        max_depth_m = float(rng.uniform(8.0, 40.0))
        descent_s = max_depth_m / 18.0 * 60.0
        ascent_s = max_depth_m / 9.0 * 60.0
        stop_s = 180.0 if duration_s > descent_s + ascent_s + 360.0 else 0.0
        bottom_s = max(duration_s - descent_s - ascent_s - stop_s, 0.0)
        knots_t = np.cumsum([0.0, descent_s, bottom_s, ascent_s * 0.8, stop_s, ascent_s * 0.2])
        knots_d = [0.0, max_depth_m, max_depth_m * 0.9, 5.0, 5.0, 0.0]
        stamps = np.asarray(
            start_s + np.arange(1, int(duration_s // sample_interval_s) + 1) * sample_interval_s,
            dtype=np.float64,
        )
        depth = np.interp(stamps - start_s, knots_t, knots_d)
        depth = np.clip(depth + rng.normal(0.0, 0.15, depth.shape), 0.0, None)
        temp = 24.0 - 0.25 * depth + rng.normal(0.0, 0.3, depth.shape)
        dives.append(
            DiveProfile(
                stamps_s=stamps,
                depth_m=depth,
                temperature_c=temp,
                start_iso=stamp_s_to_iso(start_s),
                source="synthetic",
                sample_interval_s=sample_interval_s,
            )
        )
    return dives


class SimulatedShearwater:
    """The device side of the protocol for one Petrel-family unit holding `dives`.

    model: a key of `MODELS` ("perdix-ai", "petrel2", ...). dives: any order; the unit
    lists them newest first. units: "metric" or "imperial" (how the logs store depth and
    temperature). deleted: positions in the newest-first manifest where a deleted-dive
    record is inserted. raw_logs: PNF logs held exactly as given (oldest first, after
    `dives`), e.g. the golden dives of the protocol doc. `feed(host_bytes)` returns the
    response frames, wire-ready.
    """

    def __init__(
        self,
        model: str,
        dives: Sequence[DiveProfile],
        *,
        units: str = "metric",
        serial: int = 0x1234ABCD,
        firmware_text: str | None = None,
        sample_interval_s: float | None = None,
        deleted: Sequence[int] = (),
        raw_logs: Sequence[bytes] = (),
    ) -> None:
        if units not in ("metric", "imperial"):
            raise ValueError(f"units {units!r}: expected 'metric' or 'imperial'")
        self.model = model_by_key(model)
        self.serial = serial
        self.firmware_text = firmware_text or self.model.firmware_text
        self.units = units
        ordered = sorted(dives, key=lambda profile: profile.start_s)
        self.logs: list[bytes] = [
            profile_to_log(
                profile,
                model=self.model,
                serial=serial,
                imperial=units == "imperial",
                sample_interval_s=sample_interval_s,
            )
            for profile in ordered
        ] + [bytes(log) for log in raw_logs]  # oldest first
        records = [
            protocol.ManifestRecord(fingerprint=log[12:16], offset=(i + 1) * DIVE_OFFSET_STEP)
            for i, log in enumerate(self.logs)
        ][::-1]
        for position in sorted(deleted):
            gone = protocol.ManifestRecord(
                fingerprint=bytes(4), offset=0x00F00000 + position, deleted=True
            )
            records.insert(min(position, len(records)), gone)
        self.manifest = records
        self._by_address = {
            PNF_BASE + (i + 1) * DIVE_OFFSET_STEP: log for i, log in enumerate(self.logs)
        }
        self._decoder = protocol.SlipDecoder()
        self._page = 0
        self._blocks: list[bytes] | None = None
        self._sent = 0
        self._last_counter: int | None = None
        self._last_response = b""
        self.local_clock_s: int | None = None

    def held_dives(self) -> list[tuple[DiveProfile, bytes]]:
        """What the unit holds, newest first, as the downloader should report it."""
        held = []
        for log_bytes in self.logs[::-1]:
            dive = logformat.parse_pnf(log_bytes, where="simulated dive")
            held.append(
                (dive_profile(dive, model_name=self.model.name, source="simulate"), log_bytes)
            )
        return held

    def manifest_pages(self) -> list[bytes]:
        size = protocol.MANIFEST_RECORDS
        return [
            protocol.encode_manifest_page(self.manifest[i : i + size])
            for i in range(0, max(len(self.manifest), 1), size)
        ]

    def feed(self, data: bytes) -> list[bytes]:
        """Host bytes in, response frames out (SLIP-encoded). Bad frames get no answer."""
        out = []
        for frame in self._decoder.feed(data):
            if isinstance(frame, protocol.ProtocolError):
                continue
            try:
                payload = protocol.decode_request(frame)
            except protocol.ProtocolError:
                continue
            response = self.handle(payload)
            if response is not None:
                out.append(protocol.encode_response(response))
        return out

    def handle(self, payload: bytes) -> bytes | None:
        """One request payload -> one response payload (None: no answer)."""
        if not payload:
            return None
        service = payload[0]
        if service == protocol.RDBI and len(payload) == 3:
            return self._read(int.from_bytes(payload[1:3], "big"))
        if service == protocol.WDBI and len(payload) >= 3:
            identifier = int.from_bytes(payload[1:3], "big")
            if identifier == protocol.ID_SHUTDOWN:
                self._end_session()
                return None  # the client awaits no reply; the golden device sent none
            if identifier == protocol.ID_LOCAL_CLOCK and len(payload) == 7:
                self.local_clock_s = int.from_bytes(payload[3:7], "big")
            else:
                return protocol.negative_response(service, protocol.NRC_REQUEST_OUT_OF_RANGE)
            return protocol.wdbi_response(identifier)
        if service == protocol.REQUEST_UPLOAD:
            return self._start_upload(payload)
        if service == protocol.TRANSFER_DATA and len(payload) == 2:
            return self._transfer(payload[1])
        if service == protocol.TRANSFER_EXIT:
            if self._blocks is None:
                return protocol.negative_response(service, protocol.NRC_SEQUENCE_ERROR)
            self._blocks = None
            return protocol.exit_response()
        return protocol.negative_response(service, 0x11)  # service not supported

    def _end_session(self) -> None:
        self._page = 0
        self._blocks = None

    def _read(self, identifier: int) -> bytes:
        values = {
            protocol.ID_SERIAL: protocol.encode_serial(self.serial),
            protocol.ID_FIRMWARE: self.firmware_text.encode("ascii")[:12],
            protocol.ID_MODEL: bytes((self.model.number,)),
            protocol.ID_HARDWARE: self.model.hardware_type.to_bytes(2, "big"),
            protocol.ID_LOG_UPLOAD: protocol.encode_log_upload(PNF_BASE),
        }
        if identifier not in values:
            return protocol.negative_response(protocol.RDBI, protocol.NRC_REQUEST_OUT_OF_RANGE)
        if identifier == protocol.ID_SERIAL:
            self._page = 0  # a new session starts by identifying the unit
        return protocol.rdbi_response(identifier, values[identifier])

    def _start_upload(self, payload: bytes) -> bytes:
        try:
            request = protocol.parse_upload_request(payload)
        except protocol.ProtocolError:
            return protocol.negative_response(protocol.REQUEST_UPLOAD, 0x13)
        if request.address == protocol.MANIFEST_ADDRESS and not request.compressed:
            if request.size != protocol.MANIFEST_SIZE:
                return protocol.negative_response(
                    protocol.REQUEST_UPLOAD, protocol.NRC_REQUEST_OUT_OF_RANGE
                )
            pages = self.manifest_pages()
            # A repeated manifest request gets the next page, then pages of FF (§6 step 6).
            page = pages[self._page] if self._page < len(pages) else b"\xff" * len(pages[0])
            self._page += 1
            step = MANIFEST_BLOCK_BYTES
            self._blocks = [page[i : i + step] for i in range(0, len(page), step)]
        elif request.compressed and request.address in self._by_address:
            self._blocks = protocol.compress_dive(self._by_address[request.address])
        else:
            return protocol.negative_response(
                protocol.REQUEST_UPLOAD, protocol.NRC_REQUEST_OUT_OF_RANGE
            )
        self._sent = 0
        self._last_counter = None
        return protocol.upload_response(MAX_BLOCK_BYTE)

    def _transfer(self, counter: int) -> bytes:
        if self._blocks is None:
            return protocol.negative_response(protocol.TRANSFER_DATA, protocol.NRC_SEQUENCE_ERROR)
        if counter == self._last_counter:
            return self._last_response  # repeated request: the same block again [?]
        expected = ((self._last_counter or 0) + 1) & 0xFF
        if counter != expected:
            return protocol.negative_response(
                protocol.TRANSFER_DATA, protocol.NRC_WRONG_BLOCK_COUNTER
            )
        if self._sent >= len(self._blocks):
            return protocol.negative_response(protocol.TRANSFER_DATA, protocol.NRC_SEQUENCE_ERROR)
        response = protocol.transfer_response(counter, self._blocks[self._sent])
        self._sent += 1
        self._last_counter = counter
        self._last_response = response
        return response


def dive_profile(dive: logformat.ParsedDive, *, model_name: str, source: str) -> DiveProfile:
    """A parsed Shearwater log as a DiveProfile (the form written to dive folders)."""
    return DiveProfile(
        stamps_s=np.asarray(dive.stamps_s, dtype=np.float64),
        depth_m=np.asarray(dive.depth_m, dtype=np.float64),
        temperature_c=np.asarray(dive.temperature_c, dtype=np.float64),
        start_iso=stamp_s_to_iso(dive.start_s),
        model=model_name,
        serial="" if dive.serial is None else f"{dive.serial:08X}",
        fingerprint=dive.fingerprint.hex().upper(),
        source=source,
        sample_interval_s=dive.sample_interval_s,
    )


class LineFaults:
    """Applies `FaultOptions` to outgoing response frames (seeded, reproducible)."""

    def __init__(self, faults: FaultOptions) -> None:
        self.faults = faults
        self._rng = random.Random(faults.seed)
        self.packets = 0
        self.bytes_sent = 0
        self.dropped = 0
        self.corrupted = 0
        self.stalled = False

    def before_packet(self) -> None:
        """Sleep here once when the stall point is reached."""
        stall_at = self.faults.stall_after_packets
        if stall_at is not None and not self.stalled and self.packets + 1 >= stall_at:
            self.stalled = True
            time.sleep(self.faults.stall_s)

    def disconnect_now(self) -> bool:
        limit = self.faults.disconnect_after_packets
        byte_limit = self.faults.disconnect_after_bytes
        return (limit is not None and self.packets >= limit) or (
            byte_limit is not None and self.bytes_sent >= byte_limit
        )

    def cut(self, frame: bytes) -> bytes:
        """The part of `frame` that goes out before the cable is pulled (all of it if no
        byte cut is set or it lies beyond this frame); counts what is sent."""
        limit = self.faults.disconnect_after_bytes
        if limit is not None:
            frame = frame[: max(limit - self.bytes_sent, 0)]
        self.bytes_sent += len(frame)
        return frame

    def apply(self, frame: bytes) -> bytes:
        self.packets += 1
        if not (self.faults.drop_rate or self.faults.corrupt_rate):
            return frame
        out = bytearray()
        for byte in frame:
            roll = self._rng.random()
            if roll < self.faults.drop_rate:
                self.dropped += 1
                continue
            if roll < self.faults.drop_rate + self.faults.corrupt_rate:
                self.corrupted += 1
                out.append((byte + self._rng.randrange(1, 256)) & 0xFF)
            else:
                out.append(byte)
        return bytes(out)


def serve_pty(
    device: SimulatedShearwater,
    *,
    faults: FaultOptions | LineFaults | None = None,
    ready: Callable[[str], None] | None = None,
    stop: threading.Event | None = None,
    poll_s: float = 0.05,
) -> None:
    """Serve `device` on a new pseudo-terminal until `stop` is set (or KeyboardInterrupt).

    `faults` may be a `LineFaults`, whose counters then tell what was injected.
    `ready(path)` gets the slave path (e.g. /dev/pts/4) once the pty is raw and serving.
    The unit never talks first; it answers each request frame as it completes.
    """
    line = faults if isinstance(faults, LineFaults) else LineFaults(faults or FaultOptions())
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo, no line editing: bytes pass unchanged
    path = os.ttyname(slave)
    connected = True
    try:
        if ready is not None:
            ready(path)
        while stop is None or not stop.is_set():
            if not connected:
                time.sleep(poll_s)
                continue
            readable, _, _ = select.select([master], [], [], poll_s)
            if not readable:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                continue  # no client has the slave open right now
            for frame in device.feed(data):
                line.before_packet()
                os.write(master, line.cut(line.apply(frame)))
                if line.disconnect_now():
                    log.info(
                        "simulated disconnect after %d packets, %d bytes",
                        line.packets,
                        line.bytes_sent,
                    )
                    os.close(master)
                    os.close(slave)
                    connected = False
                    break
    finally:
        if connected:
            os.close(master)
            os.close(slave)


@contextmanager
def serving_pty(
    device: SimulatedShearwater,
    faults: FaultOptions | LineFaults | None = None,
    *,
    poll_s: float = 0.01,
    start_timeout_s: float = 5.0,
) -> Iterator[str]:
    """Serve `device` on a pseudo-terminal from a background thread; yields its path.

    The thread stops when the block ends. For tests and benchmarks in one process (the
    `dc simulate` command serves from a process of its own).
    """
    stop = threading.Event()
    ready: list[str] = []
    started = threading.Event()

    def on_ready(path: str) -> None:
        ready.append(path)
        started.set()

    thread = threading.Thread(
        target=serve_pty,
        args=(device,),
        kwargs={"faults": faults, "ready": on_ready, "stop": stop, "poll_s": poll_s},
        daemon=True,
    )
    thread.start()
    if not started.wait(start_timeout_s):
        stop.set()
        raise RuntimeError("simulated dive computer: the pty did not start")
    try:
        yield ready[0]
    finally:
        stop.set()
        thread.join(start_timeout_s)
