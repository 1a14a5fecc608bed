"""H.264 / H.265 packets between MP4 (length-prefixed NAL units) and Annex B (start codes).

Pure byte work, no decoding. MP4 stores each access unit as NAL units
prefixed by their big-endian length (`lengthSizeMinusOne + 1` bytes, from
avcC/hvcC) and keeps the parameter sets (VPS/SPS/PPS) in the avcC/hvcC box.
Annex B, what `foxglove_msgs/msg/CompressedVideo` carries, puts a
`00 00 00 01` start code before each NAL unit and the parameter sets in-band
before every keyframe, so any packet from a keyframe on can be decoded alone.

We convert ourselves rather than through FFmpeg's `h264_mp4toannexb` filter:
the conversion is a few slices per frame (no emulation-prevention bytes
change), so one `bytes.join` per packet is as fast as a memory copy, and the
packets never pass through the C library twice. (`field.gopro.mp4` parses
avcC/hvcC; `to_annexb` adds the keyframe rule: parameter sets only when the
sample has none in-band.)
"""

from __future__ import annotations

from shared.errors import InputError

START_CODE = b"\x00\x00\x00\x01"

H264_IDR = 5
H264_SEI = 6
H264_SPS = 7
H264_PPS = 8
H264_AUD = 9
H265_VPS = 32
H265_SPS = 33
H265_PPS = 34
H265_AUD = 35
H265_IRAP = range(16, 22)


def nal_type(codec: str, header: int) -> int:
    """NAL unit type from the first header byte ("h264": 5 bits; "h265": 6 bits)."""
    return header & 0x1F if codec == "h264" else (header >> 1) & 0x3F


def is_keyframe_nal(codec: str, kind: int) -> bool:
    """True for an IDR (H.264) or IRAP (H.265) slice."""
    return kind == H264_IDR if codec == "h264" else kind in H265_IRAP


def is_parameter_set(codec: str, kind: int) -> bool:
    return (
        kind in (H264_SPS, H264_PPS) if codec == "h264" else kind in (H265_VPS, H265_SPS, H265_PPS)
    )


CODEC_NAMES = {"avc1": "h264", "avc3": "h264", "hvc1": "h265", "hev1": "h265"}
"""MP4 sample entry -> the `format` of foxglove CompressedVideo."""


def to_annexb(
    sample: bytes,
    *,
    codec: str,
    nal_length_size: int,
    parameter_sets: bytes,
    keyframe: bool,
    where: str,
) -> bytes:
    """One MP4 sample (length-prefixed NAL units) as an Annex B access unit.

    `codec` "h264"/"h265"; `parameter_sets`: Annex B VPS/SPS/PPS
    (`field.gopro.mp4.CodecConfig.annexb_header()`), put first on keyframes
    unless the sample already carries an SPS. Raises InputError (naming
    `where`) when a NAL length runs past the sample: the packet is corrupt.
    """
    length_size = nal_length_size
    view = memoryview(sample)
    end = len(sample)
    parts: list[bytes | memoryview] = []
    has_sps = False
    sps_kind = H264_SPS if codec == "h264" else H265_SPS
    pos = 0
    while pos < end:
        if pos + length_size > end:
            raise InputError(f"{where}: NAL length field cut at byte {pos} of {end}")
        size = int.from_bytes(view[pos : pos + length_size], "big")
        pos += length_size
        if size == 0 or pos + size > end:
            raise InputError(
                f"{where}: NAL unit of {size} bytes at byte {pos} runs past the packet "
                f"({end} bytes; corrupt sample)"
            )
        if keyframe and nal_type(codec, view[pos]) == sps_kind:
            has_sps = True
        parts.append(START_CODE)
        parts.append(view[pos : pos + size])
        pos += size
    if keyframe and not has_sps:
        return parameter_sets + b"".join(parts)
    return b"".join(parts)


def split_annexb_units(data: bytes) -> list[bytes]:
    """NAL units of an Annex B buffer (start codes of 3 or 4 bytes removed)."""
    units: list[bytes] = []
    start = data.find(b"\x00\x00\x01")
    while start >= 0:
        begin = start + 3
        nxt = data.find(b"\x00\x00\x01", begin)
        stop = len(data) if nxt < 0 else nxt
        unit = data[begin:stop]
        if nxt >= 0:
            unit = unit.rstrip(b"\x00")
        if unit:
            units.append(unit)
        start = nxt
    return units
