"""Frames straight from a GoPro MP4, on the same clock as an imported session.

For checking an import (pixel-exact comparison) and for previews of a file
not imported yet. Reading frames of an imported session is
`shared.archive.video.SessionVideo` (post-processing uses that one).

Time base: `stamp_ns` = the MP4 creation time (ns since epoch, the camera's
clock) + the frame's presentation time, exactly as `field.gopro.importer`
stamps the packets of chapter 1 (pass `start_ns` for a later chapter).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from field.gopro.mp4 import read_mp4
from shared.archive.video import SessionVideo, VideoFrame, iter_frames
from shared.clock import NS_PER_S
from shared.errors import InputError

__all__ = ["SessionVideo", "VideoFrame", "iter_frames", "iter_mp4_frames"]


def iter_mp4_frames(
    path: Path | str,
    *,
    grayscale: bool = False,
    scale: float = 1.0,
    start_ns: int | None = None,
) -> Iterator[VideoFrame]:
    """Decode every frame of the MP4's video track with PyAV (presentation order).

    `start_ns`: the stamp of media time 0 (default: the file's creation time).
    Images as in `SessionVideo`: BGR (H, W, 3) or luma (H, W) uint8, resized
    by `scale` with area averaging.
    """
    import av

    path = Path(path)
    mp4 = read_mp4(path)
    track = mp4.video_track()
    if start_ns is None:
        if mp4.creation_time is None:
            raise InputError(f"{path.name}: no creation time; give start_ns")
        created = mp4.creation_time
        start_ns = int(created.timestamp()) * NS_PER_S + created.microsecond * 1000
    fmt = "gray" if grayscale else "bgr24"
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        time_base = stream.time_base
        if time_base is None:
            raise InputError(f"{path.name}: video stream has no time base")
        keyframe_pts = set(
            (track.composition_times[track.keyframes] - track.edit_media_time).tolist()
        )
        for frame in container.decode(stream):
            if frame.pts is None:
                raise InputError(f"{path.name}: decoded frame without a timestamp")
            ticks = frame.pts * time_base * track.timescale
            stamp = start_ns + round(frame.pts * time_base * NS_PER_S)
            if scale != 1.0:
                width = max(1, round(frame.width * scale))
                height = max(1, round(frame.height * scale))
                image = frame.reformat(
                    width=width, height=height, format=fmt, interpolation="AREA"
                ).to_ndarray()
            else:
                image = frame.to_ndarray(format=fmt)
            yield VideoFrame(
                stamp_ns=stamp,
                image=np.ascontiguousarray(image, dtype=np.uint8),
                keyframe=int(ticks) in keyframe_pts,
            )
