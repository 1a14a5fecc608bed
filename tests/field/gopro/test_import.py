"""GoPro import: real files, synthetic chapters, DCIM folders, bad input, the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from field.gopro import cameras
from field.gopro.importer import (
    ImportOptions,
    group_recordings,
    import_recording,
    import_videos,
    parse_chapter,
)
from field.gopro.mp4 import read_mp4
from field.gopro.writer import (
    encode_gpmf_imu_payload,
    encode_h264,
    write_gopro_chapters,
    write_gopro_mp4,
)
from shared.archive import ArchiveReader, CompressedVideo
from shared.archive.video import SessionVideo
from shared.calibration.kalibr import read_camchain, read_imu_yaml
from shared.errors import InputError, OutputExistsError

REPO = Path(__file__).resolve().parents[3]
FPS = Fraction(30000, 1001)
PAYLOAD_S = Fraction(1001, 1000)
FRAMES_PER_PAYLOAD = 30
IMU_PER_PAYLOAD = 200
CREATED = datetime(2024, 5, 1, 10, 0, 0, tzinfo=UTC)
CREATED_NS = int(CREATED.timestamp()) * 10**9
# Gravity reads +9.81 on GoPro's Z (up); "XzY" stores (X, -Z, Y) as the MAX does.
GRAVITY_FILE_ORDER = np.array([0.0, -9.81, 0.0])


def _video_frames(count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    base = rng.integers(0, 255, size=(120, 160, 3), dtype=np.uint8)
    return [np.roll(base, 3 * i, axis=1) for i in range(count)]


def _synthetic(payloads: int = 6) -> dict[str, object]:
    """One recording: H.264 160x120 at 29.97 fps, GPMF ACCL/GYRO at ~200 Hz with STMP/CORI."""
    stream = encode_h264(_video_frames(payloads * FRAMES_PER_PAYLOAD), fps=FPS, gop_frames=15)
    gpmf = []
    for p in range(payloads):
        t = (p * IMU_PER_PAYLOAD + np.arange(IMU_PER_PAYLOAD)) / IMU_PER_PAYLOAD
        gyro = np.column_stack([0.1 * np.sin(t), 0.2 * np.cos(t), 0.05 * t])
        gpmf.append(
            encode_gpmf_imu_payload(
                accl_mps2=np.tile(GRAVITY_FILE_ORDER, (IMU_PER_PAYLOAD, 1)),
                gyro_rads=gyro,
                accl_first_us=p * 1_001_000,
                gyro_first_us=p * 1_001_000,
                accl_total_before=p * IMU_PER_PAYLOAD,
                gyro_total_before=p * IMU_PER_PAYLOAD,
                orientation_in="XzY",
                orientation_out="XYZ",
                cori_quat_wxyz=np.tile([1.0, 0, 0, 0], (FRAMES_PER_PAYLOAD, 1)),
                cori_first_us=p * 1_001_000,
                cori_total_before=p * FRAMES_PER_PAYLOAD,
            )
        )
    return {
        "video_packets": stream.packets,
        "sps": stream.sps,
        "pps": stream.pps,
        "width": stream.width,
        "height": stream.height,
        "fps": FPS,
        "keyframe_flags": stream.keyframes,
        "gpmf_payloads": gpmf,
        "creation_time": CREATED,
    }


@pytest.fixture(scope="module")
def recording() -> dict[str, object]:
    return _synthetic()


@pytest.fixture(scope="module")
def chapters(tmp_path_factory: pytest.TempPathFactory, recording: dict[str, object]) -> list[Path]:
    folder = tmp_path_factory.mktemp("chapters")
    return write_gopro_chapters(folder, file_number=42, payloads_per_chapter=3, **recording)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory, recording: dict[str, object]) -> Path:
    return write_gopro_mp4(tmp_path_factory.mktemp("whole") / "GX010099.MP4", **recording)  # type: ignore[arg-type]


def _video_stamps(session: Path) -> tuple[list[int], list[int]]:
    with ArchiveReader(session / "recording.mcap") as reader:
        stamps, logs = [], []
        for _, log_time, message in reader.messages(["/cam0/video"]):
            assert isinstance(message, CompressedVideo)
            stamps.append(message.stamp_ns)
            logs.append(log_time)
    return stamps, logs


# ----------------------------------------------------------------------------- real files


@pytest.mark.parametrize(
    ("name", "model", "gyro_hz", "accel_hz"),
    [("karma.mp4", "HERO5 Black", 397.2, 198.6), ("max-heromode.mp4", "GoPro Max", 197.5, 197.5)],
)
def test_real_file_import(
    shared_data: Path, tmp_path: Path, name: str, model: str, gyro_hz: float, accel_hz: float
) -> None:
    source = shared_data / "gopro" / name
    session = tmp_path / "session"
    result = import_recording(ImportOptions(), [source], session)
    mp4 = read_mp4(source)
    video = mp4.video_track()
    assert result.status == "imported" and result.frames == video.sample_count
    stamps, logs = _video_stamps(session)
    assert len(stamps) == video.sample_count
    created = mp4.creation_time
    assert created is not None
    assert stamps[0] == int(created.timestamp()) * 10**9
    steps = np.diff(stamps)
    assert steps.min() > 0 and logs == stamps
    # 3003 ticks of 90 kHz = 33366666.67 ns: every step rounds to one of its neighbours.
    assert set(steps.tolist()) <= {33366666, 33366667}
    with ArchiveReader(session / "recording.mcap") as reader:
        imu = reader.read_imu("/imu0")
        topics = reader.topics()
    assert set(topics) == {"/cam0/video", "/imu0", "/session"}
    assert np.all(np.diff(imu.stamps_ns) > 0)
    rate = (imu.stamps_ns.size - 1) / ((imu.stamps_ns[-1] - imu.stamps_ns[0]) * 1e-9)
    assert rate == pytest.approx(max(gyro_hz, accel_hz), rel=0.01)
    # The base stream keeps all its samples inside the other stream's time range.
    assert imu.stamps_ns.size == pytest.approx(rate * mp4.duration_s, rel=0.03)
    # Camera held roughly level: specific force points up = -y in the camera-aligned frame.
    mean_accel = imu.accel_m_s2.mean(axis=0)
    assert mean_accel[1] < -9.0 and abs(mean_accel[0]) < 1.0
    assert np.linalg.norm(mean_accel) == pytest.approx(9.8, abs=0.3)
    document = yaml.safe_load((session / "session.yaml").read_text())
    assert document["devices"]["cam0"]["model"] == model
    assert document["devices"]["imu0"]["gyro_rate_hz"] == pytest.approx(gyro_hz, rel=0.01)
    assert document["devices"]["imu0"]["accel_rate_hz"] == pytest.approx(accel_hz, rel=0.01)
    assert document["clocks"]["gopro"]["creation_time_ns"] == stamps[0]
    assert document["chapters"][0]["frames"] == video.sample_count
    camera = read_camchain(session / "calib" / "camchain.yaml")[0]
    assert (camera.camera.width, camera.camera.height) == (video.width, video.height)
    assert np.array_equal(camera.cam_from_imu, np.eye(4))
    assert read_imu_yaml(session / "calib" / "imu.yaml").update_rate_hz == pytest.approx(
        rate, rel=0.01
    )
    metadata = yaml.safe_load((session / "metadata.yaml").read_text())
    assert (
        metadata["rosbag2_bagfile_information"]["message_count"]
        == len(stamps) + imu.stamps_ns.size + 1
    )
    if name == "max-heromode.mp4":
        assert document["devices"]["cam0"]["serial"] == "C3353424500199"
        assert document["devices"]["imu0"]["axis_order_source"] == "ORIN"


def test_rosbags_opens_the_session_as_a_rosbag2_bag(shared_data: Path, tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader

    session = tmp_path / "s"
    import_recording(ImportOptions(), [shared_data / "gopro" / "karma.mp4"], session)
    with Reader(session) as bag:
        counts = {c.topic: c.msgcount for c in bag.connections}
    assert counts["/cam0/video"] == 362 and counts["/imu0"] > 4000


# ----------------------------------------------------------------------------- chapters


def test_chapter_names_and_grouping(tmp_path: Path) -> None:
    def key(name: str) -> tuple[str, int, int]:
        chapter = parse_chapter(Path(name))
        return chapter.family, chapter.file_number, chapter.index

    assert key("GX010042.MP4") == ("GX", 42, 1)
    assert key("gh020042.mp4") == ("GH", 42, 2)
    assert key("GOPR0042.MP4") == ("GOPR", 42, 1)
    assert key("GP010042.MP4") == ("GOPR", 42, 2)
    assert key("karma.mp4") == ("karma", -1, 1)
    names = ["GP020007.MP4", "GOPR0007.MP4", "GX020042.MP4", "GP010007.MP4", "GX010042.MP4"]
    recordings = group_recordings([tmp_path / n for n in names])
    assert [[c.path.name for c in r.chapters] for r in recordings] == [
        ["GOPR0007.MP4", "GP010007.MP4", "GP020007.MP4"],
        ["GX010042.MP4", "GX020042.MP4"],
    ]
    with pytest.raises(InputError, match="chapter 1 of recording GX0042 given twice"):
        group_recordings([tmp_path / "a" / "GX010042.MP4", tmp_path / "GX010042.MP4"])


def test_chapters_join_on_one_continuous_clock(
    tmp_path: Path, chapters: list[Path], whole: Path
) -> None:
    assert [p.name for p in chapters] == ["GX010042.MP4", "GX020042.MP4"]
    joined = import_recording(ImportOptions(), list(reversed(chapters)), tmp_path / "joined")
    single = import_recording(ImportOptions(), [whole], tmp_path / "single")
    assert joined.frames == single.frames == 6 * FRAMES_PER_PAYLOAD
    joined_stamps, _ = _video_stamps(tmp_path / "joined")
    single_stamps, _ = _video_stamps(tmp_path / "single")
    # Chapter 2 starts where chapter 1 ends: the same stamps as the uncut file, to 1 ns.
    assert np.abs(np.array(joined_stamps) - np.array(single_stamps)).max() <= 1
    expected = CREATED_NS + np.round(np.arange(joined.frames) * 1e9 / float(FPS)).astype(np.int64)
    assert np.abs(np.array(joined_stamps) - expected).max() <= 1
    with (
        ArchiveReader(tmp_path / "joined" / "recording.mcap") as a,
        ArchiveReader(tmp_path / "single" / "recording.mcap") as b,
    ):
        imu_joined, imu_single = a.read_imu(), b.read_imu()
    assert np.all(np.diff(imu_joined.stamps_ns) > 0)
    assert imu_joined.stamps_ns.size == imu_single.stamps_ns.size == 6 * IMU_PER_PAYLOAD
    assert np.abs(imu_joined.stamps_ns - imu_single.stamps_ns).max() < 50_000  # < 50 us
    rate = (imu_joined.stamps_ns.size - 1) / (
        (imu_joined.stamps_ns[-1] - imu_joined.stamps_ns[0]) * 1e-9
    )
    assert rate == pytest.approx(IMU_PER_PAYLOAD / 1.001, rel=1e-3)
    # "XzY" file order -> body frame: gravity reads (0, -9.81, 0) (camera level).
    assert np.allclose(imu_joined.accel_m_s2, [0.0, -9.81, 0.0], atol=0.02)
    document = yaml.safe_load((tmp_path / "joined" / "session.yaml").read_text())
    rows = document["chapters"]
    assert [r["file"] for r in rows] == ["GX010042.MP4", "GX020042.MP4"]
    assert rows[1]["start_ns"] == CREATED_NS + round(Fraction(rows[0]["duration_exact_s"]) * 10**9)
    assert document["devices"]["cam0"]["model"] == "HERO9 Black"
    assert document["devices"]["cam0"]["serial"] == "C3441324567890"
    # Every keyframe decodes on its own (parameter sets in-band).
    with SessionVideo(tmp_path / "joined") as video:
        keys = video.keyframe_times_ns()
        assert len(keys) == 12
        frame = video.frame_at(keys[7])
        assert frame.keyframe and frame.stamp_ns == keys[7]


def test_dcim_folder_groups_recordings_and_skips_imported_ones(
    tmp_path: Path, chapters: list[Path], recording: dict[str, Any]
) -> None:
    dcim = tmp_path / "DCIM" / "100GOPRO"
    dcim.mkdir(parents=True)
    for path in chapters:
        os.link(path, dcim / path.name)
    write_gopro_mp4(
        dcim / "GX010043.MP4",
        **{**recording, "creation_time": datetime(2024, 5, 1, 11, tzinfo=UTC)},
    )
    (dcim / "GL010043.LRV").write_bytes(b"low-res preview, ignored")
    out = tmp_path / "sessions"
    results = import_videos(ImportOptions(), [tmp_path / "DCIM"], out)
    assert [(r.recording, r.status, r.frames) for r in results] == [
        ("20240501-100000_GX0042", "imported", 180),
        ("20240501-110000_GX0043", "imported", 180),
    ]
    assert sorted(p.name for p in out.iterdir()) == [
        "20240501-100000_GX0042",
        "20240501-110000_GX0043",
    ]
    again = import_videos(ImportOptions(), [tmp_path / "DCIM"], out)
    assert [r.status for r in again] == ["skipped", "skipped"]


def test_cli_imports_a_folder_as_a_subprocess(tmp_path: Path, chapters: list[Path]) -> None:
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    command = [
        sys.executable,
        "-m",
        "field.cli",
        "gopro",
        "import",
        str(chapters[0].parent),
        "--out",
        str(tmp_path / "out"),
    ]
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "imported 180 frames" in done.stdout
    again = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "already imported, skipped" in again.stdout
    bad = subprocess.run(
        [*command[:5], str(tmp_path / "nope.MP4"), "--out", str(tmp_path / "x")],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert bad.returncode == 1 and "nope.MP4: no such file or folder" in bad.stderr


# ----------------------------------------------------------------------------- bad input


def _strip_moov(source: Path, target: Path) -> None:
    """A copy of `source` cut where its 'moov' starts (a camera whose battery died)."""
    data = source.read_bytes()
    moov = data.rindex(b"moov") - 4
    target.write_bytes(data[:moov])


def test_unfinalised_last_chapter_is_salvaged_from_its_sibling(
    tmp_path: Path, chapters: list[Path]
) -> None:
    folder = tmp_path / "card"
    folder.mkdir()
    os.link(chapters[0], folder / chapters[0].name)
    _strip_moov(chapters[1], folder / chapters[1].name)
    result = import_recording(ImportOptions(), sorted(folder.iterdir()), tmp_path / "s")
    assert result.frames == 6 * FRAMES_PER_PAYLOAD  # every frame of chapter 2 recovered
    assert any("not finalised" in w and "salvaged 90 frames" in w for w in result.warnings)
    stamps, _ = _video_stamps(tmp_path / "s")
    assert np.all(np.diff(stamps) > 0)
    # Salvaged frames decode, and equal the frames of the finalised file.
    with SessionVideo(tmp_path / "s") as video:
        salvaged = video.frame_at(stamps[150])
    reference = import_recording(ImportOptions(), chapters, tmp_path / "ref")
    assert reference.frames == result.frames
    with SessionVideo(tmp_path / "ref") as video:
        expected = video.frame_at(stamps[150])
    assert np.array_equal(salvaged.image, expected.image)
    with ArchiveReader(tmp_path / "s" / "recording.mcap") as reader:
        assert reader.read_imu().stamps_ns.size == 6 * IMU_PER_PAYLOAD  # telemetry salvaged too


def test_unfinalised_file_alone_needs_parameter_sets(tmp_path: Path, chapters: list[Path]) -> None:
    cut = tmp_path / "GX010077.MP4"
    _strip_moov(chapters[1], cut)
    with pytest.raises(InputError, match=r"GX010077.MP4: no 'moov' index.*--parameter-sets"):
        import_recording(ImportOptions(), [cut], tmp_path / "s")
    assert not (tmp_path / "s").exists()
    options = ImportOptions(parameter_sets_from=chapters[0])
    result = import_recording(options, [cut], tmp_path / "s")
    assert result.frames == 3 * FRAMES_PER_PAYLOAD


def test_unfinalised_file_without_video_raises(tmp_path: Path, chapters: list[Path]) -> None:
    cut = tmp_path / "GX010078.MP4"
    data = chapters[0].read_bytes()
    mdat = data.index(b"mdat") - 4
    cut.write_bytes(data[: mdat + 8] + bytes(5000))  # the mdat header, then zeros
    with pytest.raises(InputError, match="no decodable video found"):
        import_recording(ImportOptions(parameter_sets_from=chapters[0]), [cut], tmp_path / "s")


def test_file_without_gpmf_track_imports_video_only(tmp_path: Path, chapters: list[Path]) -> None:
    data = chapters[0].read_bytes()
    moov = data.rindex(b"moov")
    patched = tmp_path / "GX010050.MP4"
    patched.write_bytes(data[:moov] + data[moov:].replace(b"gpmd", b"xxxx"))
    result = import_recording(ImportOptions(), [patched], tmp_path / "s")
    assert result.imu_samples == 0 and result.frames == 90
    assert any("GX010050.MP4: no GPMF track" in w for w in result.warnings)
    with ArchiveReader(tmp_path / "s" / "recording.mcap") as reader:
        assert "/imu0" not in reader.topics()
    assert not (tmp_path / "s" / "calib" / "imu.yaml").exists()
    with pytest.raises(InputError, match=r"GX010050\.MP4: no GPMF track"):
        import_recording(ImportOptions(require_imu=True), [patched], tmp_path / "t")
    assert not (tmp_path / "t").exists()


def test_chapters_from_two_recordings_are_refused(
    tmp_path: Path, chapters: list[Path], recording: dict[str, object]
) -> None:
    other = write_gopro_mp4(tmp_path / "GX010043.MP4", **recording)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="chapters from two different recordings"):
        import_recording(ImportOptions(), [chapters[0], other], tmp_path / "s")
    stranger = write_gopro_mp4(
        tmp_path / "b" / "GX020042.MP4",
        **{**recording, "serial": "C9999999999999"},  # type: ignore[arg-type]
    )
    with pytest.raises(InputError, match=r"GX020042\.MP4: chapters from two different recordings"):
        import_recording(ImportOptions(), [chapters[0], stranger], tmp_path / "s")
    with pytest.raises(InputError, match=r"chapter\(s\) \[1\] missing"):
        import_recording(ImportOptions(), [chapters[1]], tmp_path / "s")
    assert not (tmp_path / "s").exists()


def test_corrupt_payloads_are_skipped_with_warnings(tmp_path: Path, chapters: list[Path]) -> None:
    mp4 = read_mp4(chapters[0])
    video, meta = mp4.video_track(), mp4.gpmf_track()
    data = bytearray(chapters[0].read_bytes())
    offset = int(video.sample_offsets[3])  # frame 3: its NAL length now runs past the sample
    data[offset : offset + 4] = (10**6).to_bytes(4, "big")
    offset = int(meta.sample_offsets[1])  # payload 1: a nest longer than the payload
    data[offset + 6 : offset + 8] = b"\xff\xff"
    broken = tmp_path / "GX010060.MP4"
    broken.write_bytes(bytes(data))
    result = import_recording(ImportOptions(), [broken], tmp_path / "s")
    # Frames 3..14 depend on frame 3 (next keyframe at 15): skipped.
    assert result.frames == 90 - 12
    assert any("GX010060.MP4: frame 3" in w for w in result.warnings)
    assert any("12 corrupt video packet(s) skipped" in w for w in result.warnings)
    assert any("1 of 3 GPMF payloads corrupt" in w for w in result.warnings)
    assert result.imu_samples == 2 * IMU_PER_PAYLOAD
    document = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    assert len(document["warnings"]) == 3


def test_failure_leaves_no_session_and_existing_sessions_are_kept(
    tmp_path: Path, chapters: list[Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    junk = tmp_path / "GX020042.MP4"
    junk.write_bytes(b"this is not an mp4 file at all")
    with pytest.raises(InputError, match=r"GX020042\.MP4: box ' is ' at byte 0"):
        import_recording(ImportOptions(), [chapters[0], junk], tmp_path / "s")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["GX020042.MP4"]
    # A crash half-way through writing (here: the disk fills up) leaves nothing behind either.
    import field.gopro.annexb as annexb
    import field.gopro.importer as importer

    real = annexb.to_annexb  # the function importer.to_annexb names
    calls = []

    def failing(*args: object, **kwargs: object) -> bytes:
        calls.append(1)
        if len(calls) == 50:
            raise OSError(28, "No space left on device")
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(importer, "to_annexb", failing)
    with pytest.raises(OSError, match="No space left"):
        import_recording(ImportOptions(), chapters, tmp_path / "s")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["GX020042.MP4"]
    monkeypatch.undo()
    (tmp_path / "s").mkdir()
    with pytest.raises(OutputExistsError):
        import_recording(ImportOptions(), [chapters[0]], tmp_path / "s")
    with pytest.raises(InputError, match="no video files given"):
        import_recording(ImportOptions(), [], tmp_path / "t")
    with pytest.raises(InputError, match="nothing to import"):
        import_videos(ImportOptions(), [], tmp_path / "t")


def test_dcim_failure_of_one_recording_does_not_stop_the_others(
    tmp_path: Path, chapters: list[Path]
) -> None:
    card = tmp_path / "DCIM"
    card.mkdir()
    os.link(chapters[0], card / "GX010042.MP4")
    (card / "GX010044.MP4").write_bytes(b"\x00\x00\x00\x08junk")
    results = import_videos(ImportOptions(), [card], tmp_path / "out")
    assert [r.status for r in results] == ["imported", "failed"]
    assert "GX010044.MP4" in (results[1].error or "")


def test_camera_table_and_intrinsics_guess() -> None:
    hero5 = cameras.lookup_camera(firmware="HD5.02.02.00.00")
    assert hero5.name == "HERO5 Black"
    assert cameras.lookup_camera(firmware="XX1", gpmf_model="GoPro Max").name == "GoPro Max"
    assert cameras.lookup_camera(firmware="ZZ9.99") is cameras.UNKNOWN_CAMERA
    assert cameras.camera_model_name(firmware="ZZ9.99") == "GoPro (firmware ZZ9.99)"
    air = cameras.guess_camera(hero5, width=1920, height=1080, medium="air")
    water = cameras.guess_camera(hero5, width=1920, height=1080, medium="water")
    assert water.fx == pytest.approx(air.fx * cameras.WATER_REFRACTIVE_INDEX)
    # The image edge is half the Wide field of view away from the axis.
    edge = air.unproject(np.array([[1919.5, 539.5]]))[0]
    assert np.degrees(np.arctan2(edge[0], edge[2])) == pytest.approx(118.2 / 2, abs=0.1)
    # "ZXY" (the default order): (Z up, X right, Y forward) -> body (x right, y down, z fwd).
    body = cameras.body_from_file_axes("ZXY") @ np.array([9.81, 0.0, 0.0])
    assert np.allclose(body, [0.0, -9.81, 0.0])
    assert np.allclose(cameras.body_from_file_axes("XzY") @ GRAVITY_FILE_ORDER, [0, -9.81, 0])
    assert np.linalg.det(cameras.body_from_file_axes("YxZ")) == pytest.approx(1.0)
    with pytest.raises(InputError, match="permutation of XYZ"):
        cameras.axis_order_matrix("XXY")
    with pytest.raises(InputError, match="expected positive"):
        cameras.guess_camera(hero5, width=0, height=10)
    with pytest.raises(InputError, match="medium 'oil'"):
        cameras.guess_camera(hero5, width=10, height=10, medium="oil")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="positive rate"):
        cameras.gopro_imu_noise(0.0)


def test_annexb_conversion_rules() -> None:
    from field.gopro.annexb import to_annexb

    sps, pps, idr, p_slice = b"\x67\x42", b"\x68\xce", b"\x65\x88\x84", b"\x41\x9a"
    header = b"\0\0\0\1" + sps + b"\0\0\0\1" + pps

    def avcc(*units: bytes) -> bytes:
        return b"".join(len(u).to_bytes(4, "big") + u for u in units)

    common = {"codec": "h264", "nal_length_size": 4, "parameter_sets": header, "where": "t.mp4"}
    assert to_annexb(avcc(idr), keyframe=True, **common) == header + b"\0\0\0\1" + idr  # type: ignore[arg-type]
    assert to_annexb(avcc(p_slice), keyframe=False, **common) == b"\0\0\0\1" + p_slice  # type: ignore[arg-type]
    in_band = avcc(sps, pps, idr)
    assert to_annexb(in_band, keyframe=True, **common).count(sps) == 1  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"t\.mp4: NAL unit of 9 bytes"):
        to_annexb(b"\0\0\0\x09\x65ab", keyframe=True, **common)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="NAL length field cut"):
        to_annexb(b"\0\0", keyframe=False, **common)  # type: ignore[arg-type]
    vps, hsps, hidr = b"\x40\x01\x0c", b"\x42\x01\x01", b"\x26\x01\xaf"
    h265 = {**common, "codec": "h265", "parameter_sets": b"\0\0\0\1" + vps}
    assert to_annexb(avcc(hidr), keyframe=True, **h265).startswith(b"\0\0\0\1" + vps)  # type: ignore[arg-type]
    assert not to_annexb(avcc(hsps, hidr), keyframe=True, **h265).startswith(b"\0\0\0\1" + vps)  # type: ignore[arg-type]


def test_recording_cut_inside_the_media_data_keeps_what_was_written(
    tmp_path: Path, chapters: list[Path]
) -> None:
    """Battery died mid-write: mdat declares more bytes than the file has, no moov."""
    data = chapters[1].read_bytes()
    mp4 = read_mp4(chapters[1])
    video = mp4.video_track()
    cut_at = int(video.sample_offsets[60]) + 100  # inside frame 60
    folder = tmp_path / "card"
    folder.mkdir()
    os.link(chapters[0], folder / chapters[0].name)
    (folder / chapters[1].name).write_bytes(data[:cut_at])
    result = import_recording(ImportOptions(), sorted(folder.iterdir()), tmp_path / "s")
    assert result.frames == 90 + 60  # frames 0..59 of chapter 2 are whole; 60 is cut
    with SessionVideo(tmp_path / "s") as stored:
        frames = list(stored.frames())
    assert len(frames) == 150
    document = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    assert document["chapters"][1]["finalised"] is False


def test_given_calibration_is_copied_and_checked(tmp_path: Path, chapters: list[Path]) -> None:
    from shared.calibration.cameras import PinholeRadtan
    from shared.calibration.kalibr import (
        CameraCalibration,
        ImuNoise,
        write_camchain,
        write_imu_yaml,
    )

    camchain = write_camchain(
        tmp_path / "camchain.yaml",
        [CameraCalibration(camera=PinholeRadtan(160, 120, 100.0, 101.0, 80.0, 60.0, k1=-0.1))],
    )
    imu_yaml = write_imu_yaml(tmp_path / "imu.yaml", ImuNoise(1e-3, 1e-4, 1e-4, 1e-5, 200.0))
    options = ImportOptions(camchain=camchain, imu_yaml=imu_yaml)
    import_recording(options, [chapters[0]], tmp_path / "s")
    assert (tmp_path / "s" / "calib" / "camchain.yaml").read_text() == camchain.read_text()
    assert read_imu_yaml(tmp_path / "s" / "calib" / "imu.yaml").gyroscope_noise_density == 1e-4
    document = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    assert document["calibration"]["camchain_source"] == "given (camchain.yaml)"
    wrong = write_camchain(
        tmp_path / "wrong.yaml",
        [CameraCalibration(camera=PinholeRadtan(1920, 1080, 1000.0, 1000.0, 960.0, 540.0))],
    )
    with pytest.raises(
        InputError, match="calibrated for 1920x1080 pixels, but the video is 160x120"
    ):
        import_recording(ImportOptions(camchain=wrong), [chapters[0]], tmp_path / "t")
    assert not (tmp_path / "t").exists()


@pytest.mark.parametrize(("name", "frames"), [("karma.mp4", 362), ("max-heromode.mp4", 315)])
def test_real_unfinalised_file_is_salvaged_frame_for_frame(
    shared_data: Path, tmp_path: Path, name: str, frames: int
) -> None:
    """A real file without its moov: audio, SOS samples and GoPro's GPRO block stay in the
    mdat between the video samples; every frame comes back pixel for pixel."""
    from field.gopro.frames import iter_mp4_frames

    source = shared_data / "gopro" / name
    data = source.read_bytes()
    cut = tmp_path / "GX019999.MP4"
    cut.write_bytes(data[: data.rindex(b"moov") - 4])
    result = import_recording(ImportOptions(parameter_sets_from=source), [cut], tmp_path / "s")
    assert result.frames == frames
    finalised = import_recording(ImportOptions(), [source], tmp_path / "f")
    assert result.imu_samples == finalised.imu_samples
    direct = list(iter_mp4_frames(source, grayscale=True, scale=0.25))
    with SessionVideo(tmp_path / "s", grayscale=True, scale=0.25) as video:
        salvaged = list(video.frames())
    assert len(salvaged) == frames
    assert all(np.array_equal(a.image, b.image) for a, b in zip(salvaged, direct, strict=True))
