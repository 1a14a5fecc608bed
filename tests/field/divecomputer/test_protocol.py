"""Protocol encoders/decoders against the test vectors of shearwater-protocol.md §11."""

from __future__ import annotations

import random

import pytest

from field.divecomputer import protocol as p


def wire(text: str) -> bytes:
    return bytes.fromhex(text)


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (p.rdbi_request(p.ID_SERIAL), "FF 01 04 00 22 80 10 C0"),
        (p.rdbi_request(p.ID_FIRMWARE), "FF 01 04 00 22 80 11 C0"),
        (p.rdbi_request(p.ID_MODEL), "FF 01 04 00 22 80 60 C0"),
        (p.rdbi_request(p.ID_LOG_UPLOAD), "FF 01 04 00 22 80 21 C0"),
        (
            p.upload_request(p.MANIFEST_ADDRESS, p.MANIFEST_SIZE, compressed=False),
            "FF 01 0B 00 35 00 34 E0 00 00 00 00 06 00 C0",
        ),
        (
            p.upload_request(0x80020000, p.UNKNOWN_SIZE, compressed=True),
            "FF 01 0B 00 35 10 34 80 02 00 00 FF FF FF C0",
        ),
        (
            p.upload_request(0x80001240, p.UNKNOWN_SIZE, compressed=True),
            "FF 01 0B 00 35 10 34 80 00 12 40 FF FF FF C0",
        ),
        (p.transfer_request(1), "FF 01 03 00 36 01 C0"),
        (p.transfer_request(2), "FF 01 03 00 36 02 C0"),
        (p.exit_request(), "FF 01 02 00 37 C0"),
        (p.shutdown_request(), "FF 01 05 00 2E 90 20 00 C0"),
        (
            p.wdbi_request(p.ID_LOCAL_CLOCK, (0x6B021CD7).to_bytes(4, "big")),
            "FF 01 08 00 2E 90 30 6B 02 1C D7 C0",
        ),
    ],
)
def test_requests_on_the_wire(payload: bytes, expected: str) -> None:
    assert p.encode_request(payload) == wire(expected)
    frames = p.SlipDecoder().feed(wire(expected))
    assert frames == [wire(expected)[:-1]]
    assert isinstance(frames[0], bytes)
    assert p.decode_request(frames[0]) == payload


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (
            p.rdbi_response(p.ID_SERIAL, b"1234ABCD"),
            "01 FF 0C 00 62 80 10 31 32 33 34 41 42 43 44 C0",
        ),
        (p.rdbi_response(p.ID_FIRMWARE, b"V92"), "01 FF 07 00 62 80 11 56 39 32 C0"),
        (p.rdbi_response(p.ID_MODEL, b"\x06"), "01 FF 05 00 62 80 60 06 C0"),
        (
            p.rdbi_response(p.ID_LOG_UPLOAD, p.encode_log_upload(0x80000000)),
            "01 FF 0D 00 62 80 21 01 80 00 00 00 00 00 00 00 C0",
        ),
        (p.upload_response(0xFC), "01 FF 04 00 75 10 FC C0"),
        (p.exit_response(), "01 FF 03 00 77 00 C0"),
        (p.negative_response(p.RDBI, 0x31), "01 FF 04 00 7F 22 31 C0"),
        (p.wdbi_response(p.ID_LOCAL_CLOCK), "01 FF 04 00 6E 90 30 C0"),
        (p.transfer_response(1, wire("C0 DB 00")), "01 FF 06 00 76 01 DB DC DB DD 00 C0"),
    ],
)
def test_responses_on_the_wire(payload: bytes, expected: str) -> None:
    assert p.encode_response(payload) == wire(expected)
    (frame,) = p.SlipDecoder().feed(wire(expected))
    assert isinstance(frame, bytes)
    assert p.decode_response(frame) == payload


def test_identity_decoders() -> None:
    assert p.decode_serial(b"1234ABCD") == 305441741
    assert p.decode_firmware(b"V92 Classic") == 92
    assert p.decode_firmware(b"V100 Classic") == 100
    assert p.decode_firmware(b"") == 0
    info = p.decode_log_upload(p.encode_log_upload(0x80000000))
    assert (info.dive_base_address, info.log_format) == (0x80000000, "pnf")
    assert p.decode_log_upload(p.encode_log_upload(0x90000000)).dive_base_address == 0xC0000000
    with pytest.raises(p.ProtocolError, match="not 8 hex digits"):
        p.decode_serial(b"1234ABCG")
    with pytest.raises(p.ProtocolError, match="not 8 hex digits"):
        p.decode_serial(b"1234")
    with pytest.raises(p.ProtocolError, match="at most 12"):
        p.decode_firmware(b"V92 Classic++")
    with pytest.raises(p.ProtocolError, match="unknown logbook format"):
        p.decode_log_upload(p.encode_log_upload(0x12345678))
    with pytest.raises(p.ProtocolError, match="9"):
        p.decode_log_upload(b"\x01")


