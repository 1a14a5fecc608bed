"""shared.formats.png: PNGs that other readers decode to the same pixels."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from shared.formats.png import SIGNATURE, encode_png


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, data) of each chunk, checking every CRC (a reader of our own, from the spec)."""
    assert data[:8] == SIGNATURE
    chunks, at = [], 8
    while at < len(data):
        (length,) = struct.unpack(">I", data[at : at + 4])
        kind, body = data[at + 4 : at + 8], data[at + 8 : at + 8 + length]
        (crc,) = struct.unpack(">I", data[at + 8 + length : at + 12 + length])
        assert crc == zlib.crc32(kind + body), kind
        chunks.append((kind, body))
        at += 12 + length
    return chunks


def _unfilter_up(data: bytes, height: int, row_bytes: int) -> np.ndarray:
    rows = np.frombuffer(zlib.decompress(data), np.uint8).reshape(height, row_bytes + 1)
    assert (rows[:, 0] == 2).all()
    return np.cumsum(rows[:, 1:].astype(np.int64), axis=0) % 256


@settings(max_examples=40, deadline=None)
@given(
    arrays(
        np.uint8,
        st.tuples(st.integers(1, 40), st.integers(1, 40), st.sampled_from([0, 1, 3, 4])).map(
            lambda s: s[:2] if s[2] == 0 else s
        ),
    )
)
def test_opencv_decodes_the_same_pixels(image: np.ndarray) -> None:
    data = encode_png(image)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back is not None
    np.testing.assert_array_equal(back.reshape(image.shape), image)


def test_layout_follows_the_specification() -> None:
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (9, 13, 3), dtype=np.uint8)
    chunks = _chunks(encode_png(bgr))
    assert [kind for kind, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(
        ">IIBBBBB", chunks[0][1]
    )
    assert (width, height, depth, colour) == (13, 9, 8, 2)
    assert (compression, filtering, interlace) == (0, 0, 0)
    rgb = _unfilter_up(chunks[1][1], 9, 13 * 3).reshape(9, 13, 3)
    np.testing.assert_array_equal(rgb, bgr[:, :, ::-1])  # RGB in the file
    assert chunks[2][1] == b""


def test_grey_and_alpha_colour_types() -> None:
    grey = np.arange(20, dtype=np.uint8).reshape(4, 5)
    assert struct.unpack(">IIBB", _chunks(encode_png(grey))[0][1][:10])[3] == 0
    bgra = np.dstack([grey, grey, grey, 255 - grey])
    assert struct.unpack(">IIBB", _chunks(encode_png(bgra))[0][1][:10])[3] == 6


def test_smaller_than_raw_on_a_real_photo(shared_data: Path) -> None:
    photo = cv2.imread(str(shared_data / "aprilgrid" / "000.jpg"), cv2.IMREAD_COLOR)
    assert photo is not None
    data = encode_png(photo)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, photo)
    assert len(data) < 0.8 * photo.nbytes


@pytest.mark.parametrize(
    "image",
    [np.zeros((4, 4), np.uint16), np.zeros((4, 4, 2), np.uint8), np.zeros((0, 4), np.uint8)],
)
def test_other_images_are_refused(image: np.ndarray) -> None:
    with pytest.raises(ValueError, match="image of"):
        encode_png(image)
