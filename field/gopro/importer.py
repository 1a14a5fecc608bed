"""Import GoPro recordings (all chapters) into wreckmap session folders.

    import_recording(ImportOptions(), [Path("GX010042.MP4"), Path("GX020042.MP4")],
                     Path("sessions/dive1"))
    import_videos(ImportOptions(), [Path("/media/sd/DCIM")], Path("sessions"))

A session folder (conventions.md) gets:

- `recording.mcap`: `/cam0/video` as `foxglove_msgs/msg/CompressedVideo`
  (H.264/H.265 access units copied from the MP4 without decoding, converted
  to Annex B with the parameter sets in-band on every keyframe), `/imu0` as
  `sensor_msgs/msg/Imu` in the camera-aligned body frame (see
  `field.gopro.cameras`), `/session` with the session.yaml text;
- `metadata.yaml`, so the folder is also a rosbag2 bag;
- `calib/camchain.yaml` (intrinsics guessed from camera model and resolution
  unless a calibration is given; `T_cam_imu` identity) and `calib/imu.yaml`
  (typical GoPro noise, the measured rate);
- `session.yaml`: id, camera model, serial, firmware, chapters, clocks, warnings.

**Time base.** `header.stamp` = creation time of the first chapter (the
camera's wall clock as written in mvhd, ns since the UNIX epoch; GoPro
writes local time without a zone, recorded as such in session.yaml) + media
time. Chapters are joined on one continuous clock: chapter k starts where
chapter k-1 ends, using each chapter's exact video duration (sum of its
sample durations, a rational number of seconds; rounded to the nanosecond
once per chapter). Video stamps are presentation times; the MCAP log time is
the stamp, except with B-frames where it is the decode time so that log-time
order stays decode order. IMU times come from the one GPMF reader
(`field.gopro.telemetry.assemble_telemetry`, the timing model of
`field.gopro.timing`) on each chapter's media clock, as the camera stamped
them: a corrupt or missing payload leaves a gap and shifts nothing, and an
IMU that starts after the first frame is kept so (session.yaml's
`imu_start_s` per chapter; a warning above 20 ms); samples of chapter k
that fall at or before the last sample of chapter k-1 (the telemetry of
consecutive chapters overlaps by a few ms) are dropped so stamps strictly
increase.

**IMU.** GoPro samples ACCL and GYRO separately (HERO5: 200 and 400 Hz; HERO8+
both ~200 Hz). The faster stream sets the sample times; the other is
linearly interpolated to them (samples outside its time range are dropped).

**Failure.** Everything is written in a hidden temporary folder beside the
session folder and renamed at the end; the archive itself is written as
`.part` until closed. A failure leaves no session folder. Bad input gives an
InputError naming the file: unfinalised chapters are salvaged (see
`field.gopro.salvage`) when parameter sets are known, corrupt video packets
are skipped up to the next keyframe, corrupt GPMF payloads are skipped, a
file without telemetry imports its video only; each such event is listed
under `warnings` in session.yaml.
"""

from __future__ import annotations

import itertools
import logging
import re
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from field.gopro import cameras
from field.gopro.annexb import CODEC_NAMES, to_annexb
from field.gopro.gpmf import GPMFError, decode_value, parse_klv
from field.gopro.mp4 import (
    CodecConfig,
    MissingMoovError,
    MP4File,
    Track,
    parse_codec_config,
    read_mp4,
)
from field.gopro.salvage import salvage_mdat
from field.gopro.telemetry import GPMFSample, assemble_telemetry, iter_gpmf_samples
from shared.archive import (
    HEALTH_TOPIC,
    ArchiveWriter,
    CompressedVideo,
    Imu,
    RecorderEvent,
    SessionInfo,
    imu_topic,
    video_topic,
    write_rosbag2_metadata,
)
from shared.archive.video import FRAME_SIZE_METADATA, KEYFRAME_METADATA
from shared.archive.writer import Compression
from shared.clock import NS_PER_S, seconds_from_ns
from shared.errors import InputError, OutputExistsError, WreckmapError
from shared.folders import SessionFolder
from shared.fsutil import atomic_path, write_text_atomic
from shared.progress import progress_bar

log = logging.getLogger(__name__)

SESSION_METADATA_KEYS = ("session_id", "source", "camera_model", "serial", "firmware")

# GoPro file names: GX/GH (HERO6+; chapter 01.., file number), GOPR + GPcc (HERO5 and older).
_NEW_NAME = re.compile(r"^(G[XHLS])(\d{2})(\d{4})\.MP4$", re.IGNORECASE)
_OLD_FIRST = re.compile(r"^GOPR(\d{4})\.MP4$", re.IGNORECASE)
_OLD_NEXT = re.compile(r"^GP(\d{2})(\d{4})\.MP4$", re.IGNORECASE)
VIDEO_SUFFIXES = (".mp4",)


# ------------------------------------------------------------------------------- options


@dataclass(kw_only=True)
class ImportOptions:
    """How to import.

    medium: "water" or "air", for the intrinsics guess (flat-port focal factor).
    camchain: a Kalibr camchain.yaml to copy into calib/ instead of the guess.
    imu_yaml: a Kalibr imu.yaml to copy instead of the typical GoPro values.
    parameter_sets_from: a finalised MP4 of the same camera mode whose SPS/PPS
        decode an unfinalised chapter that has no sibling chapter.
    salvage_fps: frame rate (Hz) assumed for a salvaged chapter without a
        finalised sibling (None: refuse to guess).
    require_imu: a chapter without GPMF IMU data is an error (else a warning).
    compression: MCAP chunk compression; "none" by default since H.264/H.265
        packets do not compress and zstd would halve the import speed.
    chunk_size_bytes: MCAP chunk size (uncompressed bytes); smaller chunks
        make random access by time finer.
    camera_index / imu_index: topic numbers (`/cam{N}/video`, `/imu{N}`).
    """

    medium: cameras.Medium = "water"
    camchain: Path | None = None
    imu_yaml: Path | None = None
    parameter_sets_from: Path | None = None
    salvage_fps: float | None = None
    require_imu: bool = False
    compression: Compression = "none"
    chunk_size_bytes: int = 4 * 2**20
    camera_index: int = 0
    imu_index: int = 0