def test_reply_checks() -> None:
    with pytest.raises(p.NegativeResponseError, match=r"0x22.*0x31"):
        p.parse_rdbi_response(wire("7F 22 31"), p.ID_MODEL)
    with pytest.raises(p.ProtocolError, match="expected 62 80 60"):
        p.parse_rdbi_response(wire("62 80 10 06"), p.ID_MODEL)
    with pytest.raises(p.ProtocolError, match="shorter than its header"):
        p.decode_response(wire("01 FF"))
    with pytest.raises(p.ProtocolError, match="header"):
        p.decode_response(wire("FF 01 02 00 37"))
    with pytest.raises(p.ProtocolError, match="length byte"):
        p.decode_response(wire("01 FF 05 00 37"))
    with pytest.raises(p.ProtocolError, match=r"block 2 .*expected 1"):
        p.parse_transfer_response(wire("76 02 00"), 1)
    with pytest.raises(p.ProtocolError, match="TransferData"):
        p.parse_transfer_response(wire("75 01"), 1)
    with pytest.raises(p.ProtocolError, match="RequestUpload"):
        p.parse_upload_response(wire("75 10 FF"))
    with pytest.raises(p.NegativeResponseError):
        p.parse_upload_response(wire("7F 35 22"))
    with pytest.raises(p.ProtocolError, match="RequestTransferExit"):
        p.parse_exit_response(wire("77 01"))
    with pytest.raises(p.ProtocolError, match="WDBI"):
        p.parse_wdbi_response(wire("6E 90 31"), p.ID_LOCAL_CLOCK)
    p.parse_wdbi_response(wire("6E 90 30"), p.ID_LOCAL_CLOCK)
    with pytest.raises(p.ProtocolError, match="malformed RequestUpload"):
        p.parse_upload_request(wire("35 20 34 00 00 00 00 00 00 00"))
    request = p.parse_upload_request(p.upload_request(0x80010000, 0xFFFFFF, compressed=True))
    assert (request.address, request.size, request.compressed) == (0x80010000, 0xFFFFFF, True)
    with pytest.raises(ValueError, match="exceeds 254"):
        p.encode_response(bytes(255))


def test_slip_quirks() -> None:
    decoder = p.SlipDecoder()
    # Empty frames are skipped; an escape before an ordinary byte keeps that byte.
    assert decoder.feed(wire("C0 C0 01 DB 41 C0")) == [wire("01 41")]
    # Split across reads.
    assert decoder.feed(wire("01 DB")) == []
    assert decoder.pending == 1
    assert decoder.feed(wire("DC C0")) == [wire("01 C0")]
    bad = decoder.feed(wire("01 DB DB 02 C0 05 C0"))
    assert isinstance(bad[0], p.ProtocolError) and bad[1] == b"\x05"
    bad = decoder.feed(wire("01 DB C0 07 C0"))
    assert isinstance(bad[0], p.ProtocolError) and bad[1] == b"\x07"


def test_lre_vectors() -> None:
    assert p.lre_decode_block(wire("D2 80 F8 1F F0 00 00 00 00")) == (
        wire("A5 00 00 00 C0 FF"),
        True,
    )
    plain = bytes(range(1, 33)) + bytes(range(1, 9)) + b"\x55" * 4
    coded = p.xor_encode(plain)
    assert coded[32:40] == bytes(8) and coded[40:] == wire("5C 5F 5E 59")
    expected = wire(
        "80 C0 A0 70 48 2C 1A 0F 08 84 C2 A1 70 C8 6C 3A 1F 10 88 C4 A2 71 48 AC 5A 2F 18 8C"
        " C6 A3 71 C8 EC 7A 3F 20 04 57 2B F5 EA C8 00 00 00"
    )
    assert p.compress_dive(plain) == [expected]
    assert p.decompress_blocks([expected]) == plain
    with pytest.raises(p.ProtocolError, match="multiple of 9"):
        p.lre_decode_block(bytes(10))
    with pytest.raises(p.ProtocolError, match="end-of-stream"):
        p.decompress_blocks([_full_block_without_end()])
    with pytest.raises(ValueError, match="multiple of 8"):
        p.lre_encode_blocks(b"", tokens_per_block=12)


def _full_block_without_end() -> bytes:
    return p.lre_encode_blocks(b"\x01" * 300)[0]


@pytest.mark.parametrize("tokens_per_block", [8, 64, 224])
def test_compression_round_trip_many_blocks(tokens_per_block: int) -> None:
    rng = random.Random(3)
    for size in (0, 1, 31, 32, 33, 255, 256, 1000, 5000):
        data = bytes(rng.choice((0, 0, 0, rng.randrange(256))) for _ in range(size))
        data += bytes(600)  # a zero run longer than 255
        blocks = p.lre_encode_blocks(p.xor_encode(data), tokens_per_block=tokens_per_block)
        assert all(len(b) % 9 == 0 and len(b) <= p.MAX_BLOCK_DATA for b in blocks)
        assert all(not p.lre_decode_block(b)[1] for b in blocks[:-1])
        assert p.decompress_blocks(blocks) == data


def test_manifest_pages() -> None:
    records = [p.ManifestRecord(fingerprint=bytes((i, 0, 0, 1)), offset=i << 16) for i in range(3)]
    records.insert(1, p.ManifestRecord(fingerprint=bytes(4), offset=0, deleted=True))
    page = p.encode_manifest_page(records)
    assert len(page) == 0x600 and page[128:] == b"\xff" * (0x600 - 128)
    assert page[:2] == p.MARKER_VALID and page[32:34] == p.MARKER_DELETED
    assert p.decode_manifest_page(page) == (records, False)
    full = [p.ManifestRecord(fingerprint=bytes(4), offset=i) for i in range(48)]
    assert p.decode_manifest_page(p.encode_manifest_page(full)) == (full, True)
    with pytest.raises(p.ProtocolError, match="expected 1536"):
        p.decode_manifest_page(page[:100])
    with pytest.raises(ValueError, match="do not fit"):
        p.encode_manifest_page(full + full[:1])
