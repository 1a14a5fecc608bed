"""The real GoPro clips' frames as the post-processor reads them: kept as their 4:2:0
planes (`shared.formats.recordings.PlanarYuv`), with the colour made only when asked.

Both clips are full-range (yuvj420p) BT.709 video, unlike the limited-range video
our simulator renders: the BGR made from the kept planes must equal PyAV's direct
conversion of the decoded frame pixel for pixel, and the grey image must be the luma
plane itself, from the video file and from the session folder the importer makes
of it (which crops the HERO5's 864-pixel coded width to the container's 854).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from field.gopro.importer import ImportOptions, import_recording
from shared.formats.recordings import open_recording

FRAMES = 12


@pytest.mark.parametrize("name", ["karma.mp4", "max-heromode.mp4"])
def test_real_clip_frames_keep_their_planes_and_convert_as_pyav_does(
    shared_data: Path, tmp_path: Path, name: str
) -> None:
    import av

    clip = shared_data / "gopro" / name
    direct = []
    with av.open(str(clip)) as container:
        for frame in container.decode(container.streams.video[0]):
            assert frame.format.name == "yuvj420p"  # full range: no stretch of the luma
            luma = frame.to_ndarray(format="yuvj420p")[: frame.height]
            direct.append((frame.to_ndarray(format="bgr24"), luma))
            if len(direct) == FRAMES:
                break
    from_file = [f for _, f in zip(range(FRAMES), open_recording(clip).frames(), strict=False)]
    session = tmp_path / "session"
    import_recording(ImportOptions(), [clip], session)
    from_session = [
        f for _, f in zip(range(FRAMES), open_recording(session).frames(), strict=False)
    ]
    assert len(from_file) == len(from_session) == FRAMES
    for frames in (from_file, from_session):
        for read, (bgr, luma) in zip(frames, direct, strict=True):
            assert read.luma is not None
            np.testing.assert_array_equal(read.luma, luma)
            np.testing.assert_array_equal(read.image, bgr)