# ------------------------------------------------------------------------------- chapters


@dataclass(frozen=True, order=True)
class Chapter:
    """One chapter file: `family` ("GX", "GH", "GOPR", or the stem for other names),
    `file_number` (the 4 digits shared by a recording's chapters, -1 when unknown),
    `index` (1-based chapter order within the recording)."""

    family: str
    file_number: int
    index: int
    path: Path = field(compare=False)


def parse_chapter(path: Path) -> Chapter:
    """The chapter a file name says it is (GX010042.MP4 -> GX, 42, chapter 1).

    HERO6+ name chapters GXccnnnn (cc = 01, 02, ...); HERO5 and older name the
    first chapter GOPRnnnn and the next ones GP01nnnn, GP02nnnn... Any other
    name is a recording of its own (family = its stem, chapter 1).
    """
    name = path.name
    if match := _NEW_NAME.match(name):
        family = match.group(1).upper()
        return Chapter(family, int(match.group(3)), int(match.group(2)), path)
    if match := _OLD_FIRST.match(name):
        return Chapter("GOPR", int(match.group(1)), 1, path)
    if match := _OLD_NEXT.match(name):
        return Chapter("GOPR", int(match.group(2)), int(match.group(1)) + 1, path)
    return Chapter(path.stem, -1, 1, path)


@dataclass(frozen=True)
class Recording:
    """The chapters of one recording, in order."""

    chapters: tuple[Chapter, ...]

    @property
    def name(self) -> str:
        first = self.chapters[0]
        if first.file_number < 0:
            return first.family
        return f"{first.family}{first.file_number:04d}"


def group_recordings(paths: Sequence[Path]) -> list[Recording]:
    """Group chapter files into recordings (by name family and file number), chapters sorted.

    Raises InputError when a file appears twice or a chapter number repeats.
    """
    groups: dict[tuple[str, int], list[Chapter]] = {}
    seen: set[Path] = set()
    for path in paths:
        resolved = path.resolve()
        if resolved in seen:
            raise InputError(f"{path}: given twice")
        seen.add(resolved)
        chapter = parse_chapter(path)
        key = (chapter.family, chapter.file_number)
        if chapter.file_number < 0:
            key = (str(resolved), -1)
        groups.setdefault(key, []).append(chapter)
    recordings = []
    for chapters in groups.values():
        chapters.sort()
        for a, b in itertools.pairwise(chapters):
            if a.index == b.index:
                raise InputError(
                    f"{b.path.name}: chapter {b.index} of recording {a.family}{a.file_number:04d} "
                    f"given twice (also {a.path})"
                )
        recordings.append(Recording(tuple(chapters)))
    recordings.sort(key=lambda r: (r.chapters[0].path.parent.as_posix(), r.name))
    return recordings


def find_videos(folder: Path) -> list[Path]:
    """Every GoPro-looking .MP4 under `folder` (recursively; hidden files and LRV/THM skipped)."""
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    found = [
        path
        for path in sorted(folder.rglob("*"))
        if path.is_file()
        and path.suffix.lower() in VIDEO_SUFFIXES
        and not any(part.startswith(".") for part in path.relative_to(folder).parts)
    ]
    return found


# ------------------------------------------------------------------------------- results


@dataclass
class ImportResult:
    """One recording's outcome: `status` "imported", "skipped" (already there) or "failed"."""

    recording: str
    session_dir: Path
    status: str
    frames: int = 0
    imu_samples: int = 0
    duration_s: float = 0.0
    bytes_read: int = 0
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)
    error: str | None = None


# ------------------------------------------------------------------------------- per chapter


@dataclass
class _ChapterVideo:
    """One chapter's video: packets as (file offset, size) or salvaged bytes, and times."""

    chapter: Chapter
    mp4: MP4File | None
    track: Track | None
    config: CodecConfig
    timescale: int
    duration: Fraction  # seconds, exact
    pts_ns: np.ndarray  # media time of each packet (presentation), int64 ns
    dts_ns: np.ndarray  # media time of each packet (decode), int64 ns
    keyframes: np.ndarray
    salvaged_packets: list[bytes] | None = None
    gpmf_payloads: list[bytes] | None = None

    @property
    def frames(self) -> int:
        return int(self.keyframes.shape[0])

    @property
    def codec(self) -> str:
        """ "h264" or "h265" (the CompressedVideo format)."""
        return CODEC_NAMES[self.config.codec]

    @property
    def video_bytes(self) -> int:
        if self.track is not None:
            return int(self.track.sample_sizes.sum(dtype=np.int64))
        return sum(len(p) for p in self.salvaged_packets or [])


