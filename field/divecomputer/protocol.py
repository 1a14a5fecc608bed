"""Shearwater serial protocol, both sides: SLIP framing, packets, services, compression.

Pure code (no I/O). The downloader (`download.py`) and the simulated device
(`simulator.py`) both use these encoders and decoders, so what one writes the other
reads. Byte layouts follow ../shared/docs/shearwater-protocol.md (sections in comments).
All multi-byte integers are big-endian.
"""

from __future__ import annotations

from dataclasses import dataclass

from shared.errors import DeviceError

# SLIP special bytes (protocol doc §2).
END = 0xC0
ESC = 0xDB
ESC_END = 0xDC
ESC_ESC = 0xDD

# Packet addresses (§3): host FF, device 01.
HOST = 0xFF
DEVICE = 0x01
MAX_PAYLOAD = 254

# Services (§4), UDS-like codes.
RDBI = 0x22
WDBI = 0x2E
REQUEST_UPLOAD = 0x35
TRANSFER_DATA = 0x36
TRANSFER_EXIT = 0x37
NEGATIVE = 0x7F
POSITIVE_OFFSET = 0x40

# Data identifiers (§4.3).
ID_SERIAL = 0x8010
ID_FIRMWARE = 0x8011
ID_HARDWARE = 0x8050
ID_MODEL = 0x8060
ID_LOG_UPLOAD = 0x8021
ID_SHUTDOWN = 0x9020
ID_LOCAL_CLOCK = 0x9030

# Negative response codes (UDS meaning; the client only prints them).
NRC_REQUEST_OUT_OF_RANGE = 0x31
NRC_CONDITIONS_NOT_CORRECT = 0x22
NRC_SEQUENCE_ERROR = 0x24
NRC_WRONG_BLOCK_COUNTER = 0x73

# Memory map (§6, §7).
MANIFEST_ADDRESS = 0xE0000000
MANIFEST_SIZE = 0x600
RECORD_SIZE = 32
MANIFEST_RECORDS = MANIFEST_SIZE // RECORD_SIZE
UNKNOWN_SIZE = 0xFFFFFF
MARKER_VALID = b"\xa5\xc4"
MARKER_DELETED = b"\x5a\x23"
COMPRESSED = 0x10
UNCOMPRESSED = 0x00
ADDRESS_AND_LENGTH_FORMAT = 0x34
MAX_BLOCK_DATA = 252  # 254 payload bytes less `76 NN`
LRE_TOKENS_PER_FULL_BLOCK = MAX_BLOCK_DATA * 8 // 9  # 224
XOR_DISTANCE = 32


class ProtocolError(DeviceError):
    """Bytes from the link break the protocol (bad escape, header, length or reply)."""


class NegativeResponseError(DeviceError):
    """The device answered `7F <service> <code>` (unsupported or refused)."""

    def __init__(self, service: int, code: int) -> None:
        super().__init__(
            f"device refused service 0x{service:02X} (negative response code 0x{code:02X})"
        )
        self.service = service
        self.code = code


# ---------------------------------------------------------------- SLIP (§2)


def slip_encode(packet: bytes) -> bytes:
    """Escape `packet` and end it with one `C0` (no leading `C0`, as the client sends)."""
    out = bytearray()
    for byte in packet:
        if byte == END:
            out += bytes((ESC, ESC_END))
        elif byte == ESC:
            out += bytes((ESC, ESC_ESC))
        else:
            out.append(byte)
    out.append(END)
    return bytes(out)


