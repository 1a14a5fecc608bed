"""Download new dives from a Shearwater (Petrel family) over any pyserial URL.

`download_dives(port, out_dir, options)` identifies the unit, reads the dive list,
downloads the dives not yet in the dive folder, decompresses and parses them, and writes
each complete dive (CSV, raw log bytes, `dives.json` entry) as soon as it is checked.
The port is anything `serial.serial_for_url` opens: a device path, `rfc2217://`,
`socket://` (a Bluetooth-serial bridge works the same way).

Robustness: the link has no checksum, so every reply is checked (header, length, echo,
block counter, compression) and a bad or missing reply is retried with backoff: first
the same block (`36 NN` again), then the whole transfer, then a new session (the
manifest cannot be re-read mid-session: a repeated manifest request means "next page").
After the last attempt a `DeviceError` says what failed; dives already written stay, and
a re-run skips them. `verify=True` also reads every reply until two reads agree, which
catches corruption that keeps the framing intact.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

from field.divecomputer import logformat, protocol
from field.divecomputer.simulator import MODELS, dive_profile
from shared.errors import DeviceError, InputError
from shared.formats.diveprofile import read_dive_index, write_dive
from shared.fsutil import write_text_atomic
from shared.progress import progress_bar

log = logging.getLogger(__name__)

STATE_NAME = "download-state.json"
MAX_FRAME_BYTES = 4 + protocol.MAX_PAYLOAD  # decoded: header + largest payload
T = TypeVar("T")


class Transport(Protocol):
    """The part of `serial.Serial` the downloader uses (a fake can stand in for tests)."""

    timeout: float | None

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    def reset_input_buffer(self) -> None: ...

    def reset_output_buffer(self) -> None: ...

    def close(self) -> None: ...


@dataclass(kw_only=True)
class DownloadOptions:
    """How to talk to the unit.

    expected_model: a model key (`perdix-ai`, `petrel2`, ...); a different unit is an error.
    read_timeout_s: silence after which a reply counts as lost (the reference client: 3 s).
    settle_s: wait after opening the port before purging it (the reference client: 0.3 s).
    block_retries: re-requests of one reply before restarting the transfer.
    transfer_retries: restarts of one dive transfer before starting a new session.
    session_retries: new sessions (port reopened) before giving up with DeviceError.
    backoff_s: first pause before a retry, doubled each time up to backoff_max_s.
    verify: read every reply until two reads agree (doubles the traffic; for noisy links).
    fingerprint: 8 hex digits; download only dives newer than this one (default: the
        newest dive of this unit already downloaded into the folder).
    """

    expected_model: str | None = None
    baudrate: int = 115_200
    read_timeout_s: float = 3.0
    settle_s: float = 0.3
    block_retries: int = 4
    transfer_retries: int = 3
    session_retries: int = 3
    backoff_s: float = 0.25
    backoff_max_s: float = 4.0
    verify: bool = False
    fingerprint: str | None = None


@dataclass
class DeviceIdentity:
    """Who answered: serial number, firmware, model number and the log format it uses."""

    serial: int
    firmware: int
    firmware_text: str
    model_number: int
    model_name: str
    log_upload: protocol.LogUploadInfo

    @property
    def serial_text(self) -> str:
        return f"{self.serial:08X}"


@dataclass
class DownloadResult:
    identity: DeviceIdentity | None
    written: list[Path] = field(default_factory=list)
    already_present: int = 0
    listed: int = 0


class LinkLostError(DeviceError):
    """The port went away (unplugged, closed, out of range)."""


class _RetryError(Exception):
    """A reply was bad or missing; the caller retries (wraps the cause)."""


def open_serial(port: str, *, baudrate: int, poll_s: float) -> Transport:
    """Open `port` with pyserial (device path or URL), 8N1, no flow control."""
    import serial

    try:
        transport: Transport = serial.serial_for_url(
            port,
            baudrate=baudrate,
            bytesize=serial.EIGHTBITS,
            parity=serial.PARITY_NONE,
            stopbits=serial.STOPBITS_ONE,
            timeout=poll_s,
            write_timeout=5.0,
        )
    except (serial.SerialException, OSError, ValueError) as error:
        raise LinkLostError(f"{port}: cannot open ({error})") from None
    return transport


def _link_errors() -> tuple[type[BaseException], ...]:
    import serial

    return (serial.SerialException, OSError)


class ShearwaterLink:
    """Request/reply over one open transport, with per-reply retries."""

    def __init__(self, transport: Transport, options: DownloadOptions, port: str) -> None:
        self.transport = transport
        self.options = options
        self.port = port
        self.decoder = protocol.SlipDecoder()
        self._errors = _link_errors()

    def purge(self) -> None:
        try:
            self.transport.reset_input_buffer()
            self.transport.reset_output_buffer()
        except self._errors as error:
            raise LinkLostError(f"{self.port}: link lost ({error})") from None
        self.decoder.reset()

    def send(self, payload: bytes) -> None:
        try:
            self.transport.write(protocol.encode_request(payload))
        except self._errors as error:
            raise LinkLostError(f"{self.port}: link lost while writing ({error})") from None

    def receive(self) -> bytes:
        """The payload of the next reply frame; `_RetryError` on silence or a bad frame."""
        deadline = time.monotonic() + self.options.read_timeout_s
        while True:
            try:
                waiting = self.transport.in_waiting
                data = self.transport.read(max(1, waiting))
            except self._errors as error:
                raise LinkLostError(f"{self.port}: link lost while reading ({error})") from None
            if data:
                frames = self.decoder.feed(data)
                if frames:
                    frame = frames[0]  # one request, one reply: more is stale noise
                    if isinstance(frame, protocol.ProtocolError):
                        raise _RetryError(str(frame))
                    try:
                        return protocol.decode_response(frame)
                    except protocol.ProtocolError as error:
                        raise _RetryError(str(error)) from None
                if self.decoder.pending > MAX_FRAME_BYTES:
                    raise _RetryError(f"frame longer than {MAX_FRAME_BYTES} bytes (lost end byte)")
            if time.monotonic() > deadline:
                raise _RetryError(f"no reply within {self.options.read_timeout_s} s")

    def backoff(self, attempt: int) -> None:
        time.sleep(min(self.options.backoff_s * 2**attempt, self.options.backoff_max_s))
        self.purge()

    def transact(
        self, payload: bytes, parse: Callable[[bytes], T], *, what: str, repeatable: bool = True
    ) -> T:
        """Send `payload`, parse the reply; retry bad replies (`verify`: until two agree).

        A request that is not `repeatable` (the manifest request: asking again means
        "next page") is sent once and never verified.
        """
        seen: Counter[Any] = Counter()
        verify = self.options.verify and repeatable
        attempts = self.options.block_retries + 1 if repeatable else 1
        if verify:
            attempts = 2 * attempts + 2
        last_error = ""
        for attempt in range(attempts):
            if attempt:
                self.backoff(attempt - 1)
            self.send(payload)
            try:
                value = parse(self.receive())
            except _RetryError as error:
                last_error = str(error)
                log.debug("%s: %s (attempt %d)", what, error, attempt + 1)
                continue
            except protocol.NegativeResponseError:
                raise
            except protocol.ProtocolError as error:
                last_error = str(error)
                log.debug("%s: %s (attempt %d)", what, error, attempt + 1)
                continue
            if not verify:
                return value
            seen[value] += 1
            if seen[value] >= 2:
                return value
            last_error = "replies disagree"
        raise _RetryError(f"{what}: {last_error} after {attempts} requests")


def identify(link: ShearwaterLink) -> DeviceIdentity:
    """Serial, firmware, model and log-upload information, in the reference client's order."""

    def rdbi(identifier: int) -> Callable[[bytes], bytes]:
        return lambda payload: protocol.parse_rdbi_response(payload, identifier)

    try:
        serial = link.transact(
            protocol.rdbi_request(protocol.ID_SERIAL),
            lambda p: protocol.decode_serial(rdbi(protocol.ID_SERIAL)(p)),
            what="serial number",
        )
        firmware_raw = link.transact(
            protocol.rdbi_request(protocol.ID_FIRMWARE),
            lambda p: _firmware(rdbi(protocol.ID_FIRMWARE)(p)),
            what="firmware",
        )
        model_data = link.transact(
            protocol.rdbi_request(protocol.ID_MODEL), rdbi(protocol.ID_MODEL), what="model"
        )
        log_upload = link.transact(
            protocol.rdbi_request(protocol.ID_LOG_UPLOAD),
            lambda p: protocol.decode_log_upload(rdbi(protocol.ID_LOG_UPLOAD)(p)),
            what="log-upload information",
        )
    except protocol.NegativeResponseError as error:
        raise DeviceError(f"{link.port}: unit refused an identity read ({error})") from None
    if len(model_data) != 1:
        raise DeviceError(f"{link.port}: model answer of {len(model_data)} bytes (expected 1)")
    number = model_data[0]
    name = _model_name(link, number)
    return DeviceIdentity(
        serial=serial,
        firmware=firmware_raw[0],
        firmware_text=firmware_raw[1],
        model_number=number,
        model_name=name,
        log_upload=log_upload,
    )


