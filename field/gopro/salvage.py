"""Salvage an unfinalised GoPro MP4 (battery died: media data but no 'moov' index).

Without the index we do not know where samples start, so we walk the mdat:
GoPro interleaves runs of video samples (NAL units, each prefixed by its
4-byte big-endian length), AAC audio, GPMF payloads (a 'DEVC' nest) and the
SOS recovery track. At each position we accept a NAL unit when its length
fits, its header is a legal unit type for the codec, and (when we were not
already inside a run of NAL units) the next unit header checks out too;
otherwise we skip a GPMF nest whole or move on one byte. NAL units are
grouped into access units (a new one starts at an AUD/parameter set/SEI
after a slice, or at a slice whose first_mb / first_slice_segment flag says
it starts a picture). Frames before the first keyframe are dropped (nothing
can decode them). The parameter sets come from the data when the camera
wrote them in-band, else from a sibling chapter (or a file the user gives).

Times: frames are assumed at a constant rate (`fps`, from a sibling chapter
or the user): frame i at i / fps seconds of media time. GPMF payloads found
are returned with their order; the importer times them (STMP when present).
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass, field
from pathlib import Path

from field.gopro.annexb import (
    H264_AUD,
    H264_IDR,
    H264_PPS,
    H264_SEI,
    H264_SPS,
    H265_AUD,
    H265_PPS,
    H265_SPS,
    H265_VPS,
    START_CODE,
    is_keyframe_nal,
    nal_type,
)
from shared.errors import InputError

# Slices, SEI, SPS, PPS, AUD: what cameras write (partitions, fillers, end codes never).
_H264_TYPES = frozenset({1, 5, 6, 7, 8, 9})
_H265_TYPES = frozenset({*range(0, 10), *range(16, 22), *range(32, 41)})
MAX_NAL_BYTES = 64 * 2**20  # a 4K keyframe is a few MB; anything larger is not a NAL length


@dataclass
class SalvagedChapter:
    """What could be read from an unfinalised file.

    `packets`: Annex B access units, decode order, from the first keyframe;
    `keyframes`: one flag per packet; `gpmf_payloads`: raw GPMF payloads in
    file order; `skipped_bytes`: bytes of mdat that were neither video nor
    GPMF (audio, SOS, damage); `parameter_sets_in_band`: whether the data
    carried its own SPS/PPS.
    """

    packets: list[bytes] = field(default_factory=list)
    keyframes: list[bool] = field(default_factory=list)
    gpmf_payloads: list[bytes] = field(default_factory=list)
    skipped_bytes: int = 0
    dropped_leading_units: int = 0
    parameter_sets_in_band: bool = False


def _legal(codec: str, buf: mmap.mmap | bytes, pos: int, end: int) -> int:
    """Length of a plausible length-prefixed NAL unit at `pos`, else 0."""
    if pos + 6 > end:
        return 0
    size = int.from_bytes(buf[pos : pos + 4], "big")
    if size < 2 or size > MAX_NAL_BYTES or pos + 4 + size > end:
        return 0
    header = buf[pos + 4]
    if header & 0x80:
        return 0
    if codec == "h264":
        kind = header & 0x1F
        if kind not in _H264_TYPES:
            return 0
        if (kind == H264_AUD and size != 2) or (kind == H264_SPS and size < 4):
            return 0
        ref_idc = (header >> 5) & 0x03
        if kind in (H264_IDR, H264_SPS, H264_PPS) and ref_idc == 0:
            return 0
        if kind in (H264_SEI, H264_AUD) and ref_idc != 0:
            return 0
    else:
        second = buf[pos + 5]
        if (header & 0x01) or (second >> 3) or not (second & 0x07):
            return 0
        if (header >> 1) & 0x3F not in _H265_TYPES:
            return 0
    return size


def _starts_picture(codec: str, unit: bytes) -> bool:
    """True when a slice NAL unit is the first slice of a picture."""
    if codec == "h264":
        return len(unit) > 1 and bool(unit[1] & 0x80)  # first_mb_in_slice == 0 (ue '1')
    return len(unit) > 2 and bool(unit[2] & 0x80)  # first_slice_segment_in_pic_flag


def _is_slice(codec: str, kind: int) -> bool:
    return 1 <= kind <= 5 if codec == "h264" else kind < 32


def _is_au_delimiter(codec: str, kind: int) -> bool:
    if codec == "h264":
        return kind in (H264_AUD, H264_SPS, H264_PPS, H264_SEI)
    return kind in (H265_AUD, H265_VPS, H265_SPS, H265_PPS, 39)


def salvage_mdat(
    path: Path | str,
    *,
    mdat_offset: int,
    mdat_size: int,
    codec: str,
    parameter_sets: tuple[bytes, ...] = (),
    frames_start_with_aud: bool = False,
) -> SalvagedChapter:
    """Scan `mdat` of an unfinalised file for video access units and GPMF payloads.

    `codec` "h264" or "h265"; `parameter_sets` (raw NAL units, no start
    codes, from a finalised sibling) are put before each keyframe; without
    them the data's own (scanned) are used. `frames_start_with_aud`: the
    camera starts every frame with an access unit delimiter (GoPro does; the
    importer checks a finalised sibling), so a run of NAL units may only
    start with one: this rejects almost every false start inside audio.
    Raises InputError when no keyframe can be found, or when there are no
    parameter sets at all (neither in-band nor given).
    """
    path = Path(path)
    result = SalvagedChapter()
    units_of_frame: list[bytes] = []
    frame_has_slice = False
    in_band: dict[int, bytes] = {}
    with path.open("rb") as file:
        size = path.stat().st_size
        if size == 0:
            raise InputError(f"{path.name}: empty file")
        buf = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            end = min(size, mdat_offset + mdat_size)
            pos = mdat_offset
            in_run = False
            frames: list[list[bytes]] = []

            def flush() -> None:
                nonlocal units_of_frame, frame_has_slice
                if units_of_frame:
                    frames.append(units_of_frame)
                units_of_frame = []
                frame_has_slice = False

            while pos < end:
                length = _legal(codec, buf, pos, end)
                if length:
                    # Each unit must be followed by another one (or a GPMF nest, or the
                    # end); only a slice may end a run of units (the last unit of a frame
                    # before audio), and only inside a run we entered through a chain.
                    after = pos + 4 + length
                    chained = (
                        after >= end
                        or bool(_legal(codec, buf, after, end))
                        or buf[after : after + 4] == b"DEVC"
                    )
                    kind = nal_type(codec, buf[pos + 4])
                    ends_run = in_run and _is_slice(codec, kind)
                    bad_start = (
                        not in_run and frames_start_with_aud and kind not in (H264_AUD, H265_AUD)
                    )
                    if bad_start or not (chained or ends_run):
                        length = 0
                if length:
                    unit = bytes(buf[pos + 4 : pos + 4 + length])
                    kind = nal_type(codec, unit[0])
                    if _is_slice(codec, kind):
                        if frame_has_slice and _starts_picture(codec, unit):
                            flush()
                        frame_has_slice = True
                    elif _is_au_delimiter(codec, kind) and frame_has_slice:
                        flush()
                    if kind in ((H264_SPS, H264_PPS) if codec == "h264" else (32, 33, 34)):
                        in_band.setdefault(kind, unit)
                    units_of_frame.append(unit)
                    pos += 4 + length
                    in_run = True
                    continue
                in_run = False
                if buf[pos : pos + 4] == b"DEVC" and pos + 8 <= end:
                    struct_size, repeat = struct.unpack(">BH", buf[pos + 5 : pos + 8])
                    total = 8 + ((struct_size * repeat + 3) & ~3)
                    if pos + total <= end:
                        flush()
                        result.gpmf_payloads.append(bytes(buf[pos : pos + total]))
                        pos += total
                        continue
                result.skipped_bytes += 1
                pos += 1
            flush()
        finally:
            buf.close()
    # Parameter sets of a finalised sibling are known good; in-band ones (scanned) only
    # serve when there are none (GoPro does not repeat them in-band anyway).
    sets = parameter_sets or tuple(in_band[k] for k in sorted(in_band))
    result.parameter_sets_in_band = not parameter_sets and bool(in_band)
    if not sets:
        raise InputError(
            f"{path.name}: no 'moov' index and no SPS/PPS in the data; to salvage the video, "
            "import it together with a finalised chapter of the same recording or give "
            "a finalised file from the same camera mode as the parameter-set source"
        )
    prefix = b"".join(START_CODE + unit for unit in sets)
    started = False
    for units in frames:
        kinds = [nal_type(codec, u[0]) for u in units]
        keyframe = any(is_keyframe_nal(codec, k) for k in kinds)
        if not any(_is_slice(codec, k) for k in kinds):
            continue
        if not started and not keyframe:
            result.dropped_leading_units += len(units)
            continue
        started = True
        body = b"".join(START_CODE + u for u in units if not _is_param(codec, u))
        result.packets.append(prefix + body if keyframe else body)
        result.keyframes.append(keyframe)
    if not result.packets:
        raise InputError(
            f"{path.name}: no 'moov' index and no decodable video found in its media data "
            f"({mdat_size} bytes scanned, no {codec.upper()} keyframe)"
        )
    return result


def _is_param(codec: str, unit: bytes) -> bool:
    kind = nal_type(codec, unit[0])
    return kind in ((H264_SPS, H264_PPS) if codec == "h264" else (32, 33, 34))