def _ticks_to_ns(ticks: np.ndarray, timescale: int) -> np.ndarray:
    """Media ticks -> ns, exact integer rounding (half up)."""
    ticks = ticks.astype(np.int64)
    return (ticks * NS_PER_S + timescale // 2) // timescale


def _open_chapter(chapter: Chapter) -> MP4File | MissingMoovError:
    try:
        return read_mp4(chapter.path)
    except MissingMoovError as error:
        return error


def _video_of(chapter: Chapter, mp4: MP4File) -> _ChapterVideo:
    track = mp4.video_track()
    if track.sample_count == 0:
        raise InputError(f"{chapter.path.name}: video track has no samples")
    config = parse_codec_config(
        track.codec, track.codec_config, source=f"{chapter.path.name}: track {track.track_id}"
    )
    if not config.parameter_sets:
        raise InputError(f"{chapter.path.name}: {track.codec} has no SPS/PPS in its sample entry")
    start = int(track.edit_media_time)
    pts = track.composition_times.astype(np.int64) - start
    dts = track.decode_times.astype(np.int64) - start
    duration = Fraction(int(track.durations.sum(dtype=np.int64)), track.timescale)
    if not bool(track.keyframes[0]):
        raise InputError(f"{chapter.path.name}: the video does not start with a keyframe")
    return _ChapterVideo(
        chapter=chapter,
        mp4=mp4,
        track=track,
        config=config,
        timescale=track.timescale,
        duration=duration,
        pts_ns=_ticks_to_ns(pts, track.timescale),
        dts_ns=_ticks_to_ns(dts, track.timescale),
        keyframes=track.keyframes.astype(bool),
    )


def _salvaged_video(
    chapter: Chapter,
    error: MissingMoovError,
    *,
    config: CodecConfig,
    fps: Fraction,
    aud_first: bool,
    warnings: list[str],
) -> _ChapterVideo:
    if error.mdat_offset is None or error.mdat_size is None:
        raise InputError(f"{chapter.path.name}: no 'moov' index and no media data to salvage")
    salvaged = salvage_mdat(
        chapter.path,
        mdat_offset=error.mdat_offset,
        mdat_size=error.mdat_size,
        codec=CODEC_NAMES[config.codec],
        parameter_sets=config.parameter_sets,
        frames_start_with_aud=aud_first,
    )
    n = len(salvaged.packets)
    index = np.arange(n, dtype=np.int64)
    times = (index * NS_PER_S * fps.denominator + fps.numerator // 2) // fps.numerator
    warnings.append(
        f"{chapter.path.name}: not finalised (no 'moov' index); salvaged {n} frames by "
        f"scanning the media data, timed at a constant {float(fps):.3f} fps"
        + ("" if salvaged.parameter_sets_in_band else " with parameter sets of a sibling file")
        + (
            f"; {salvaged.dropped_leading_units} NAL units before the first keyframe dropped"
            if salvaged.dropped_leading_units
            else ""
        )
    )
    return _ChapterVideo(
        chapter=chapter,
        mp4=None,
        track=None,
        config=config,
        timescale=fps.numerator,
        duration=Fraction(n) / fps,
        pts_ns=times,
        dts_ns=times,
        keyframes=np.asarray(salvaged.keyframes, dtype=bool),
        salvaged_packets=salvaged.packets,
        gpmf_payloads=salvaged.gpmf_payloads,
    )


@dataclass
class _ChapterImu:
    """IMU samples of one chapter on its media clock, in the body frame B."""

    times_ns: np.ndarray  # int64, media time
    gyro_rad_s: np.ndarray  # (N, 3)
    accel_m_s2: np.ndarray  # (N, 3)
    gyro_rate_hz: float
    accel_rate_hz: float
    axis_order: str
    axis_order_source: str
    timing_method: str
    clock_origin: str  # how STMP was tied to the chapter's media time


# An IMU that starts more than this after video frame 0 is said in a warning: four samples at
# 200 Hz, above the few ms by which the start the TSMP fit gives (HERO5-7) moves with the payloads
# it is fitted to (karma.mp4 starts 11 ms after its first frame; 2-3 ms change with 2 of its 13
# payloads lost).
_LATE_IMU_NS = 20_000_000


def _gpmf_samples(video: _ChapterVideo, warnings: list[str]) -> Iterable[GPMFSample] | None:
    """The chapter's stored GPMF payloads, or None (with a warning) when it has none."""
    if video.mp4 is not None:
        try:
            video.mp4.gpmf_track()
        except InputError as error:
            warnings.append(str(error))
            return None
        return iter_gpmf_samples(video.mp4)
    raw = video.gpmf_payloads or []
    if not raw:
        return None
    # No sample table: GoPro flushes telemetry about every 1.001 s; STMP refines it.
    return [
        GPMFSample(index=index, start_s=index * 1.001, duration_s=1.001, data=data)
        for index, data in enumerate(raw)
    ]


def _read_chapter_imu(
    video: _ChapterVideo, camera: cameras.GoProCamera, warnings: list[str]
) -> _ChapterImu | None:
    """ACCL + GYRO of a chapter in the body frame, or None (with a warning) when absent.

    The streams and their sample times come from `assemble_telemetry`, the
    reader `gopro telemetry` uses too; here they are turned to the body frame
    and put on one time base.
    """
    name = video.chapter.path.name
    samples = _gpmf_samples(video, warnings)
    if samples is None:
        return None
    found = assemble_telemetry(samples, source=name, keys=("ACCL", "GYRO"))
    warnings.extend(found.warnings)
    missing = [key for key in ("ACCL", "GYRO") if key not in found.streams]
    if missing:
        reasons = [
            found.skipped[key]
            for key in missing
            if key in found.skipped and "no GPMF stream" not in found.skipped[key]
        ]
        warnings.append(
            f"{name}: no {' or '.join(missing)} samples in the GPMF track "
            "(expected the camera's accelerometer and gyroscope); video imported without IMU"
            + (f" ({'; '.join(reasons)})" if reasons else "")
        )
        return None
    streams = {key: found.streams[key] for key in ("ACCL", "GYRO")}
    values = {}
    for key, stream in streams.items():
        order = stream.orientation_in or camera.imu_axis_order
        if stream.elements != 3:
            problem = f"{key} has {stream.elements} values per sample (expected 3)"
        elif order is None:
            problem = (
                f"{key} has no ORIN and the axis order of this camera model "
                f"({camera.name}) is unknown"
            )
        else:
            body_from_file = cameras.body_from_file_axes(order, source=f"{name}: {key}")
            values[key] = stream.values @ body_from_file.T
            continue
        warnings.append(f"{name}: {problem}; video imported without IMU")
        return None
    accel_t = streams["ACCL"].times_ns
    gyro_t = streams["GYRO"].times_ns
    gyro = values["GYRO"]
    accel = values["ACCL"]
    if accel_t.shape == gyro_t.shape and np.array_equal(accel_t, gyro_t):
        times = gyro_t
    else:
        base_is_gyro = gyro_t.shape[0] >= accel_t.shape[0]
        base_t, other_t, other = (
            (gyro_t, accel_t, accel) if base_is_gyro else (accel_t, gyro_t, gyro)
        )
        keep = (base_t >= other_t[0]) & (base_t <= other_t[-1])
        base_t = base_t[keep]
        resampled = np.column_stack(
            [np.interp(base_t, other_t, other[:, axis]) for axis in range(3)]
        )
        if base_is_gyro:
            gyro, accel = gyro[keep], resampled
        else:
            gyro, accel = resampled, accel[keep]
        times = base_t
    increasing = np.concatenate([[True], np.diff(times) > 0])
    if not increasing.all():
        warnings.append(f"{name}: {int((~increasing).sum())} IMU samples out of time order dropped")
        times, gyro, accel = times[increasing], gyro[increasing], accel[increasing]
    gyro_stream = streams["GYRO"]
    if times.size:
        late_ns = int(times[0]) - int(video.pts_ns.min())
        if late_ns > _LATE_IMU_NS:
            warnings.append(
                f"{name}: the IMU starts {late_ns / 1e6:.1f} ms after the first video frame "
                "(its samples keep the camera's times; the first frames have no IMU before them)"
            )
    return _ChapterImu(
        times_ns=times,
        gyro_rad_s=gyro,
        accel_m_s2=accel,
        gyro_rate_hz=gyro_stream.rate_hz,
        accel_rate_hz=streams["ACCL"].rate_hz,
        axis_order=gyro_stream.orientation_in or camera.imu_axis_order or "",
        axis_order_source="ORIN" if gyro_stream.orientation_in else f"model ({camera.name})",
        timing_method=gyro_stream.timing_method,
        clock_origin=found.clock_origin,
    )


# ------------------------------------------------------------------------------- camera facts


@dataclass
class _CameraFacts:
    model: str
    firmware: str | None
    serial: str | None
    camera_id: str | None
    lens: str | None
    gpmf_model: str | None
    lens_mode: str | None


def _camera_facts(mp4: MP4File | None) -> _CameraFacts:
    if mp4 is None:
        return _CameraFacts("GoPro (unknown model)", None, None, None, None, None, None)
    firmware = mp4.text_atom("FIRM")
    lens = mp4.text_atom("LENS")
    came = mp4.user_data.get("CAME")
    camera_id = came.hex() if came and any(came) else None
    serial = model = lens_mode = None
    settings = mp4.user_data.get("GPMF")
    if settings:
        try:
            for klv in _walk(parse_klv(settings, source=mp4.name)):
                if klv.key in ("CASN", "MINF", "VFOV") and klv.type == "c":
                    text = str(decode_value(klv, source=mp4.name)).strip("\x00 ")
                    if klv.key == "CASN":
                        serial = text or None
                    elif klv.key == "MINF":
                        model = text or None
                    else:
                        lens_mode = text or None
        except GPMFError as error:
            log.warning("%s: unreadable GPMF settings in udta (%s)", mp4.name, error)
    return _CameraFacts(
        model=cameras.camera_model_name(firmware=firmware, gpmf_model=model),
        firmware=firmware,
        serial=serial,
        camera_id=camera_id,
        lens=lens or None,
        gpmf_model=model,
        lens_mode=lens_mode,
    )


def _walk(klvs: Sequence[Any]) -> list[Any]:
    out = []
    for klv in klvs:
        out.append(klv)
        out.extend(_walk(klv.children))
    return out


# ------------------------------------------------------------------------------- checks


def _check_same_recording(chapters: Sequence[Chapter], mp4s: Sequence[MP4File | None]) -> None:
    """InputError when the chapters cannot be one recording (names, camera, format)."""
    first = chapters[0]
    for chapter in chapters[1:]:
        if (chapter.family, chapter.file_number) != (first.family, first.file_number):
            raise InputError(
                f"{chapter.path.name}: belongs to another recording than {first.path.name} "
                f"(chapters from two different recordings: file numbers "
                f"{first.family}{first.file_number:04d} and "
                f"{chapter.family}{chapter.file_number:04d}); import them separately"
            )
    expected = list(range(chapters[0].index, chapters[0].index + len(chapters)))
    found = [c.index for c in chapters]
    if found != expected or found[0] != 1:
        missing = sorted(set(range(1, found[-1] + 1)) - set(found))
        raise InputError(
            f"{first.family}{first.file_number:04d}: chapter(s) {missing} missing "
            f"(found {found}); a recording's chapters must all be imported together"
        )
    reference: tuple[MP4File, tuple[Any, ...]] | None = None
    for chapter, mp4 in zip(chapters, mp4s, strict=True):
        if mp4 is None:
            continue
        video = mp4.video_track()
        key = (
            mp4.user_data.get("CAME"),
            mp4.text_atom("FIRM"),
            video.codec,
            video.width,
            video.height,
        )
        if reference is None:
            reference = (mp4, key)
        elif key != reference[1]:
            raise InputError(
                f"{chapter.path.name}: chapters from two different recordings (camera id, "
                f"firmware, codec or frame size differ from {reference[0].name}: "
                f"{_describe(key)} vs {_describe(reference[1])})"
            )
    # Creation times that run backwards between chapters of one camera and file number are
    # a camera clock step (GPS, app sync), not another recording: `_write_streams` keeps
    # the media clock and reports it.


def _describe(key: tuple[Any, ...]) -> str:
    came, firmware, codec, width, height = key
    ident = came.hex()[:8] if came else "?"
    return f"id {ident} fw {firmware} {codec} {width}x{height}"


# ------------------------------------------------------------------------------- import


CHAPTER_CLOCK_TOLERANCE_NS = 2_000_000_000
"""mvhd creation times have 1 s resolution: a chapter's creation time further than this from
both readings GoPro writes (its own start, or the recording's start) is a clock step."""


def _mp4_creation_ns(mp4: MP4File | None) -> int | None:
    if mp4 is None or mp4.creation_time is None:
        return None
    when = mp4.creation_time
    return int(when.timestamp()) * NS_PER_S + when.microsecond * 1000


def chapter_clock_step_ns(
    created_ns: int | None, chapter_start_ns: int, recording_start_ns: int
) -> int | None:
    """How far a chapter's creation time is from where the media clock puts it (ns), or
    None when it agrees: with its own start on the joined media clock, or with the
    recording's start (cameras that stamp every chapter with it), to 2 s."""
    if created_ns is None:
        return None
    for reading in (chapter_start_ns, recording_start_ns):
        if abs(created_ns - reading) <= CHAPTER_CLOCK_TOLERANCE_NS:
            return None
    return created_ns - chapter_start_ns


def _creation_ns(mp4s: Sequence[MP4File | None], chapters: Sequence[Chapter]) -> tuple[int, str]:
    first = mp4s[0]
    if first is not None and first.creation_time is not None:
        when = first.creation_time
        return int(when.timestamp()) * NS_PER_S + when.microsecond * 1000, "mvhd"
    stat = chapters[0].path.stat()
    return stat.st_mtime_ns, "file modification time"


@dataclass(frozen=True)
class _Reference:
    """What salvaging an unfinalised chapter borrows from a finalised file."""

    config: CodecConfig
    fps: Fraction
    size: tuple[int, int]
    frames_start_with_aud: bool


def _starts_with_aud(video: _ChapterVideo) -> bool:
    """True when the first sample's first NAL unit is an access unit delimiter."""
    if video.mp4 is None or video.track is None:
        return False
    sample = video.mp4.read_sample(video.track, 0)
    size = video.config.nal_length_size
    if len(sample) <= size:
        return False
    header = sample[size]
    kind = header & 0x1F if video.codec == "h264" else (header >> 1) & 0x3F
    return kind == (9 if video.codec == "h264" else 35)


def _reference_config(
    videos: Sequence[_ChapterVideo | None], options: ImportOptions
) -> _Reference | None:
    """What salvaging needs from a finalised sibling chapter, else from the given file."""
    for video in videos:
        if video is not None and video.track is not None:
            return _Reference(
                video.config,
                _frame_rate(video),
                (video.track.width, video.track.height),
                _starts_with_aud(video),
            )
    if options.parameter_sets_from is not None:
        mp4 = read_mp4(options.parameter_sets_from)
        donor = _video_of(parse_chapter(options.parameter_sets_from), mp4)
        fps = (
            Fraction(options.salvage_fps).limit_denominator(1001)
            if options.salvage_fps
            else _frame_rate(donor)
        )
        track = mp4.video_track()
        return _Reference(donor.config, fps, (track.width, track.height), _starts_with_aud(donor))
    return None


def _frame_rate(video: _ChapterVideo) -> Fraction:
    track = video.track
    if track is None or track.sample_count == 0:
        raise InputError(f"{video.chapter.path.name}: no frame rate")
    ticks = int(np.median(track.durations))
    return Fraction(track.timescale, ticks)


def import_recording(
    options: ImportOptions,
    videos: Sequence[Path],
    session_dir: Path,
    *,
    overwrite: bool = False,
    session_id: str | None = None,
) -> ImportResult:
    """Import the chapters `videos` of ONE recording into `session_dir`.

    Chapters are ordered by their GoPro names; InputError when they are from
    two recordings, a chapter is missing or a file cannot be read at all.
    OutputExistsError when `session_dir` exists and `overwrite` is false.
    Returns counts, timings and the warnings (also in session.yaml).
    """
    started = time.perf_counter()
    session_dir = Path(session_dir)
    if not videos:
        raise InputError("no video files given (expected one or more GoPro .MP4 chapters)")
    if session_dir.exists() and not overwrite:
        raise OutputExistsError(f"{session_dir}: already exists (refusing to overwrite)")
    for path in videos:
        if not Path(path).is_file():
            raise InputError(f"{path}: no such file")
    recordings = group_recordings([Path(p) for p in videos])
    chapters = [c for r in recordings for c in r.chapters]
    if len(recordings) > 1:
        names = ", ".join(f"{r.name} ({len(r.chapters)} chapter(s))" for r in recordings)
        raise InputError(
            f"{chapters[0].path.name}: chapters from two different recordings given ({names}); "
            "import one recording at a time, or give the folder to import each"
        )
    warnings: list[str] = []
    opened = [_open_chapter(c) for c in chapters]
    mp4s = [m if isinstance(m, MP4File) else None for m in opened]
    _check_same_recording(chapters, mp4s)
    chapter_videos: list[_ChapterVideo | None] = [
        _video_of(c, m) if m is not None else None for c, m in zip(chapters, mp4s, strict=True)
    ]
    donor_size: tuple[int, int] | None = None
    if any(v is None for v in chapter_videos):
        reference = _reference_config(chapter_videos, options)
        for i, (chapter, opened_mp4) in enumerate(zip(chapters, opened, strict=True)):
            if not isinstance(opened_mp4, MissingMoovError):
                continue
            if reference is None:
                raise InputError(
                    f"{opened_mp4} To salvage its video, import it with a finalised chapter "
                    "of the same recording, or give --parameter-sets FILE.MP4 (a finalised "
                    "file from the same camera and video mode)."
                )
            fps = reference.fps
            donor_size = reference.size
            if options.salvage_fps:
                fps = Fraction(options.salvage_fps).limit_denominator(1001)
            chapter_videos[i] = _salvaged_video(
                chapter,
                opened_mp4,
                config=reference.config,
                fps=fps,
                aud_first=reference.frames_start_with_aud,
                warnings=warnings,
            )
    ready = [v for v in chapter_videos if v is not None]
    codecs = {v.codec for v in ready}
    if len(codecs) > 1:
        raise InputError(f"{chapters[0].path.name}: chapters mix codecs {sorted(codecs)}")
    facts = _camera_facts(mp4s[0] if mp4s[0] is not None else next((m for m in mp4s if m), None))
    camera = cameras.lookup_camera(firmware=facts.firmware, gpmf_model=facts.gpmf_model)
    creation_ns, creation_source = _creation_ns(mp4s, chapters)
    first_mp4 = next((m for m in mp4s if m is not None), None)
    width = first_mp4.video_track().width if first_mp4 else 0
    height = first_mp4.video_track().height if first_mp4 else 0
    if not width and ready:
        width, height = donor_size or _size_from_sps(ready[0])
    if session_id is None:
        session_id = session_dir.name
    imus = []
    for video in ready:
        imu = _read_chapter_imu(video, camera, warnings)
        if imu is None and options.require_imu:
            raise InputError(warnings[-1])
        imus.append(imu)
    total_bytes = sum(v.video_bytes for v in ready)
    result = ImportResult(recording=session_id, session_dir=session_dir, status="imported")
    with atomic_path(session_dir, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        session = SessionFolder(tmp)
        writer = ArchiveWriter(
            session.recording,
            compression=options.compression,
            chunk_size=options.chunk_size_bytes,
            engine="wreckmap",  # bulk copy: our record writer (shared/archive/writer.py says why)
            metadata={
                "session_id": session_id,
                "source": "gopro",
                "camera_model": facts.model,
                "serial": facts.serial or "",
                "firmware": facts.firmware or "",
            },
        )
        try:
            chapter_rows, keyframe_stamps, imu_count = _write_streams(
                writer, ready, imus, creation_ns, options, total_bytes, warnings,
                chapter_created_ns={
                    c.path: _mp4_creation_ns(m) for c, m in zip(chapters, mp4s, strict=True)
                },
            )  # fmt: skip
            imu_rate = _imu_rate(imus)
            calib_rows = _write_calibration(
                tmp, options, camera, width=width, height=height, imu_rate_hz=imu_rate
            )
            yaml_text = _session_yaml(
                session_id=session_id,
                facts=facts,
                camera=camera,
                ready=ready,
                imus=imus,
                chapter_rows=chapter_rows,
                creation_ns=creation_ns,
                creation_source=creation_source,
                creation_time=first_mp4.creation_time if first_mp4 else None,
                width=width,
                height=height,
                options=options,
                calib_rows=calib_rows,
                recordings=[session.relative(session.recording)],
                imu_rate_hz=imu_rate,
                warnings=warnings,
            )
            topic = video_topic(options.camera_index)
            writer.add_metadata(
                KEYFRAME_METADATA, {topic: ",".join(str(s) for s in keyframe_stamps)}
            )
            writer.add_metadata(FRAME_SIZE_METADATA, {topic: f"{width}x{height}"})
            # Log time = session start, not the host clock: the bag's span is the recording's.
            writer.write(
                "/session",
                SessionInfo(stamp_ns=time.time_ns(), yaml_text=yaml_text),
                log_time_ns=creation_ns,
            )
            writer.close()
        except BaseException:
            writer.abort()
            raise
        write_rosbag2_metadata(tmp)
        write_text_atomic(session.session_yaml, yaml_text)
    result.frames = sum(int(row["frames"]) for row in chapter_rows)
    result.imu_samples = imu_count
    result.duration_s = float(sum((v.duration for v in ready), Fraction(0)))
    result.bytes_read = total_bytes
    result.seconds = time.perf_counter() - started
    result.warnings = warnings
    for line in warnings:
        log.warning("%s", line)
    return result


def _size_from_sps(video: _ChapterVideo) -> tuple[int, int]:
    """Frame size by decoding the first keyframe (only for salvaged chapters)."""
    import av

    codec = av.CodecContext.create("h264" if video.codec == "h264" else "hevc", "r")
    try:
        for packet in (video.salvaged_packets or [])[:1]:
            for frame in codec.decode(av.Packet(packet)):
                return int(frame.width), int(frame.height)
        for frame in codec.decode(None):
            return int(frame.width), int(frame.height)
    except av.FFmpegError as error:
        raise InputError(
            f"{video.chapter.path.name}: the salvaged first keyframe does not decode ({error})"
        ) from None
    raise InputError(f"{video.chapter.path.name}: cannot find the frame size of the salvaged video")


def _imu_rate(imus: Sequence[_ChapterImu | None]) -> float | None:
    rates = [max(i.gyro_rate_hz, i.accel_rate_hz) for i in imus if i is not None]
    return float(np.mean(rates)) if rates else None


def _write_streams(
    writer: ArchiveWriter,
    videos: Sequence[_ChapterVideo],
    imus: Sequence[_ChapterImu | None],
    creation_ns: int,
    options: ImportOptions,
    total_bytes: int,
    warnings: list[str],
    *,
    chapter_created_ns: dict[Path, int | None] | None = None,
) -> tuple[list[dict[str, Any]], list[int], int]:
    """Write every chapter's packets and IMU samples; returns chapter rows, keyframe log times,
    IMU sample count. A chapter whose creation time disagrees with the joined media clock
    (the camera's clock stepped) is reported in its row, the warnings and on /health; the
    stamps follow the media clock."""
    vtopic = video_topic(options.camera_index)
    itopic = imu_topic(options.imu_index)
    frame_id = f"cam{options.camera_index}"
    imu_frame = f"imu{options.imu_index}"
    offset = Fraction(0)
    last_imu_ns: int | None = None
    last_log_ns: int | None = None
    keyframe_stamps: list[int] = []
    rows: list[dict[str, Any]] = []
    imu_total = 0
    bar = progress_bar(total=total_bytes, desc="import", unit="B", unit_scale=True)
    try:
        for video, imu in zip(videos, imus, strict=True):
            chapter_start_ns = creation_ns + round(offset * NS_PER_S)
            created = (chapter_created_ns or {}).get(video.chapter.path)
            step_ns = None
            if offset > 0:
                step_ns = chapter_clock_step_ns(created, chapter_start_ns, creation_ns)
            if step_ns is not None:
                step_s = step_ns / NS_PER_S
                warnings.append(
                    f"{video.chapter.path.name}: created {step_s:+.1f} s away from where the "
                    "previous chapters' durations put it (the camera clock stepped?); its "
                    "stamps follow the media clock"
                )
                details = {
                    "chapter": video.chapter.path.name,
                    "step_s": round(step_s, 3),
                    "created_ns": created,
                    "media_clock_ns": chapter_start_ns,
                }
                writer.write(
                    HEALTH_TOPIC,
                    RecorderEvent(
                        stamp_ns=chapter_start_ns,
                        frame_id=f"cam{options.camera_index}",
                        kind="clock_step",
                        yaml_text=yaml.safe_dump(details),
                    ),
                    log_time_ns=chapter_start_ns,
                )
            pts = chapter_start_ns + video.pts_ns
            b_frames = not np.array_equal(video.pts_ns, video.dts_ns)
            log_times = chapter_start_ns + (video.dts_ns if b_frames else video.pts_ns)
            if b_frames:
                # Decode times start before the first presentation time by the reorder delay.
                log_times = log_times + int(video.pts_ns[0] - video.dts_ns[0])
            imu_times = imu_values = None
            imu_written = 0
            if imu is not None:
                imu_times = chapter_start_ns + imu.times_ns
                keep = np.ones(imu_times.shape[0], dtype=bool)
                if last_imu_ns is not None:
                    keep = imu_times > last_imu_ns
                imu_times = imu_times[keep]
                imu_values = (imu.gyro_rad_s[keep], imu.accel_m_s2[keep])
            imu_pos = 0
            codec = video.codec
            header = video.config.annexb_header()
            name = video.chapter.path.name
            skipped_corrupt = 0
            waiting_for_key = False
            packets = _packet_source(video)
            written = 0
            for index, (sample, size) in enumerate(packets):
                stamp = int(pts[index])
                log_time = int(log_times[index])
                if last_log_ns is not None and log_time <= last_log_ns:
                    log_time = last_log_ns + 1  # chapter joins never go back in log time
                if imu_times is not None and imu_values is not None:
                    while imu_pos < imu_times.shape[0] and imu_times[imu_pos] <= log_time:
                        _write_imu(writer, itopic, imu_frame, imu_times, imu_values, imu_pos)
                        imu_pos += 1
                keyframe = bool(video.keyframes[index])
                if video.track is not None:
                    if waiting_for_key and not keyframe:
                        skipped_corrupt += 1
                        bar.update(size)
                        continue
                    try:
                        data = to_annexb(
                            sample,
                            codec=codec,
                            nal_length_size=video.config.nal_length_size,
                            parameter_sets=header,
                            keyframe=keyframe,
                            where=f"{name}: frame {index}",
                        )
                    except InputError as error:
                        if not skipped_corrupt:
                            warnings.append(str(error))
                        skipped_corrupt += 1
                        waiting_for_key = True
                        bar.update(size)
                        continue
                    waiting_for_key = False
                else:
                    data = sample
                writer.write(
                    vtopic,
                    CompressedVideo(stamp_ns=stamp, frame_id=frame_id, format=codec, data=data),
                    log_time_ns=log_time,
                )
                written += 1
                last_log_ns = log_time
                if keyframe:
                    keyframe_stamps.append(log_time)
                bar.update(size)
            if skipped_corrupt:
                warnings.append(
                    f"{name}: {skipped_corrupt} corrupt video packet(s) skipped (and the "
                    "frames depending on them, up to the next keyframe)"
                )
            if imu_times is not None and imu_values is not None:
                while imu_pos < imu_times.shape[0]:
                    _write_imu(writer, itopic, imu_frame, imu_times, imu_values, imu_pos)
                    imu_pos += 1
                imu_written = int(imu_times.shape[0])
                if imu_written:
                    last_imu_ns = int(imu_times[-1])
            imu_total += imu_written
            rows.append(
                {
                    "file": name,
                    "chapter": video.chapter.index,
                    "start_ns": chapter_start_ns,
                    "duration_s": float(video.duration),
                    "duration_exact_s": f"{video.duration.numerator}/{video.duration.denominator}",
                    "frames": written,
                    "keyframes": int(video.keyframes.sum()),
                    "imu_samples": imu_written,
                    "imu_start_s": (
                        None
                        if imu is None or not imu.times_ns.size
                        else seconds_from_ns(int(imu.times_ns[0]))
                    ),
                    "video_bytes": video.video_bytes,
                    "finalised": video.track is not None,
                    "clock_step_s": None if step_ns is None else round(step_ns / NS_PER_S, 3),
                }
            )
            offset += video.duration
    finally:
        bar.close()
    return rows, keyframe_stamps, imu_total


def _packet_source(video: _ChapterVideo) -> Any:
    """(sample bytes, size) for each packet: read by offset from the MP4, or salvaged."""
    if video.track is None:
        for packet in video.salvaged_packets or []:
            yield packet, len(packet)
        return
    track = video.track
    offsets = track.sample_offsets.tolist()
    sizes = track.sample_sizes.tolist()
    # One buffered handle, reads in file order: the OS read-ahead sees a sequential stream.
    with video.chapter.path.open("rb", buffering=1024 * 1024) as file:
        position = -1
        for offset, size in zip(offsets, sizes, strict=True):
            if offset != position:
                file.seek(offset)
            data = file.read(size)
            if len(data) != size:
                raise InputError(
                    f"{video.chapter.path.name}: video sample at byte {offset} needs {size} "
                    f"bytes, the file ends after {len(data)} (truncated copy?)"
                )
            position = offset + size
            yield data, size


def _write_imu(
    writer: ArchiveWriter,
    topic: str,
    frame_id: str,
    times: np.ndarray,
    values: tuple[np.ndarray, np.ndarray],
    index: int,
) -> None:
    writer.write(
        topic,
        Imu(
            stamp_ns=int(times[index]),
            frame_id=frame_id,
            angular_velocity_rad_s=values[0][index],
            linear_acceleration_m_s2=values[1][index],
        ),
    )


def _write_calibration(
    folder: Path,
    options: ImportOptions,
    camera: cameras.GoProCamera,
    *,
    width: int,
    height: int,
    imu_rate_hz: float | None,
) -> dict[str, Any]:
    from shared.calibration.kalibr import (
        CameraCalibration,
        read_camchain,
        read_imu_yaml,
    )

    session = SessionFolder(folder)
    session.calib.mkdir()
    rows: dict[str, Any] = {"camchain": session.relative(session.camchain)}
    if options.camchain is not None:
        given = read_camchain(options.camchain)[0].camera  # validate before copying
        if (given.width, given.height) != (width, height):
            raise InputError(
                f"{options.camchain}: calibrated for {given.width}x{given.height} pixels, "
                f"but the video is {width}x{height} (expected a calibration of this video mode)"
            )
        shutil.copyfile(options.camchain, session.camchain)
        rows["camchain_source"] = f"given ({options.camchain.name})"
    else:
        guess = cameras.guess_camera(camera, width=width, height=height, medium=options.medium)
        session.write_camchain(
            [
                CameraCalibration(
                    camera=guess,
                    cam_from_imu=np.eye(4),
                    topic=video_topic(options.camera_index),
                    name=f"cam{options.camera_index}",
                )
            ],
        )
        rows["camchain_source"] = (
            f"guess: {camera.name} Wide FOV {camera.hfov_wide_deg} deg, equidistant, "
            f"medium {options.medium}; T_cam_imu identity (camera-aligned body frame)"
        )
    if options.imu_yaml is not None:
        read_imu_yaml(options.imu_yaml)
        shutil.copyfile(options.imu_yaml, session.imu_yaml)
        rows["imu"] = session.relative(session.imu_yaml)
        rows["imu_source"] = f"given ({options.imu_yaml.name})"
    elif imu_rate_hz is not None:
        session.write_imu_noise(
            cameras.gopro_imu_noise(imu_rate_hz, topic=imu_topic(options.imu_index))
        )
        rows["imu"] = session.relative(session.imu_yaml)
        rows["imu_source"] = "typical GoPro MEMS noise (field.gopro.cameras.GOPRO_IMU_NOISE)"
    return rows


def _iso(ns: int) -> str:
    return datetime.fromtimestamp(ns / NS_PER_S, tz=UTC).isoformat()


def _session_yaml(
    *,
    session_id: str,
    facts: _CameraFacts,
    camera: cameras.GoProCamera,
    ready: Sequence[_ChapterVideo],
    imus: Sequence[_ChapterImu | None],
    chapter_rows: list[dict[str, Any]],
    creation_ns: int,
    creation_source: str,
    creation_time: datetime | None,
    width: int,
    height: int,
    options: ImportOptions,
    calib_rows: dict[str, Any],
    recordings: list[str],
    imu_rate_hz: float | None,
    warnings: list[str],
) -> str:
    fps = _frame_rate(ready[0]) if ready[0].track is not None else None
    imu_info: dict[str, Any] | None = None
    first_imu = next((i for i in imus if i is not None), None)
    if first_imu is not None:
        imu_info = {
            "kind": "gopro_gpmf",
            "topic": imu_topic(options.imu_index),
            "frame_id": f"imu{options.imu_index}",
            "frame": "camera-aligned body frame B: x right, y down, z forward (= camera axes)",
            "rate_hz": imu_rate_hz,
            "gyro_rate_hz": first_imu.gyro_rate_hz,
            "accel_rate_hz": first_imu.accel_rate_hz,
            "file_axis_order": first_imu.axis_order,
            "axis_order_source": first_imu.axis_order_source,
            "timing": first_imu.timing_method,
            "clock_origin": first_imu.clock_origin,
            "resampling": (
                "none"
                if first_imu.gyro_rate_hz == first_imu.accel_rate_hz
                else "slower stream linearly interpolated to the faster one's times"
            ),
        }
    document = {
        "id": session_id,
        "source": "gopro import",
        "imported_utc": datetime.now(tz=UTC).isoformat(),
        "recording": recordings,
        "devices": {
            f"cam{options.camera_index}": {
                "kind": "gopro",
                "model": facts.model,
                "serial": facts.serial,
                "camera_id": facts.camera_id,
                "firmware": facts.firmware,
                "lens": facts.lens,
                "lens_mode": facts.lens_mode,
                "codec": ready[0].codec,
                "width": width,
                "height": height,
                "fps": float(fps) if fps else None,
                "topic": video_topic(options.camera_index),
                "frame_id": f"cam{options.camera_index}",
                "clock": "gopro",
            },
            **({f"imu{options.imu_index}": {**imu_info, "clock": "gopro"}} if imu_info else {}),
        },
        "clocks": {
            "gopro": {
                "description": (
                    "camera wall clock at the start of chapter 1 (MP4 creation time) plus "
                    "MP4 media time; chapters joined end to end on their exact durations"
                ),
                "creation_time": creation_time.replace(tzinfo=None).isoformat()
                if creation_time
                else _iso(creation_ns),
                "creation_time_ns": creation_ns,
                "creation_time_source": creation_source,
                "zone": "unknown (GoPro writes its clock as set on the camera, usually local)",
            }
        },
        "chapters": chapter_rows,
        "calibration": calib_rows,
        "warnings": list(warnings),
    }
    return yaml.safe_dump(document, sort_keys=False, allow_unicode=True)


# ------------------------------------------------------------------------------- many


def session_name(recording: Recording) -> str:
    """Folder name of a recording's session: `<creation YYYYmmdd-HHMMSS>_<name>`.

    The camera's creation time comes from chapter 1 (its file modification
    time when the chapter is unfinalised), so the same recording always maps
    to the same name and re-importing a card skips it.
    """
    first = recording.chapters[0]
    try:
        created = read_mp4(first.path).creation_time
    except MissingMoovError:
        created = None
    if created is None:
        created = datetime.fromtimestamp(first.path.stat().st_mtime, tz=UTC)
    return f"{created.strftime('%Y%m%d-%H%M%S')}_{recording.name}"


def import_videos(
    options: ImportOptions,
    inputs: Sequence[Path],
    out: Path,
    *,
    overwrite: bool = False,
    on_result: Callable[[ImportResult], None] | None = None,
) -> list[ImportResult]:
    """Import files or folders.

    Only files given: they must be the chapters of one recording, imported
    into the session folder `out`. Any folder given (an SD card's DCIM/):
    every .MP4 under it is grouped into recordings and each recording becomes
    `out/<session_name>`; recordings whose session folder already holds a
    session.yaml are skipped (status "skipped"), and a recording that fails
    is reported (status "failed", `error`) without stopping the others.
    `on_result` is called after each recording.
    """
    paths = [Path(p) for p in inputs]
    if not paths:
        raise InputError("nothing to import (expected GoPro .MP4 files or a DCIM folder)")
    for path in paths:
        if not path.exists():
            raise InputError(f"{path}: no such file or folder")
    if not any(p.is_dir() for p in paths):
        result = import_recording(options, paths, out, overwrite=overwrite)
        if on_result:
            on_result(result)
        return [result]
    files: list[Path] = []
    for path in paths:
        files.extend(find_videos(path) if path.is_dir() else [path])
    if not files:
        raise InputError(f"{', '.join(map(str, paths))}: no .MP4 files found")
    results = []
    for recording in group_recordings(files):
        try:
            name = session_name(recording)
        except WreckmapError as error:
            result = ImportResult(
                recording=recording.name,
                session_dir=out / recording.name,
                status="failed",
                error=str(error),
            )
            results.append(result)
            if on_result:
                on_result(result)
            continue
        target = out / name
        if SessionFolder(target).session_yaml.exists() and not overwrite:
            result = ImportResult(recording=name, session_dir=target, status="skipped")
        else:
            try:
                result = import_recording(
                    options,
                    [c.path for c in recording.chapters],
                    target,
                    overwrite=overwrite,
                    session_id=name,
                )
            except WreckmapError as error:
                result = ImportResult(
                    recording=name, session_dir=target, status="failed", error=str(error)
                )
        results.append(result)
        if on_result:
            on_result(result)
    return results