def _firmware(data: bytes) -> tuple[int, str]:
    return protocol.decode_firmware(data), data.decode("ascii", errors="replace")


def _model_name(link: ShearwaterLink, number: int) -> str:
    candidates = [model for model in MODELS.values() if model.number == number]
    if not candidates:
        return f"Shearwater model {number}"
    if len(candidates) == 1:
        return candidates[0].name
    # Petrel and Petrel 2 share model number 3; only the hardware type tells them apart.
    try:
        hardware = link.transact(
            protocol.rdbi_request(protocol.ID_HARDWARE),
            lambda p: protocol.parse_rdbi_response(p, protocol.ID_HARDWARE),
            what="hardware type",
        )
    except (protocol.NegativeResponseError, _RetryError):
        return " / ".join(model.name for model in candidates)
    for model in candidates:
        if model.hardware_type.to_bytes(2, "big") == hardware:
            return model.name
    return " / ".join(model.name for model in candidates)


def _upload(
    link: ShearwaterLink,
    address: int,
    size: int,
    *,
    compressed: bool,
    what: str,
    on_block: Callable[[int], None] | None = None,
) -> list[bytes]:
    """One RequestUpload / TransferData... / RequestTransferExit cycle; returns the blocks."""
    link.transact(
        protocol.upload_request(address, size, compressed=compressed),
        protocol.parse_upload_response,
        what=f"{what} upload request",
        repeatable=address != protocol.MANIFEST_ADDRESS,
    )
    blocks: list[bytes] = []
    received = 0
    counter = 1
    while True:
        this_counter = counter

        def parse(
            payload: bytes, this_counter: int = this_counter, received: int = received
        ) -> bytes:
            data = protocol.parse_transfer_response(payload, this_counter)
            if compressed:
                protocol.lre_decode_block(data)  # raises on a length that is not 9k
            elif received + len(data) > size:
                raise protocol.ProtocolError(
                    f"{what}: blocks add up past the requested {size} bytes"
                )
            return data

        data = link.transact(
            protocol.transfer_request(counter), parse, what=f"{what} block {counter}"
        )
        blocks.append(data)
        received += len(data)
        if on_block is not None:
            on_block(len(data))
        counter = (counter + 1) & 0xFF
        if compressed and protocol.lre_decode_block(data)[1]:
            break
        if not compressed and received == size:
            break
        if not data:
            raise _RetryError(f"{what}: empty block before the end of the transfer")
    link.send(protocol.exit_request())
    try:
        protocol.parse_exit_response(link.receive())
    except (_RetryError, protocol.ProtocolError) as error:
        # The data is complete; a lost exit reply only needs a clean line for what follows.
        log.debug("%s: exit reply: %s", what, error)
        link.backoff(0)
    return blocks