class SlipDecoder:
    """Collects bytes into frames; `feed` returns complete frames (empty ones skipped).

    A frame with a bad escape (`DB C0` or `DB DB`) is returned as a `ProtocolError`
    instance in the list rather than raised, so the reader can decide to drop it.
    """

    def __init__(self) -> None:
        self._frame = bytearray()
        self._escaped = False
        self._bad: str | None = None

    def reset(self) -> None:
        """Forget a partial frame (after purging the link)."""
        self._frame.clear()
        self._escaped = False
        self._bad = None

    @property
    def pending(self) -> int:
        """Bytes of an unfinished frame held so far."""
        return len(self._frame)

    def feed(self, data: bytes) -> list[bytes | ProtocolError]:
        frames: list[bytes | ProtocolError] = []
        for byte in data:
            if self._escaped:
                self._escaped = False
                if byte == ESC_END:
                    self._frame.append(END)
                elif byte == ESC_ESC:
                    self._frame.append(ESC)
                elif byte in (END, ESC):
                    # The reference client gives up on these; mark the frame bad.
                    self._bad = f"SLIP escape followed by 0x{byte:02X}"
                    if byte == END:
                        frames.append(ProtocolError(self._bad))
                        self.reset()
                else:
                    self._frame.append(byte)  # kept as is (§2)
                continue
            if byte == END:
                if self._bad is not None:
                    frames.append(ProtocolError(self._bad))
                elif self._frame:
                    frames.append(bytes(self._frame))
                self.reset()
            elif byte == ESC:
                self._escaped = True
            else:
                self._frame.append(byte)
        return frames


# ---------------------------------------------------------------- packets (§3)


def _pack(destination: int, source: int, payload: bytes) -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return bytes((destination, source, len(payload) + 1, 0)) + payload


def encode_request(payload: bytes) -> bytes:
    """Host -> device wire bytes: SLIP(`FF 01 LL 00 payload`) + `C0`."""
    return slip_encode(_pack(HOST, DEVICE, payload))


def encode_response(payload: bytes) -> bytes:
    """Device -> host wire bytes: SLIP(`01 FF LL 00 payload`) + `C0`."""
    return slip_encode(_pack(DEVICE, HOST, payload))


def _unpack(frame: bytes, destination: int, source: int, what: str) -> bytes:
    if len(frame) < 4:
        raise ProtocolError(f"{what} frame of {len(frame)} bytes is shorter than its header")
    if frame[0] != destination or frame[1] != source or frame[3] != 0:
        raise ProtocolError(
            f"{what} header {frame[:4].hex(' ')} (expected {destination:02x} {source:02x} .. 00)"
        )
    length = frame[2]
    if length < 1 or len(frame) != length + 3:
        raise ProtocolError(
            f"{what} length byte {length} does not match a frame of {len(frame)} bytes"
        )
    return frame[4:]


def decode_response(frame: bytes) -> bytes:
    """Payload of a device -> host frame (SLIP already undone); checks header and length."""
    return _unpack(frame, DEVICE, HOST, "response")


def decode_request(frame: bytes) -> bytes:
    """Payload of a host -> device frame (SLIP already undone)."""
    return _unpack(frame, HOST, DEVICE, "request")


# ---------------------------------------------------------------- services (§4)


def rdbi_request(identifier: int) -> bytes:
    return bytes((RDBI,)) + identifier.to_bytes(2, "big")


def rdbi_response(identifier: int, data: bytes) -> bytes:
    return bytes((RDBI + POSITIVE_OFFSET,)) + identifier.to_bytes(2, "big") + data


def wdbi_request(identifier: int, data: bytes) -> bytes:
    return bytes((WDBI,)) + identifier.to_bytes(2, "big") + data


def wdbi_response(identifier: int) -> bytes:
    return bytes((WDBI + POSITIVE_OFFSET,)) + identifier.to_bytes(2, "big")


def negative_response(service: int, code: int) -> bytes:
    return bytes((NEGATIVE, service, code))


def check_negative(payload: bytes, service: int) -> None:
    """Raise `NegativeResponseError` if `payload` is exactly `7F <service> NN`."""
    if len(payload) == 3 and payload[0] == NEGATIVE and payload[1] == service:
        raise NegativeResponseError(service, payload[2])


def parse_rdbi_response(payload: bytes, identifier: int) -> bytes:
    """Data of a `62 IH IL data` answer to RDBI `identifier`."""
    check_negative(payload, RDBI)
    expected = rdbi_response(identifier, b"")
    if payload[:3] != expected:
        raise ProtocolError(
            f"unexpected answer {payload[:3].hex(' ')} to RDBI 0x{identifier:04X} "
            f"(expected {expected.hex(' ')})"
        )
    return payload[3:]


