"""The recording registry: every kind read through one interface, write-then-read."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.archive import ArchiveWriter, CompressedImage, CompressedVideo, Imu
from shared.calibration.cameras import PinholeRadtan
from shared.calibration.kalibr import CameraCalibration, write_camchain
from shared.errors import InputError
from shared.formats.euroc import EurocWriter
from shared.formats.recordings import (
    RECORDING_KINDS,
    open_recording,
    recording_kind,
    spaced_by,
)

T0_NS = 1_700_000_000_000_000_000
UP = np.array([0.0, 0.0, 9.81])


def _image(k: int) -> np.ndarray:
    image = np.zeros((24, 32, 3), np.uint8)
    image[:, :, 0] = 10 * k
    image[4:8, 4 + k : 8 + k, 2] = 200
    return image


def _png(k: int) -> bytes:
    ok, data = cv2.imencode(".png", _image(k))
    assert ok
    return data.tobytes()


def _camera() -> CameraCalibration:
    return CameraCalibration(
        camera=PinholeRadtan(width=32, height=24, fx=30.0, fy=30.0, cx=16.0, cy=12.0)
    )


def _clip(path: Path, *, frames: int, rate: int) -> Path:
    """An MPEG-4 video file of `_image(0)`, `_image(1)`, ... at `rate` frames a second."""
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=rate)
        stream.width, stream.height = 32, 24
        stream.pix_fmt = "yuv420p"
        for k in range(frames):
            container.mux(stream.encode(av.VideoFrame.from_ndarray(_image(k), format="bgr24")))
        container.mux(stream.encode(None))
    return path


def _session(folder: Path, *, imu_rows: list[tuple[int, float]], images: int = 3) -> Path:
    """A session folder: `images` PNG stills 50 ms apart, IMU rows (stamp, gyro x) as given,
    split over two rotated recordings at the middle image."""
    folder.mkdir()
    middle = T0_NS + (images // 2) * 50_000_000
    for part, keep in enumerate((lambda t: t < middle, lambda t: t >= middle)):
        with ArchiveWriter(folder / f"recording_{part:03d}.mcap") as writer:
            for stamp, rate in imu_rows:
                if keep(stamp):
                    writer.write("/imu0", Imu(stamp, "imu0", np.array([rate, 0, 0]), UP))
            for k in range(images):
                stamp = T0_NS + k * 50_000_000
                if keep(stamp):
                    writer.write("/cam0/image", CompressedImage(stamp, "cam0", "png", _png(k)))
    write_camchain(folder / "calib" / "camchain.yaml", [_camera()])
    return folder


def test_a_session_reads_frames_imu_and_calibration_across_rotated_files(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rows = [(T0_NS + k * 5_000_000, 0.1 * k) for k in range(40)]
    rows.insert(10, rows[9])  # a message written twice
    session = _session(tmp_path / "s", imu_rows=rows)
    assert recording_kind(session) == "session"
    recording = open_recording(session)
    assert recording.camera_topic == "/cam0/image" and recording.frame_count == 3
    frames = list(recording.frames())
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.stamp_ns for f in frames] == [T0_NS, T0_NS + 50_000_000, T0_NS + 100_000_000]
    np.testing.assert_array_equal(frames[1].image, _image(1))
    assert frames[1].encoded_png == _png(1)
    grey = next(recording.frames(grayscale=True))
    assert grey.image.shape == (24, 32)
    assert recording.calibration is not None and recording.calibration.camera.width == 32
    assert recording.imu_noise is None and not recording.calibration_is_guess
    with caplog.at_level(logging.WARNING):
        imu, cleaning = recording.imu()
    assert cleaning.duplicate_rows == 1 and "1 rows repeating a stamp merged" in caplog.text
    np.testing.assert_array_equal(imu.stamps_ns, sorted({stamp for stamp, _ in rows}))
    np.testing.assert_allclose(imu.gyro_rad_s[:, 0], 0.1 * np.arange(40))
    # One archive of it reads alone; calib/ is looked for beside it.
    single = open_recording(session / "recording_001.mcap")
    assert single.kind == "session" and single.frame_count == 2
    assert single.calibration is not None


def test_session_topics_and_errors(tmp_path: Path) -> None:
    session = _session(tmp_path / "s", imu_rows=[(T0_NS, 0.0)])
    # Asked for video, recorded as stills: the stills are found.
    assert open_recording(session, camera_topic="/cam0/video").camera_topic == "/cam0/image"
    with pytest.raises(InputError, match=r"no camera topic '/cam1/image_raw' \(topics: "):
        open_recording(session, camera_topic="/cam1/image_raw")
    with pytest.raises(InputError, match=r"/imu0: fewer than 2 IMU samples \(1 usable\)"):
        open_recording(session).imu()
    with pytest.raises(InputError, match=r"/imu1: no IMU topic \(topics: /cam0/image, /imu0\)"):
        open_recording(session, imu_topic="/imu1").imu()
    imu_only = tmp_path / "imu_only"
    imu_only.mkdir()
    with ArchiveWriter(imu_only / "recording.mcap") as writer:
        for k in range(3):
            writer.write("/imu0", Imu(T0_NS + k * 5_000_000, "imu0", np.zeros(3), UP))
    # Without images: refused unless only the IMU is wanted.
    with pytest.raises(InputError, match="no camera topic"):
        open_recording(imu_only)
    recording = open_recording(imu_only, need_camera=False)
    assert recording.frame_count == 0 and len(recording.imu()[0]) == 3
    with pytest.raises(InputError, match="no camera topic"):
        list(recording.frames())


def test_a_video_session_in_an_unknown_codec_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "vp9"
    folder.mkdir()
    with ArchiveWriter(folder / "recording.mcap") as writer:
        # Starts like an H.264 IDR access unit, so it is decoded (and refused) at once.
        writer.write("/cam0/video", CompressedVideo(T0_NS, "cam0", "vp9", b"\x00\x00\x01\x05"))
    recording = open_recording(folder)
    assert recording.camera_topic == "/cam0/video" and recording.frame_count == 1
    with pytest.raises(InputError, match=r"video format 'vp9' \(expected h264 or h265\)"):
        list(recording.frames())


def test_an_euroc_folder_reads_like_the_writer_wrote_it(tmp_path: Path) -> None:
    stamps = T0_NS + np.arange(40) * 5_000_000
    gyro = np.column_stack([np.linspace(0, 1, 40), np.zeros(40), np.zeros(40)])
    with EurocWriter(tmp_path / "euroc", camera=_camera()) as writer:
        for k in range(3):
            writer.add_image(T0_NS + k * 50_000_000, _image(k))
        writer.add_imu(stamps, gyro, np.tile(UP, (40, 1)))
    recording = open_recording(tmp_path / "euroc")
    assert recording.kind == "euroc" and recording.has_imu and recording.frame_count == 3
    frames = list(recording.frames())
    assert [f.stamp_ns for f in frames] == [T0_NS + k * 50_000_000 for k in range(3)]
    np.testing.assert_array_equal(frames[2].image, _image(2))
    assert recording.calibration is not None
    assert recording.calibration.camera == _camera().camera
    imu, cleaning = recording.imu()
    np.testing.assert_array_equal(imu.stamps_ns, stamps)
    np.testing.assert_allclose(imu.gyro_rad_s, gyro)
    assert not cleaning.changed
    # mav0 itself reads the same; without imu0 it is a camera-only cut.
    assert open_recording(tmp_path / "euroc" / "mav0").frame_count == 3
    (tmp_path / "euroc" / "mav0" / "imu0" / "data.csv").unlink()
    camera_only = open_recording(tmp_path / "euroc")
    assert not camera_only.has_imu
    with pytest.raises(InputError, match=r"mav0/imu0/data.csv: missing"):
        camera_only.imu()


def test_an_imu_only_euroc_folder_gives_its_imu_but_no_frames(tmp_path: Path) -> None:
    imu0 = tmp_path / "imu_set" / "mav0" / "imu0"
    imu0.mkdir(parents=True)
    (imu0 / "data.csv").write_text(
        "#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n"
        + "".join(f"{T0_NS + k * 5_000_000},0.5,0,0,0,0,9.81\n" for k in range(4))
    )
    assert recording_kind(tmp_path / "imu_set") == "euroc"
    with pytest.raises(InputError, match=r"imu_set: no images \(expected mav0/cam0/data.csv\)"):
        open_recording(tmp_path / "imu_set")
    imu, _ = open_recording(tmp_path / "imu_set", need_camera=False).imu()
    assert len(imu) == 4 and np.all(imu.gyro_rad_s[:, 0] == 0.5)


def test_an_image_folder_and_a_video_file(tmp_path: Path) -> None:
    folder = tmp_path / "stills"
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / f"{k:03d}.png"), _image(k))
    recording = open_recording(folder)
    assert recording.kind == "images" and not recording.has_imu
    frames = list(recording.frames())
    assert [f.stamp_ns for f in frames] == [0, 10**9, 2 * 10**9]
    assert frames[0].encoded_png is not None
    with pytest.raises(InputError, match="holds no IMU samples"):
        recording.imu()
    clip = open_recording(_clip(tmp_path / "clip.mp4", frames=5, rate=4))
    assert clip.kind == "video" and clip.frame_count == 5
    colour = list(clip.frames())
    assert [f.stamp_ns for f in colour] == [k * 250_000_000 for k in range(5)]
    assert colour[0].image.shape == (24, 32, 3)
    assert next(clip.frames(grayscale=True)).image.shape == (24, 32)


def test_spaced_by_keeps_the_first_stamp_then_each_one_a_step_after_the_last_kept() -> None:
    keep = spaced_by(60)
    assert [t for t in (0, 33, 66, 100, 133, 190, 200, 250) if keep(t)] == [0, 66, 133, 200]
    every = spaced_by(0)
    assert all(every(t) for t in (5, 5, 6))


def test_thinned_frames_are_not_read_or_decoded_and_keep_their_index(tmp_path: Path) -> None:
    step = 90_000_000  # of 50 ms apart: every other image
    with EurocWriter(tmp_path / "euroc", camera=_camera()) as writer:
        for k in range(6):
            writer.add_image(T0_NS + k * 50_000_000, _image(k))
    # A file the thinning skips is never read: a broken one there goes unnoticed.
    broken = sorted((tmp_path / "euroc" / "mav0" / "cam0" / "data").iterdir())[3]
    broken.write_bytes(b"not an image")
    euroc = open_recording(tmp_path / "euroc")
    frames = list(euroc.frames(min_step_ns=step))
    assert [f.index for f in frames] == [0, 2, 4]
    assert [f.stamp_ns for f in frames] == [T0_NS + k * 50_000_000 for k in (0, 2, 4)]
    np.testing.assert_array_equal(frames[2].image, _image(4))
    with pytest.raises(InputError, match="cannot be read as an image"):
        list(euroc.frames())
    # Stills in a session: the same.
    session = open_recording(_session(tmp_path / "s", imu_rows=[], images=5))
    stills = list(session.frames(min_step_ns=step))
    assert [f.index for f in stills] == [0, 2, 4]
    np.testing.assert_array_equal(stills[1].image, _image(2))
    assert stills[1].encoded_png == _png(2)
    # A video file decodes every frame but gives only the kept ones.
    clip = open_recording(_clip(tmp_path / "clip.mp4", frames=6, rate=20))
    every = list(clip.frames())
    kept = list(clip.frames(min_step_ns=step))
    assert [f.index for f in kept] == [0, 2, 4]
    assert [f.stamp_ns for f in kept] == [every[i].stamp_ns for i in (0, 2, 4)]
    np.testing.assert_array_equal(kept[1].image, every[2].image)
    # Any test of the stamps instead of the step: each kind asks it once per image (and
    # the EuRoC's broken image 3 is again never read).
    for recording, count in ((euroc, 6), (session, 5), (clip, 6)):
        asked: list[int] = []

        def even_ones(stamp_ns: int, asked: list[int] = asked) -> bool:
            asked.append(stamp_ns)
            return len(asked) % 2 == 1

        chosen = list(recording.frames(keep=even_ones))
        assert len(asked) == count
        assert [f.index for f in chosen] == list(range(0, count, 2))
        assert [f.stamp_ns for f in chosen] == asked[::2]


def test_a_path_that_is_no_recording_names_the_kinds(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"missing: no such file or folder \(expected an EuRoC"):
        open_recording(tmp_path / "missing")
    note = tmp_path / "notes.txt"
    note.write_text("x")
    with pytest.raises(InputError) as caught:
        open_recording(note)
    message = str(caught.value)
    assert message.startswith(f"{note}: not a recording (expected ") and "\n" not in message
    for kind in RECORDING_KINDS.values():
        assert kind.expected in message
    with pytest.raises(InputError, match="cannot open as a video"):
        fake = tmp_path / "fake.mp4"
        fake.write_bytes(b"\x00" * 64)
        list(open_recording(fake).frames())
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "1.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match=r"1\.png: cannot be read as an image"):
        list(open_recording(broken).frames())


def test_video_frames_keep_their_planes_and_convert_as_pyav_does(tmp_path: Path) -> None:
    import av

    from shared.formats.recordings import PlanarYuv

    path = _clip(tmp_path / "clip.mp4", frames=4, rate=4)
    with av.open(str(path)) as container:
        direct = [
            (f.to_ndarray(format="bgr24"), f.to_ndarray(format="gray"))
            for f in container.decode(container.streams.video[0])
        ]
    frames = list(open_recording(path).frames())
    assert len(frames) == len(direct) == 4
    for frame, (bgr, grey) in zip(frames, direct, strict=True):
        # A limited-range (16-235) clip: the luma plane comes out stretched to 0-255,
        # as PyAV's own grey conversion gives it, and BGR converts as PyAV does.
        luma = frame.luma
        assert luma is not None and luma.shape == (24, 32)
        np.testing.assert_array_equal(luma, grey)
        np.testing.assert_array_equal(frame.image, bgr)
        assert frame.image is frame.image  # converted once
    # Grey frames and stills have no planes: their image is what the frontend takes.
    assert next(open_recording(path).frames(grayscale=True)).luma is None
    # Odd sizes and other pixel formats are converted at once.
    assert PlanarYuv.of(av.VideoFrame(33, 24, "yuv420p")) is None
    assert PlanarYuv.of(av.VideoFrame(32, 24, "rgb24")) is None
    with pytest.raises(ValueError, match="pixel format"):
        PlanarYuv(np.zeros((36, 32), np.uint8), "nv12")