def read_manifest(
    link: ShearwaterLink, *, stop_fingerprint: bytes | None
) -> list[protocol.ManifestRecord]:
    """The valid dives, newest first, down to (not including) `stop_fingerprint`."""
    kept: list[protocol.ManifestRecord] = []
    for page_number in range(1, 1000):
        blocks = _upload(
            link,
            protocol.MANIFEST_ADDRESS,
            protocol.MANIFEST_SIZE,
            compressed=False,
            what=f"manifest page {page_number}",
        )
        records, full = protocol.decode_manifest_page(b"".join(blocks))
        for record in records:
            if record.deleted:
                continue
            if stop_fingerprint is not None and record.fingerprint == stop_fingerprint:
                return kept
            kept.append(record)
        if not full:
            return kept
    raise DeviceError(f"{link.port}: the dive list never ends (1000 full pages)")


def _state_key(identity: DeviceIdentity) -> str:
    return f"shearwater-{identity.serial_text}"


def _read_state(out_dir: Path) -> dict[str, Any]:
    path = out_dir / STATE_NAME
    if not path.exists():
        return {}
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: expected an object of units")
    return state


def _parse_fingerprint(text: str, where: str) -> bytes:
    try:
        value = bytes.fromhex(text)
    except ValueError:
        value = b""
    if len(value) != 4:
        raise InputError(f"{where}: fingerprint {text!r} is not 8 hex digits")
    return value