def parse_wdbi_response(payload: bytes, identifier: int) -> None:
    check_negative(payload, WDBI)
    if payload != wdbi_response(identifier):
        raise ProtocolError(f"unexpected answer {payload.hex(' ')} to WDBI 0x{identifier:04X}")


@dataclass(frozen=True)
class UploadRequest:
    """RequestUpload (`35 CF 34 A3..A0 S2..S0`): what memory the host asks for."""

    address: int
    size: int
    compressed: bool


def upload_request(address: int, size: int, *, compressed: bool) -> bytes:
    return (
        bytes((REQUEST_UPLOAD, COMPRESSED if compressed else UNCOMPRESSED))
        + bytes((ADDRESS_AND_LENGTH_FORMAT,))
        + address.to_bytes(4, "big")
        + size.to_bytes(3, "big")
    )


def parse_upload_request(payload: bytes) -> UploadRequest:
    if (
        len(payload) != 10
        or payload[0] != REQUEST_UPLOAD
        or payload[1] not in (COMPRESSED, UNCOMPRESSED)
        or payload[2] != ADDRESS_AND_LENGTH_FORMAT
    ):
        raise ProtocolError(f"malformed RequestUpload {payload.hex(' ')}")
    return UploadRequest(
        address=int.from_bytes(payload[3:7], "big"),
        size=int.from_bytes(payload[7:10], "big"),
        compressed=payload[1] == COMPRESSED,
    )


def upload_response(max_block: int) -> bytes:
    return bytes((REQUEST_UPLOAD + POSITIVE_OFFSET, 0x10, max_block))


def parse_upload_response(payload: bytes) -> int:
    """The device's `MB` byte from `75 10 MB` (probably its largest block length)."""
    check_negative(payload, REQUEST_UPLOAD)
    if len(payload) != 3 or payload[0] != 0x75 or payload[1] != 0x10 or payload[2] > 0xFE:
        raise ProtocolError(f"unexpected answer {payload.hex(' ')} to RequestUpload")
    return payload[2]


def transfer_request(counter: int) -> bytes:
    return bytes((TRANSFER_DATA, counter & 0xFF))


def transfer_response(counter: int, data: bytes) -> bytes:
    return bytes((TRANSFER_DATA + POSITIVE_OFFSET, counter & 0xFF)) + data


def parse_transfer_response(payload: bytes, counter: int) -> bytes:
    """Data of `76 NN data`; NN must echo the request."""
    check_negative(payload, TRANSFER_DATA)
    if len(payload) < 2 or payload[0] != 0x76:
        raise ProtocolError(f"unexpected answer {payload[:2].hex(' ')} to TransferData")
    if payload[1] != counter & 0xFF:
        raise ProtocolError(
            f"TransferData answer for block {payload[1]} (expected {counter & 0xFF})"
        )
    return payload[2:]


def exit_request() -> bytes:
    return bytes((TRANSFER_EXIT,))


def exit_response() -> bytes:
    return bytes((TRANSFER_EXIT + POSITIVE_OFFSET, 0x00))


def parse_exit_response(payload: bytes) -> None:
    check_negative(payload, TRANSFER_EXIT)
    if payload != exit_response():
        raise ProtocolError(f"unexpected answer {payload.hex(' ')} to RequestTransferExit")


def shutdown_request() -> bytes:
    """WDBI 0x9020 = 00: end of session; the client sends it and awaits no answer."""
    return wdbi_request(ID_SHUTDOWN, b"\x00")


# ---------------------------------------------------------------- identity (§4.3)


def encode_serial(serial: int) -> bytes:
    return f"{serial:08X}".encode("ascii")


