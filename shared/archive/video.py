"""Decoded frames of a session's video (CompressedVideo packets decoded with PyAV).

    with SessionVideo("sessions/dive1", grayscale=True, scale=0.5) as video:
        for frame in video.frames():              # every frame, in time order
            frame.stamp_ns, frame.image            # int ns since epoch, (H, W) uint8
        still = video.frame_at(t_ns)               # the frame shown at t_ns

Time base: `stamp_ns` is the packet's `header.stamp` (sensor clock, ns since
the UNIX epoch): for an imported GoPro file, creation time + media time, so
exactly the frame's presentation time. Frames come out in presentation order.

Random access (`frames(start_ns=...)`, `frame_at`) starts decoding at the
last keyframe at or before the asked time: its log time is looked up in the
archive's `video_keyframes` Metadata record when the writer stored one, else
found by reading the packets of a time window before the asked time (the MCAP
chunk index selects only the chunks of that window; the window doubles until
a keyframe is found). Then packets are decoded forward and frames before the
asked time are dropped. Keyframes are recognised from the Annex B data
(an H.264 IDR or an H.265 IRAP NAL unit).

A packet the decoder refuses (damaged data) is skipped and counted in
`skipped_packets`; the frames depending on it may come out damaged until
the next keyframe, as in any player.

Images are numpy uint8 arrays, BGR (H, W, 3) as OpenCV expects or, with
`grayscale`, the luma plane as (H, W); `scale` resizes with area averaging.
Only PyAV and numpy are needed (post-processing imports this; not `field`).
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from types import TracebackType

import av
import numpy as np
from numpy.typing import NDArray

from shared.archive.messages import CompressedVideo
from shared.archive.reader import ArchiveReader
from shared.clock import NS_PER_S
from shared.errors import InputError

KEYFRAME_METADATA = "video_keyframes"
"""Metadata record the importer writes: topic -> comma-separated keyframe log times (ns)."""
FRAME_SIZE_METADATA = "video_frame_size"
"""Metadata record: topic -> "WIDTHxHEIGHT", the display size the container declared.