def download_dives(
    port: str,
    out_dir: Path | str,
    options: DownloadOptions,
    *,
    open_transport: Callable[[str], Transport] | None = None,
) -> DownloadResult:
    """Download the unit's new dives into the dive folder `out_dir`.

    `open_transport(port)` opens the link (default: pyserial `serial_for_url` at
    `options.baudrate`). Returns what was written. Raises `DeviceError` when the unit
    cannot be read after the configured retries (dives written before stay valid).
    """
    out_dir = Path(out_dir)
    if options.expected_model is not None and options.expected_model not in MODELS:
        raise InputError(
            f"--model {options.expected_model!r}: unknown (known: {', '.join(MODELS)})"
        )
    opener = open_transport or (
        lambda url: open_serial(url, baudrate=options.baudrate, poll_s=0.05)
    )
    result = DownloadResult(identity=None)
    last_error: Exception | None = None
    for session in range(options.session_retries + 1):
        if session:
            pause = min(options.backoff_s * 2**session, options.backoff_max_s)
            log.info("retrying in %.1f s (%s)", pause, last_error)
            time.sleep(pause)
        try:
            transport = opener(port)
        except LinkLostError as error:
            last_error = error
            continue
        link = ShearwaterLink(transport, options, port)
        try:
            _session(link, out_dir, options, result)
            return result
        except (_RetryError, LinkLostError, protocol.ProtocolError) as error:
            last_error = error
        finally:
            _close(link)
    saved = len(result.written)
    raise DeviceError(
        f"{port}: download failed after {options.session_retries + 1} sessions "
        f"({last_error}); {saved} complete dive(s) saved in {out_dir}, re-run to resume"
    )


def _close(link: ShearwaterLink) -> None:
    # The reference client always ends with WDBI 0x9020 = 00 and waits for no reply.
    try:
        link.send(protocol.shutdown_request())
        time.sleep(0.01)
    except LinkLostError:
        pass
    with contextlib.suppress(*link._errors):
        link.transport.close()


def _session(
    link: ShearwaterLink, out_dir: Path, options: DownloadOptions, result: DownloadResult
) -> None:
    time.sleep(options.settle_s)
    link.purge()
    identity = identify(link)
    result.identity = identity
    if options.expected_model is not None:
        expected = MODELS[options.expected_model]
        if expected.number != identity.model_number:
            raise DeviceError(
                f"{link.port}: expected a {expected.name} (model {expected.number}), the unit "
                f"says {identity.model_name} (model {identity.model_number})"
            )
    if identity.log_upload.log_format not in ("pnf", "pnf-early"):
        raise DeviceError(
            f"{link.port}: log format {identity.log_upload.log_format} is not supported "
            "(Petrel Native Format only)"
        )
    state = _read_state(out_dir)
    key = _state_key(identity)
    stop_text = options.fingerprint or state.get(key, {}).get("newest_fingerprint")
    stop = None if stop_text is None else _parse_fingerprint(stop_text, str(out_dir / STATE_NAME))
    records = read_manifest(link, stop_fingerprint=stop)
    result.listed = len(records)
    present = {
        entry.get("fingerprint")
        for entry in read_dive_index(out_dir)
        if entry.get("serial") == identity.serial_text
    }
    todo = [r for r in records if r.fingerprint.hex().upper() not in present]
    result.already_present = len(records) - len(todo)
    bar = progress_bar(total=len(todo), desc=f"{identity.model_name} dives", unit="dive")
    try:
        for record in todo:
            _download_one(link, identity, record, out_dir, options, result)
            bar.update(1)
    finally:
        bar.close()
    if records:
        state[key] = {
            "model": identity.model_name,
            "newest_fingerprint": records[0].fingerprint.hex().upper(),
        }
        write_text_atomic(out_dir / STATE_NAME, json.dumps(state, indent=2) + "\n", overwrite=True)


def _download_one(
    link: ShearwaterLink,
    identity: DeviceIdentity,
    record: protocol.ManifestRecord,
    out_dir: Path,
    options: DownloadOptions,
    result: DownloadResult,
) -> None:
    address = identity.log_upload.dive_base_address + record.offset
    fingerprint = record.fingerprint.hex().upper()
    where = f"{link.port} dive {fingerprint}"
    last_error: Exception | None = None
    for attempt in range(options.transfer_retries + 1):
        if attempt:
            link.backoff(attempt)
        try:
            blocks = _upload(link, address, protocol.UNKNOWN_SIZE, compressed=True, what=where)
            raw = protocol.decompress_blocks(blocks)
            dive = logformat.parse_pnf(raw, where=where)
            logformat.check_dive(
                dive, fingerprint=record.fingerprint, serial=identity.serial, where=where
            )
        except protocol.NegativeResponseError as error:
            raise DeviceError(f"{where}: {error}") from None
        except (_RetryError, protocol.ProtocolError, InputError) as error:
            last_error = error
            log.debug("%s: %s (transfer attempt %d)", where, error, attempt + 1)
            continue
        profile = dive_profile(dive, model_name=identity.model_name, source=f"download {link.port}")
        profile.serial = identity.serial_text
        result.written.append(write_dive(out_dir, profile, raw=raw))
        return
    raise _RetryError(f"{where}: {last_error}")