def decode_serial(data: bytes) -> int:
    """8 ASCII hex digits -> the 32-bit serial number."""
    text = data.decode("ascii", errors="replace")
    if len(data) != 8 or any(c not in "0123456789abcdefABCDEF" for c in text):
        raise ProtocolError(f"serial number {data!r} is not 8 hex digits")
    return int(text, 16)


def decode_firmware(data: bytes) -> int:
    """Firmware text "V92 Classic" -> 92 (skip the first character, then decimal digits)."""
    if len(data) > 12:
        raise ProtocolError(f"firmware text of {len(data)} bytes (at most 12)")
    digits = ""
    for char in data[1:].decode("ascii", errors="replace"):
        if not char.isdigit():
            break
        digits += char
    return int(digits) if digits else 0


@dataclass(frozen=True)
class LogUploadInfo:
    """Answer to RDBI 0x8021: the dive-log base address and the log format it names."""

    base_address: int
    dive_base_address: int
    log_format: str  # "pnf", "pnf-early", "legacy", "predator"


_LOG_FORMATS = {
    0x80000000: (0x80000000, "pnf"),
    0x90000000: (0xC0000000, "pnf-early"),
    0xC0000000: (0xC0000000, "legacy"),
    0xDD000000: (0xC0000000, "predator"),
}


def encode_log_upload(base_address: int) -> bytes:
    # Bytes 0 and 5..8 are not read by the client; 01 and zeros as in the reference fake.
    return b"\x01" + base_address.to_bytes(4, "big") + b"\x00" * 4


def decode_log_upload(data: bytes) -> LogUploadInfo:
    if len(data) != 9:
        raise ProtocolError(f"log-upload information of {len(data)} bytes (expected 9)")
    base = int.from_bytes(data[1:5], "big")
    if base not in _LOG_FORMATS:
        raise ProtocolError(f"unknown logbook format: base address 0x{base:08X}")
    dive_base, name = _LOG_FORMATS[base]
    return LogUploadInfo(base_address=base, dive_base_address=dive_base, log_format=name)


# ---------------------------------------------------------------- manifest (§7)


@dataclass(frozen=True)
class ManifestRecord:
    """One 32-byte manifest record: a dive (valid or deleted) and where it is stored."""

    fingerprint: bytes  # 4 bytes, the dive start time (dive bytes 12..15)
    offset: int  # from the dive base address
    deleted: bool = False


def encode_manifest_page(records: list[ManifestRecord]) -> bytes:
    """A 0x600-byte page: records, then `FF` filling (end of list)."""
    if len(records) > MANIFEST_RECORDS:
        raise ValueError(f"{len(records)} records do not fit one page of {MANIFEST_RECORDS}")
    page = bytearray(b"\xff" * MANIFEST_SIZE)
    for index, record in enumerate(records):
        raw = bytearray(RECORD_SIZE)
        raw[0:2] = MARKER_DELETED if record.deleted else MARKER_VALID
        raw[4:8] = record.fingerprint
        raw[20:24] = record.offset.to_bytes(4, "big")
        page[index * RECORD_SIZE : (index + 1) * RECORD_SIZE] = raw
    return bytes(page)


def decode_manifest_page(page: bytes) -> tuple[list[ManifestRecord], bool]:
    """Records of one page (valid and deleted, in order) and whether the page is full.

    A full page (48 valid or deleted records) means the host must ask for the next one.
    Unlike the reference client, deleted records before valid ones lose nothing here.
    """
    if len(page) != MANIFEST_SIZE:
        raise ProtocolError(f"manifest page of {len(page)} bytes (expected {MANIFEST_SIZE})")
    records: list[ManifestRecord] = []
    for index in range(MANIFEST_RECORDS):
        raw = page[index * RECORD_SIZE : (index + 1) * RECORD_SIZE]
        marker = raw[0:2]
        if marker not in (MARKER_VALID, MARKER_DELETED):
            return records, False
        records.append(
            ManifestRecord(
                fingerprint=bytes(raw[4:8]),
                offset=int.from_bytes(raw[20:24], "big"),
                deleted=marker == MARKER_DELETED,
            )
        )
    return records, True


