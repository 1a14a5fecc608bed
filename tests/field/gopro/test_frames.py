"""Reading frames back from an imported session: exact pixels, exact times, random access."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from field.gopro.frames import iter_mp4_frames
from field.gopro.importer import ImportOptions, import_recording
from field.gopro.mp4 import read_mp4
from shared.archive import ArchiveReader, ArchiveWriter, CompressedVideo
from shared.archive.video import SessionVideo, is_keyframe, iter_frames, session_archives
from shared.errors import InputError


@pytest.fixture(scope="module", params=["karma.mp4", "max-heromode.mp4"])
def imported(
    request: pytest.FixtureRequest, shared_data: Path, tmp_path_factory
) -> tuple[Path, Path]:
    source = shared_data / "gopro" / request.param
    session = tmp_path_factory.mktemp("frames") / "session"
    import_recording(ImportOptions(), [source], session)
    return source, session


def test_every_frame_equals_the_mp4_decode_pixel_for_pixel(imported: tuple[Path, Path]) -> None:
    source, session = imported
    direct = list(iter_mp4_frames(source))
    with SessionVideo(session) as video:
        frames = list(video.frames())
        assert video.frame_count == len(direct)
    assert len(frames) == len(direct)
    assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in direct]
    assert [f.keyframe for f in frames] == [f.keyframe for f in direct]
    assert frames[0].image.shape == direct[0].image.shape
    for index in (0, 1, len(frames) // 2, len(frames) - 1):
        assert np.array_equal(frames[index].image, direct[index].image)


def test_random_access_matches_sequential_decoding(imported: tuple[Path, Path]) -> None:
    _, session = imported
    with SessionVideo(session, grayscale=True) as video:
        frames = list(video.frames())
        stamps = [f.stamp_ns for f in frames]
        for index in (0, 5, 8, 133, len(frames) - 1):
            at = video.frame_at(stamps[index] + 1000)  # shown until the next frame
            assert at.stamp_ns == stamps[index]
            assert np.array_equal(at.image, frames[index].image)
        window = list(video.frames(stamps[37], stamps[52]))
        assert [f.stamp_ns for f in window] == stamps[37:52]
        assert np.array_equal(window[0].image, frames[37].image)
        with pytest.raises(InputError, match="no frame at"):
            video.frame_at(stamps[0] - 1)


def test_scale_and_grayscale(imported: tuple[Path, Path]) -> None:
    source, session = imported
    first = next(iter_mp4_frames(source))
    height, width = first.image.shape[:2]
    grey = next(iter_frames(session, grayscale=True, scale=0.5))
    assert grey.image.shape == (round(height * 0.5), round(width * 0.5))
    assert grey.image.dtype == np.uint8
    colour = next(iter_frames(session))
    assert colour.image.shape == (height, width, 3)
    direct_grey = next(iter_mp4_frames(source, grayscale=True, scale=0.5))
    assert np.array_equal(grey.image, direct_grey.image)


def test_keyframe_lookup_without_the_stored_index(
    imported: tuple[Path, Path], tmp_path: Path
) -> None:
    """An archive without the `video_keyframes` record is searched backwards by time windows."""
    _, session = imported
    bare = tmp_path / "bare.mcap"
    with ArchiveReader(session / "recording.mcap") as reader, ArchiveWriter(bare) as writer:
        for topic, log_time, message in reader.messages(["/cam0/video"]):
            writer.write(topic, message, log_time_ns=log_time)
    with (
        SessionVideo(session) as indexed,
        SessionVideo(bare, frame_size=indexed.frame_size) as video,
    ):
        stored = indexed.keyframe_times_ns()
        assert video.keyframe_times_ns() == stored  # found by decoding NAL headers
        late = stored[-1] + 3 * 33_366_667
        assert np.array_equal(video.frame_at(late).image, indexed.frame_at(late).image)


def test_errors_name_the_problem(tmp_path: Path, imported: tuple[Path, Path]) -> None:
    _, session = imported
    with pytest.raises(InputError, match="no video topic '/cam1/video'"):
        SessionVideo(session, topic="/cam1/video")
    with pytest.raises(InputError, match="scale 0"):
        SessionVideo(session, scale=0)
    with pytest.raises(InputError, match="no recording"):
        session_archives(tmp_path)
    with pytest.raises(InputError, match="no such session folder"):
        session_archives(tmp_path / "missing")
    odd = tmp_path / "odd.mcap"
    with ArchiveWriter(odd) as writer:
        writer.write(
            "/cam0/video",
            CompressedVideo(
                stamp_ns=1, frame_id="cam0", format="vp9", data=b"\x00\x00\x00\x01\x65"
            ),
        )
    with SessionVideo(odd) as video, pytest.raises(InputError, match="video format 'vp9'"):
        next(video.frames())


def test_keyframe_detection() -> None:
    assert is_keyframe(b"\x00\x00\x00\x01\x67abc\x00\x00\x00\x01\x68d\x00\x00\x01\x65e", "h264")
    assert not is_keyframe(b"\x00\x00\x00\x01\x41abc", "h264")
    assert is_keyframe(b"\x00\x00\x00\x01\x26\x01abc", "h265")  # IDR_W_RADL = 19
    assert not is_keyframe(b"\x00\x00\x00\x01\x02\x01abc", "h265")  # TRAIL_R


def test_h265_session_decodes_like_the_encoder_output(tmp_path: Path) -> None:
    """H.265 Annex B packets (VPS/SPS/PPS in-band) read back frame for frame, keyframes found."""
    import av

    encoder = av.CodecContext.create("libx265", "w")
    assert isinstance(encoder, av.VideoCodecContext)
    encoder.width, encoder.height, encoder.pix_fmt = 64, 64, "yuv420p"
    encoder.time_base = Fraction(1, 30)
    encoder.options = {"x265-params": "keyint=10:min-keyint=10:bframes=0:log-level=none"}
    rng = np.random.default_rng(3)
    base = rng.integers(0, 255, size=(64, 96, 3), dtype=np.uint8)
    packets = []
    for index in range(25):
        frame = av.VideoFrame.from_ndarray(
            np.ascontiguousarray(base[:, index : index + 64]), format="rgb24"
        )
        frame = frame.reformat(format="yuv420p")
        frame.pts = index
        packets += [bytes(p) for p in encoder.encode(frame)]
    packets += [bytes(p) for p in encoder.encode(None)]
    decoder = av.CodecContext.create("hevc", "r")
    expected = []
    for data in packets:
        expected += [f.to_ndarray(format="gray") for f in decoder.decode(av.Packet(data))]
    expected += [f.to_ndarray(format="gray") for f in decoder.decode(None)]
    archive = tmp_path / "h265.mcap"
    stamps = [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(len(packets))]
    with ArchiveWriter(archive) as writer:
        for stamp, data in zip(stamps, packets, strict=True):
            writer.write(
                "/cam0/video",
                CompressedVideo(stamp_ns=stamp, frame_id="cam0", format="h265", data=data),
            )
    with SessionVideo(archive, grayscale=True) as video:
        frames = list(video.frames())
        assert [f.stamp_ns for f in frames] == stamps
        assert all(np.array_equal(f.image, e) for f, e in zip(frames, expected, strict=True))
        assert video.keyframe_times_ns() == stamps[::10]
        assert np.array_equal(video.frame_at(stamps[17]).image, expected[17])


def test_b_frames_keep_presentation_stamps_and_decode_order(tmp_path: Path) -> None:
    """An MP4 with B-frames (ctts + edit list, written by FFmpeg): exact stamps and pixels."""
    import av

    source = tmp_path / "bframes.mp4"
    with av.open(str(source), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(30000, 1001))
        stream.width, stream.height, stream.pix_fmt = 160, 120, "yuv420p"
        stream.codec_context.options = {
            "preset": "ultrafast",
            "x264-params": "bframes=2:b-adapt=0:keyint=12:min-keyint=12:scenecut=0:threads=1",
        }
        base = np.random.default_rng(2).integers(0, 255, (120, 300, 3), np.uint8)
        for i in range(40):
            frame = av.VideoFrame.from_ndarray(
                np.ascontiguousarray(base[:, 3 * i : 3 * i + 160]), format="rgb24"
            )
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    track = read_mp4(source).video_track()
    assert np.any(track.composition_times != track.decode_times)  # really reordered
    result = import_recording(ImportOptions(), [source], tmp_path / "s")
    assert result.frames == 40
    assert any("no GPMF track" in w for w in result.warnings)
    direct = list(iter_mp4_frames(source, start_ns=0))
    with SessionVideo(tmp_path / "s") as video:
        frames = list(video.frames())
        origin = frames[0].stamp_ns - direct[0].stamp_ns
        assert [f.stamp_ns - origin for f in frames] == [f.stamp_ns for f in direct]
        assert all(np.array_equal(a.image, b.image) for a, b in zip(frames, direct, strict=True))
        assert np.array_equal(video.frame_at(frames[17].stamp_ns).image, frames[17].image)
    with ArchiveReader(tmp_path / "s" / "recording.mcap") as reader:
        logs = [log for _, log, _ in reader.messages(["/cam0/video"])]
    assert np.all(np.diff(logs) > 0)  # decode order kept in log time


def test_damaged_packet_is_skipped_and_counted(imported: tuple[Path, Path], tmp_path: Path) -> None:
    _, session = imported
    damaged = tmp_path / "damaged.mcap"
    with ArchiveReader(session / "recording.mcap") as reader, ArchiveWriter(damaged) as writer:
        for index, (topic, log_time, message) in enumerate(reader.messages(["/cam0/video"])):
            assert isinstance(message, CompressedVideo)
            if index == 3:
                message.data = b"\x00\x00\x00\x01\x65" + b"\xff" * 64  # an IDR of garbage
            writer.write(topic, message, log_time_ns=log_time)
    with SessionVideo(session) as good, SessionVideo(damaged, frame_size=good.frame_size) as video:
        frames = list(video.frames())
        count = good.frame_count
    assert count - 2 <= len(frames) < count
    assert video.skipped_packets == 1


def test_a_thinned_session_gives_the_kept_frames_with_their_own_index_and_pixels(
    imported: tuple[Path, Path],
) -> None:
    from shared.formats.recordings import open_recording, spaced_by

    _, session = imported
    recording = open_recording(session)
    every = list(recording.frames(grayscale=True))
    step_ns = 60_000_000  # 30 fps: every other frame
    keep = spaced_by(step_ns)
    expected = [f for f in every if keep(f.stamp_ns)]
    thinned = list(recording.frames(grayscale=True, min_step_ns=step_ns))
    assert len(every) / 2 - 1 <= len(thinned) <= len(every) / 2 + 1
    assert [f.index for f in thinned] == [f.index for f in expected]
    assert [f.stamp_ns for f in thinned] == [f.stamp_ns for f in expected]
    assert np.all(np.diff([f.stamp_ns for f in thinned]) >= step_ns)
    for position in (0, 1, len(thinned) // 2, len(thinned) - 1):
        assert np.array_equal(thinned[position].image, expected[position].image)