Some cameras (GoPro at 854x480) encode a larger coded size without SPS
cropping and rely on the container's size; FFmpeg crops to it when told, so
frames match those decoded straight from the MP4 pixel for pixel."""

_CODEC_NAMES = {"h264": "h264", "h265": "hevc", "hevc": "hevc"}
_FIRST_WINDOW_NS = 4_000_000_000


@dataclass(frozen=True)
class VideoFrame:
    """One decoded frame: `stamp_ns` (header.stamp, ns since epoch), the image, and
    whether its packet was a keyframe."""

    stamp_ns: int
    image: NDArray[np.uint8]
    keyframe: bool


def is_keyframe(data: bytes, codec: str) -> bool:
    """True when an Annex B access unit holds an IDR (H.264) or IRAP (H.265) slice."""
    hevc = codec in ("h265", "hevc")
    pos = data.find(b"\x00\x00\x01")
    seen = 0
    while pos >= 0 and pos + 3 < len(data) and seen < 16:
        header = data[pos + 3]
        if hevc:
            if 16 <= (header >> 1) & 0x3F <= 21:
                return True
        elif header & 0x1F == 5:
            return True
        seen += 1
        pos = data.find(b"\x00\x00\x01", pos + 3)
    return False


def session_archives(path: Path | str) -> list[Path]:
    """The archive files of a session folder (`recording.mcap` or `recording_NNN.mcap`,
    by name), or `[path]` for a file. InputError when there is none."""
    path = Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise InputError(f"{path}: no such session folder or archive")
    files = sorted(path.glob("recording*.mcap")) or sorted(path.glob("*.mcap"))
    if not files:
        raise InputError(f"{path}: no recording*.mcap (expected a session folder)")
    return files


class SessionVideo:
    """Frames of one video topic of a session folder or archive file.

    Args:
        path: a session folder or one `.mcap` file.
        topic: the CompressedVideo topic (default `/cam0/video`).
        scale: resize factor (0 < scale <= 1 to downscale), area interpolation.
        grayscale: luma only, (H, W) uint8; else BGR (H, W, 3) uint8.
        threads: decoder threads (0: FFmpeg chooses).
        frame_size: (width, height) the container declared, to crop a larger
            coded size; default: the archive's `video_frame_size` record.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        topic: str = "/cam0/video",
        scale: float = 1.0,
        grayscale: bool = False,
        threads: int = 0,
        frame_size: tuple[int, int] | None = None,
    ) -> None:
        if not 0.0 < scale <= 4.0:
            raise InputError(f"scale {scale}: expected 0 < scale <= 4")
        self.path = Path(path)
        self.topic = topic
        self.scale = scale
        self.grayscale = grayscale
        self.threads = threads
        self.frame_size = frame_size
        self.skipped_packets = 0
        """Packets the decoder refused as invalid data (skipped, counted here)."""
        self._readers = [ArchiveReader(p) for p in session_archives(path)]
        self._spans: list[tuple[int, int]] = []
        self._keyframes: list[list[int] | None] = []
        self._count = 0
        for reader in self._readers:
            info = reader.topics().get(topic)
            if info is None:
                self._spans.append((0, -1))
            else:
                self._spans.append((info.first_log_time_ns, info.last_log_time_ns))
                self._count += info.message_count
            self._keyframes.append(self._stored_keyframes(reader))
            if self.frame_size is None:
                self.frame_size = self._stored_frame_size(reader)
        if self._count == 0:
            names = ", ".join(sorted({t for r in self._readers for t in r.topics()})) or "none"
            raise InputError(f"{self.path}: no video topic {topic!r} (topics: {names})")

    @property
    def frame_count(self) -> int:
        """Packets on the topic (= frames), from the archive index."""
        return self._count

    def time_span_ns(self) -> tuple[int, int]:
        """(first, last) packet log time on the topic, ns since epoch."""
        spans = [s for s in self._spans if s[1] >= s[0]]
        return min(s[0] for s in spans), max(s[1] for s in spans)

    def _stored_keyframes(self, reader: ArchiveReader) -> list[int] | None:
        text = reader.metadata().get(KEYFRAME_METADATA, {}).get(self.topic)
        if text is None:
            return None
        try:
            return sorted(int(v) for v in text.split(",") if v)
        except ValueError:
            return None  # unreadable record: fall back to scanning

    def _stored_frame_size(self, reader: ArchiveReader) -> tuple[int, int] | None:
        text = reader.metadata().get(FRAME_SIZE_METADATA, {}).get(self.topic, "")
        width, _, height = text.partition("x")
        if width.isdigit() and height.isdigit():
            return int(width), int(height)
        return None

    # -- decoding ------------------------------------------------------------

    def _decoder(self, codec: str) -> av.VideoCodecContext:
        name = _CODEC_NAMES.get(codec)
        if name is None:
            raise InputError(f"{self.path}: video format {codec!r} (expected h264 or h265)")
        context = av.CodecContext.create(name, "r")
        if not isinstance(context, av.VideoCodecContext):
            raise InputError(f"{self.path}: {name} is not a video codec")
        context.thread_count = self.threads
        if self.frame_size is not None:
            context.width, context.height = self.frame_size
        return context

    def _image(self, frame: av.VideoFrame) -> NDArray[np.uint8]:
        fmt = "gray" if self.grayscale else "bgr24"
        if self.scale != 1.0:
            width = max(1, round(frame.width * self.scale))
            height = max(1, round(frame.height * self.scale))
            frame = frame.reformat(width=width, height=height, format=fmt, interpolation="AREA")
            image = frame.to_ndarray()
        else:
            image = frame.to_ndarray(format=fmt)
        return np.ascontiguousarray(image, dtype=np.uint8)

    def _decode_reader(
        self, reader: ArchiveReader, start_log_ns: int | None, end_ns: int | None
    ) -> Iterator[tuple[int, bool, av.VideoFrame]]:
        """(stamp, keyframe, frame) from `start_log_ns` (a keyframe) to the end / `end_ns`."""
        context: av.VideoCodecContext | None = None
        pending: dict[int, tuple[int, bool]] = {}
        started = False
        for _, log_time, message in reader.messages([self.topic], start_log_ns, None):
            if not isinstance(message, CompressedVideo):
                raise InputError(f"{reader.path}: topic {self.topic!r} is not CompressedVideo")
            if end_ns is not None and message.stamp_ns >= end_ns and log_time >= end_ns:
                break
            key = is_keyframe(message.data, message.format)
            if not started:
                if not key:
                    continue  # nothing decodes before the first keyframe
                started = True
            if context is None:
                context = self._decoder(message.format)
            packet = av.Packet(message.data)
            packet.pts = log_time
            packet.time_base = Fraction(1, NS_PER_S)
            pending[log_time] = (message.stamp_ns, key)
            try:
                decoded = context.decode(packet)
            except av.error.InvalidDataError:
                # A damaged packet: skip it; the decoder recovers at the next keyframe.
                pending.pop(log_time, None)
                self.skipped_packets += 1
                continue
            for frame in decoded:
                yield self._pop(pending, frame)
        if context is not None:
            for frame in context.decode(None):
                yield self._pop(pending, frame)

    @staticmethod
    def _pop(
        pending: dict[int, tuple[int, bool]], frame: av.VideoFrame
    ) -> tuple[int, bool, av.VideoFrame]:
        if frame.pts is None or frame.pts not in pending:
            raise InputError("decoder returned a frame without a known timestamp")
        stamp, key = pending.pop(frame.pts)
        return stamp, key, frame

    def frames(
        self,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        keep: Callable[[int], bool] | None = None,
    ) -> Iterator[VideoFrame]:
        """Decoded frames with `start_ns <= stamp_ns < end_ns` (None: no bound), in time order.

        `keep`, called with the stamp of each frame in that span in turn, drops those it
        is false for: they are still decoded (later frames refer to them) but not
        converted to an image, the costlier part at our sizes.
        """
        for stamp, key, frame in self.decoded(start_ns, end_ns, keep=keep):
            yield VideoFrame(stamp_ns=stamp, image=self._image(frame), keyframe=key)

    def decoded(
        self,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        keep: Callable[[int], bool] | None = None,
    ) -> Iterator[tuple[int, bool, av.VideoFrame]]:
        """As `frames`, but (stamp_ns, keyframe, PyAV frame) not yet converted (this
        object's `scale` and `grayscale` do not apply): for a caller that converts
        only what it needs."""
        for index, reader in enumerate(self._readers):
            first, last = self._spans[index]
            if last < first or (end_ns is not None and first >= end_ns):
                continue
            if start_ns is not None and last < start_ns:
                continue
            seek = None if start_ns is None else self._keyframe_at_or_before(index, start_ns)
            for stamp, key, frame in self._decode_reader(reader, seek, end_ns):
                if start_ns is not None and stamp < start_ns:
                    continue
                if end_ns is not None and stamp >= end_ns:
                    continue
                if keep is not None and not keep(stamp):
                    continue
                yield stamp, key, frame

    def frame_at(self, stamp_ns: int) -> VideoFrame:
        """The frame on screen at `stamp_ns`: the last one with stamp <= `stamp_ns`.

        InputError when `stamp_ns` is before the first frame.
        """
        for index in reversed(range(len(self._readers))):
            first, last = self._spans[index]
            if last < first or first > stamp_ns:
                continue
            seek = self._keyframe_at_or_before(index, stamp_ns)
            best: tuple[int, bool, av.VideoFrame] | None = None
            for stamp, key, frame in self._decode_reader(self._readers[index], seek, None):
                if stamp <= stamp_ns and (best is None or stamp >= best[0]):
                    best = (stamp, key, frame)
                elif stamp > stamp_ns and best is not None:
                    break
            if best is not None:
                return VideoFrame(stamp_ns=best[0], image=self._image(best[2]), keyframe=best[1])
        first_ns = self.time_span_ns()[0]
        raise InputError(f"{self.path}: no frame at {stamp_ns} ns (video starts at {first_ns} ns)")

    def keyframe_times_ns(self) -> list[int]:
        """Log times (ns) of every keyframe on the topic (stored list, else a full scan)."""
        times: list[int] = []
        for index, reader in enumerate(self._readers):
            stored = self._keyframes[index]
            if stored is None:
                stored = [
                    log_time
                    for _, log_time, message in reader.messages([self.topic])
                    if isinstance(message, CompressedVideo)
                    and is_keyframe(message.data, message.format)
                ]
                self._keyframes[index] = stored
            times.extend(stored)
        return times

    def _keyframe_at_or_before(self, index: int, log_ns: int) -> int | None:
        """Log time of the last keyframe at or before `log_ns` in archive `index` (None: start)."""
        stored = self._keyframes[index]
        if stored is not None:
            position = bisect.bisect_right(stored, log_ns)
            return stored[position - 1] if position else None
        reader = self._readers[index]
        first, _ = self._spans[index]
        window = _FIRST_WINDOW_NS
        while True:
            low = max(first, log_ns - window)
            found = None
            for _, log_time, message in reader.messages([self.topic], low, log_ns + 1):
                if isinstance(message, CompressedVideo) and is_keyframe(
                    message.data, message.format
                ):
                    found = log_time
            if found is not None:
                return found
            if low <= first:
                return None
            window *= 2

    # -- lifetime -----------------------------------------------------------

    def close(self) -> None:
        for reader in self._readers:
            reader.close()

    def __enter__(self) -> SessionVideo:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def iter_frames(
    path: Path | str,
    *,
    topic: str = "/cam0/video",
    scale: float = 1.0,
    grayscale: bool = False,
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> Iterator[VideoFrame]:
    """Every frame of `topic` in a session folder or archive (see `SessionVideo`)."""
    with SessionVideo(path, topic=topic, scale=scale, grayscale=grayscale) as video:
        yield from video.frames(start_ns, end_ns)