# ---------------------------------------------------------------- compression (§5)


def xor_encode(plain: bytes) -> bytes:
    """Device side: `coded[i] = plain[i] ^ plain[i-32]` for i >= 32."""
    coded = bytearray(plain)
    for i in range(XOR_DISTANCE, len(plain)):
        coded[i] = plain[i] ^ plain[i - XOR_DISTANCE]
    return bytes(coded)


def xor_decode(coded: bytes) -> bytes:
    """Host side: `plain[i] = coded[i] ^ plain[i-32]`, upwards from i = 32."""
    plain = bytearray(coded)
    for i in range(XOR_DISTANCE, len(plain)):
        plain[i] ^= plain[i - XOR_DISTANCE]
    return bytes(plain)


def lre_decode_block(block: bytes) -> tuple[bytes, bool]:
    """Decode one block of 9-bit tokens; returns (bytes, end token reached).

    Raises `ProtocolError` when the block length is not a multiple of 9 bytes.
    """
    if len(block) % 9:
        raise ProtocolError(
            f"compressed block of {len(block)} bytes (decompression error, LRE phase: "
            "expected a multiple of 9)"
        )
    value = int.from_bytes(block, "big")
    tokens = len(block) * 8 // 9
    out = bytearray()
    for index in range(tokens):
        token = (value >> (9 * (tokens - 1 - index))) & 0x1FF
        if token & 0x100:
            out.append(token & 0xFF)
        elif token == 0:
            return bytes(out), True
        else:
            out += bytes(token)
    return bytes(out), False


def _lre_tokens(data: bytes) -> list[int]:
    tokens: list[int] = []
    run = 0
    for byte in data:
        if byte == 0:
            run += 1
            if run == 255:
                tokens.append(run)
                run = 0
            continue
        if run:
            tokens.append(run)
            run = 0
        tokens.append(0x100 | byte)
    if run:
        tokens.append(run)
    return tokens


def _pack_tokens(tokens: list[int]) -> bytes:
    value = 0
    for token in tokens:
        value = (value << 9) | token
    return value.to_bytes(len(tokens) * 9 // 8, "big")


def lre_encode_blocks(
    data: bytes, *, tokens_per_block: int = LRE_TOKENS_PER_FULL_BLOCK
) -> list[bytes]:
    """Run-length code `data` into blocks of 9-bit tokens (device side).

    Zero runs become run tokens; every other byte a literal. Every block but the last
    holds exactly `tokens_per_block` real tokens (a multiple of 8); the last holds the
    rest, the end token and zero padding up to a multiple of 8 tokens.
    """
    if tokens_per_block % 8 or not 8 <= tokens_per_block <= LRE_TOKENS_PER_FULL_BLOCK:
        raise ValueError(f"tokens_per_block {tokens_per_block} must be a multiple of 8, 8..224")
    tokens = _lre_tokens(data)
    blocks = []
    start = 0
    # A non-final block cannot be padded (a zero token means "end"), so the final block
    # must have room for the end token: split only while more than a block remains.
    while len(tokens) - start >= tokens_per_block:
        blocks.append(_pack_tokens(tokens[start : start + tokens_per_block]))
        start += tokens_per_block
    last = [*tokens[start:], 0]
    last += [0] * (-len(last) % 8)
    blocks.append(_pack_tokens(last))
    return blocks


def compress_dive(plain: bytes) -> list[bytes]:
    """Device side of §5: XOR-code the dive, then LRE-code it into transfer blocks."""
    return lre_encode_blocks(xor_encode(plain))


def decompress_blocks(blocks: list[bytes]) -> bytes:
    """Host side of §5: LRE-decode each block, join, then undo the XOR step.

    Raises `ProtocolError` when no block holds the end token.
    """
    joined = bytearray()
    for block in blocks:
        data, ended = lre_decode_block(block)
        joined += data
        if ended:
            return xor_decode(bytes(joined))
    raise ProtocolError("compressed dive ended without the LRE end-of-stream token")
