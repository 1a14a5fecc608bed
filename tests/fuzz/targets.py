"""Every parser under fuzz: its seed inputs, its structure-aware mutator and how to call it.

A `Target` writes its template files into a scratch folder, replaces one of them
(`relpath`) with the hostile bytes and calls `parse` on that file. Seeds are the real
files of ../shared/data and files made by our own writers (ArchiveWriter, build_pnf,
the simulated Shearwater, EurocWriter, write_dive, format_camchain...).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import random
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from . import mutators as mut
from .harness import Outcome, judge

REPO = Path(__file__).resolve().parents[2]
SHARED_DATA = REPO.parent / "shared" / "data"
REGRESSIONS = Path(__file__).resolve().parent / "regressions"
T0_NS = 1_700_000_000_000_000_000


@dataclass
class Target:
    """One parser entry point under fuzz.

    `seeds()` gives (label, bytes) of valid inputs; `mutate(rng, seed)` a damaged copy;
    `parse(path)` runs the parser (and what callers do next) on the file at `path`.
    `template()` gives other files (relative path -> bytes) the parser reads beside it.
    `wire`: a byte-stream protocol (no file): errors must only be non-empty.
    """

    name: str
    relpath: str
    seeds: Callable[[], list[tuple[str, bytes]]]
    mutate: Callable[[random.Random, bytes], bytes]
    parse: Callable[[Path], object]
    needs_location: bool = True
    wire: bool = False
    template: Callable[[], dict[str, bytes]] = field(default=lambda: {})
    time_limit_s: float = 5.0


def materialize(target: Target, data: bytes, folder: Path) -> Path:
    """Write the target's files into `folder` (emptied first), the hostile one last."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for relpath, content in target.template().items():
        path = folder / relpath
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)
    path = folder / target.relpath
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def run_input(
    target: Target,
    data: bytes,
    folder: Path,
    *,
    peak_limit_bytes: int | None = None,
    time_limit_s: float | None = None,
) -> Outcome:
    """Materialize `data` and judge the parser on it."""
    path = materialize(target, data, folder)
    names: tuple[str, ...] = (
        ("",)
        if target.wire
        else tuple({path.name, folder.name, *(Path(p).name for p in target.template())})
    )
    outcome = judge(
        lambda: target.parse(path),
        names=names,
        needs_location=target.needs_location and not target.wire,
        time_limit_s=time_limit_s or target.time_limit_s,
        peak_limit_bytes=peak_limit_bytes,
    )
    if target.wire and outcome.kind == "error" and not outcome.message.strip():
        return Outcome("no-file-name", "empty error message", outcome.elapsed_s)
    return outcome


# ------------------------------------------------------------------------------------ GoPro


@functools.cache
def _gpmf_seeds() -> list[tuple[str, bytes]]:
    from field.gopro.mp4 import read_mp4

    seeds = []
    for name in ("karma.mp4", "max-heromode.mp4"):
        mp4 = read_mp4(SHARED_DATA / "gopro" / name)
        track = mp4.gpmf_track()
        for index in (0, track.sample_count - 1):
            seeds.append((f"{name} payload {index}", mp4.read_sample(track, index)))
        if mp4.user_data.get("GPMF"):
            seeds.append((f"{name} udta GPMF", mp4.user_data["GPMF"]))
    return seeds


def _parse_gpmf(path: Path) -> None:
    from field.gopro import gpmf

    payload = gpmf.parse_payload(path.read_bytes(), source=path.name)
    for stream in payload.streams:
        # As read_telemetry does: a stream that cannot be scaled is skipped, not fatal;
        # its error must still say where it is.
        try:
            stream.scaled()
            stream.orientation_matrix()
        except gpmf.GPMFError as error:
            if path.name not in str(error) or "at byte" not in str(error):
                raise RuntimeError(f"GPMF error without file or offset: {error}") from None


@functools.cache
def _mp4_seeds() -> list[tuple[str, bytes]]:
    return [
        (name, (SHARED_DATA / "gopro" / name).read_bytes())
        for name in ("karma.mp4", "max-heromode.mp4")
    ]


@functools.cache
def _mp4_boxes(seed: bytes) -> list[tuple[int, int, bytes]]:
    return mut.mp4_boxes(seed)


def _mutate_mp4(rng: random.Random, data: bytes) -> bytes:
    boxes = _mp4_boxes(data) if any(data is s for _, s in _mp4_seeds()) else mut.mp4_boxes(data)
    if not boxes:
        return mut.mutate_bytes(rng, data)
    return mut.mutate_mp4(rng, data, boxes)


def _parse_mp4(path: Path) -> None:
    from field.gopro.mp4 import avcc_to_annexb, parse_codec_config, read_mp4
    from field.gopro.telemetry import global_settings, read_telemetry

    mp4 = read_mp4(path)
    for track in mp4.tracks:
        track.pts_ns()
        track.sample_times_s()
    video = next((t for t in mp4.tracks if t.handler == "vide"), None)
    if video is not None and video.codec_config:
        where = f"{path.name}: track {video.track_id}"
        config = parse_codec_config(video.codec, video.codec_config, source=where)
        for index, packet in enumerate(mp4.iter_packets(video)):
            avcc_to_annexb(packet.data, nal_length_size=config.nal_length_size, source=path.name)
            if index >= 5:
                break
    global_settings(mp4)
    telemetry = read_telemetry(path)
    for stream in telemetry.streams.values():
        _ = stream.times_ns, stream.values


@functools.cache
def _unfinalised_seed() -> tuple[bytes, int, tuple[bytes, ...]]:
    """karma.mp4 cut after its mdat (no moov, as when the battery dies), the mdat offset
    and the SPS/PPS of the finalised file (what the importer passes to salvage)."""
    from field.gopro.mp4 import parse_codec_config, read_mp4

    source = SHARED_DATA / "gopro" / "karma.mp4"
    mp4 = read_mp4(source)
    video = mp4.video_track()
    offset, size = mp4.mdat_ranges[0]
    config = parse_codec_config(video.codec, video.codec_config)
    return source.read_bytes()[: offset + size], offset, config.parameter_sets


def _parse_unfinalised(path: Path) -> None:
    from field.gopro import gpmf
    from field.gopro.mp4 import MissingMoovError, read_mp4
    from field.gopro.salvage import salvage_mdat

    _, offset, parameter_sets = _unfinalised_seed()
    try:
        read_mp4(path)
        return  # a mutation that happens to read as a complete file
    except MissingMoovError as error:
        mdat_offset = offset if error.mdat_offset is None else error.mdat_offset
        mdat_size = path.stat().st_size if error.mdat_size is None else error.mdat_size
    salvaged = salvage_mdat(path, mdat_offset=mdat_offset, mdat_size=mdat_size, codec="h264",
                            parameter_sets=parameter_sets, frames_start_with_aud=True)  # fmt: skip
    for payload in salvaged.gpmf_payloads:
        try:
            gpmf.parse_payload(payload, source=path.name)
        except gpmf.GPMFError as error:  # the importer skips such a payload with a warning
            if path.name not in str(error):
                raise RuntimeError(f"GPMF error without the file name: {error}") from None


def _parse_import(path: Path) -> None:
    """The whole GoPro import (video packets, IMU, calibration guess, MCAP, session.yaml)."""
    from field.gopro.importer import ImportOptions, import_videos
    from shared.errors import InputError

    os.environ["WRECKMAP_PROGRESS"] = "0"
    for result in import_videos(ImportOptions(), [path], path.parent / "session"):
        if result.error is not None:
            raise InputError(result.error)


# ------------------------------------------------------------------------------ Dive computer


@functools.cache
def _pnf_seeds() -> list[tuple[str, bytes]]:
    from field.divecomputer import logformat
    from field.divecomputer.simulator import MODELS, profile_to_log, synthetic_dives

    dives = synthetic_dives(2, seed=3, duration_s=300.0)
    model = next(iter(MODELS.values()))
    seeds = [
        ("simulator metric", profile_to_log(dives[0], model=model, serial=0x1234ABCD)),
        ("simulator imperial", profile_to_log(dives[1], model=model, serial=7, imperial=True)),
    ]
    settings = logformat.PnfSettings(start_s=1_700_000_000, sample_interval_ms=2000)
    seeds.append(
        ("build_pnf", logformat.build_pnf(settings, [0.0, 5.0, 12.3, 3.0], [20, 18, 15, 19]))
    )
    return seeds


def _parse_pnf(path: Path) -> None:
    from field.divecomputer import logformat

    data = path.read_bytes()
    dive = logformat.parse_pnf(data, where=path.name)
    logformat.check_dive(dive, fingerprint=dive.fingerprint, serial=dive.serial, where=path.name)


@functools.cache
def _wire_seeds() -> list[tuple[str, bytes]]:
    """What a simulated Shearwater sends during a full download session."""
    from field.divecomputer import protocol as p
    from field.divecomputer.simulator import SimulatedShearwater, synthetic_dives

    unit = SimulatedShearwater("perdix-ai", synthetic_dives(1, seed=4, duration_s=240.0))
    wire = bytearray()

    def ask(payload: bytes) -> None:
        for frame in unit.feed(p.encode_request(payload)):
            wire.extend(frame)

    for identifier in (p.ID_SERIAL, p.ID_FIRMWARE, p.ID_MODEL, p.ID_LOG_UPLOAD):
        ask(p.rdbi_request(identifier))
    for address, size, compressed in (
        (p.MANIFEST_ADDRESS, p.MANIFEST_SIZE, False),
        (0x80000000 + 0x00010000, p.UNKNOWN_SIZE, True),
    ):
        ask(p.upload_request(address, size, compressed=compressed))
        for counter in range(1, 40):
            ask(p.transfer_request(counter))
        ask(p.exit_request())
    return [("simulated session", bytes(wire))]


def _parse_wire(path: Path) -> None:
    """Host side of a session: SLIP frames, packets, services, manifest, dive blocks."""
    from field.divecomputer import logformat
    from field.divecomputer import protocol as p

    decoder = p.SlipDecoder()
    blocks: list[list[bytes]] = [[]]
    for frame in decoder.feed(path.read_bytes()):
        if isinstance(frame, p.ProtocolError):
            continue
        try:
            payload = p.decode_response(frame)
        except p.ProtocolError:
            continue
        if not payload:
            continue
        kind = payload[0]
        if kind == 0x62 and len(payload) >= 3:
            identifier = int.from_bytes(payload[1:3], "big")
            data = p.parse_rdbi_response(payload, identifier)
            if identifier == p.ID_SERIAL:
                p.decode_serial(data)
            elif identifier == p.ID_FIRMWARE:
                p.decode_firmware(data)
            elif identifier == p.ID_LOG_UPLOAD:
                p.decode_log_upload(data)
        elif kind == 0x75:
            p.parse_upload_response(payload)
            blocks.append([])
        elif kind == 0x76 and len(payload) >= 2:
            blocks[-1].append(p.parse_transfer_response(payload, payload[1]))
        elif kind == p.NEGATIVE:
            # A refusal is an answer (the downloader retries or stops), not a parse error.
            with contextlib.suppress(p.NegativeResponseError):
                p.check_negative(payload, payload[1] if len(payload) > 1 else 0)
        elif kind == 0x77:
            p.parse_exit_response(payload)
    for group in blocks:
        if not group:
            continue
        joined = b"".join(group)
        if len(joined) == p.MANIFEST_SIZE:
            p.decode_manifest_page(joined)
            continue
        try:
            plain = p.decompress_blocks(group)
        except p.ProtocolError:
            continue
        logformat.parse_pnf(plain, where="downloaded dive")


def _divelog(name: str) -> Callable[[], list[tuple[str, bytes]]]:
    return lambda: [(name, (SHARED_DATA / "divelogs" / name).read_bytes())]


def _parse_logbook(path: Path) -> None:
    from field.divecomputer.importers import import_logbook, read_logbook

    for profile in read_logbook(path):
        _ = profile.duration_s, profile.max_depth_m
    import_logbook(path, path.parent / "dives")


# ------------------------------------------------------------------------------------- MCAP


@functools.cache
def _mcap_seeds() -> list[tuple[str, bytes]]:
    import tempfile

    from shared.archive import ArchiveWriter, DepthSample, Imu, SessionInfo, depth_topic, imu_topic

    rng = np.random.default_rng(5)
    seeds = []
    cases: tuple[tuple[Literal["zstd", "none"], int], ...] = (("zstd", 3000), ("none", 2000))
    for compression, chunk_size in cases:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "seed.mcap"
            with ArchiveWriter(
                path, chunk_size=chunk_size, compression=compression, metadata={"site": "wreck"}
            ) as writer:
                writer.write("/session", SessionInfo(stamp_ns=T0_NS, yaml_text="a: 1"))
                for i in range(60):
                    writer.write(
                        imu_topic(0),
                        Imu(
                            stamp_ns=T0_NS + i * 5_000_000,
                            frame_id="imu0",
                            angular_velocity_rad_s=rng.normal(size=3),
                            linear_acceleration_m_s2=rng.normal(size=3),
                        ),
                    )
                    if i % 10 == 0:
                        writer.write(
                            depth_topic(0),
                            DepthSample(
                                stamp_ns=T0_NS + i * 5_000_000, frame_id="d", depth_m=float(i)
                            ),
                        )
            seeds.append((f"ArchiveWriter {compression}", path.read_bytes()))
    return seeds


def _read_archive(path: Path, *, salvage: bool) -> None:
    from shared.archive import ArchiveReader

    with ArchiveReader(path, salvage=salvage) as reader:
        for _ in reader.messages():
            pass
        topics = reader.topics()
        reader.metadata()
        if topics:
            reader.time_span_ns()
        for name, info in topics.items():
            if info.schema_name == "sensor_msgs/msg/Imu":
                reader.read_imu(name)


# ---------------------------------------------------------------------- calibration, formats


@functools.cache
def _calibration_files() -> dict[str, bytes]:
    from shared.calibration.aprilgrid import AprilGridTarget
    from shared.calibration.cameras import PinholeEquidistant, PinholeRadtan
    from shared.calibration.kalibr import (
        CameraCalibration,
        ImuNoise,
        format_camchain,
        format_imu_yaml,
        format_target_yaml,
    )
    from shared.geometry import make_pose, so3_exp

    rng = np.random.default_rng(7)
    models: list[type[PinholeRadtan] | type[PinholeEquidistant]] = [
        PinholeRadtan,
        PinholeEquidistant,
    ]
    cams = [
        CameraCalibration(
            camera=model(640, 480, 500.5, 501.25, 319.7, 239.9, -0.1, 0.02, 0.001, -0.002),
            cam_from_imu=make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 0.1),
            timeshift_cam_imu_s=1.5e-3,
            name=f"cam{i}",
        )
        for i, model in enumerate(models)
    ]
    noise = ImuNoise(2.0e-3, 3.0e-3, 1.6968e-4, 1.9393e-5, 200.0, "/imu0")
    target = AprilGridTarget(tag_rows=6, tag_cols=6, tag_size_m=0.088, tag_spacing_ratio=0.3)
    return {
        "camchain.yaml": format_camchain(cams).encode(),
        "imu.yaml": format_imu_yaml(noise).encode(),
        "target.yaml": format_target_yaml(target).encode(),
    }


def _kalibr_seed(name: str) -> Callable[[], list[tuple[str, bytes]]]:
    return lambda: [(name, _calibration_files()[name])]


def _parse_camchain(path: Path) -> None:
    from shared.calibration.kalibr import format_camchain, read_camchain

    format_camchain(read_camchain(path))


def _parse_imu_yaml(path: Path) -> None:
    from shared.calibration.kalibr import read_imu_yaml

    read_imu_yaml(path)


def _parse_target_yaml(path: Path) -> None:
    from shared.calibration.kalibr import read_target_yaml

    read_target_yaml(path)


@functools.cache
def _tum_seeds() -> list[tuple[str, bytes]]:
    from shared.formats.tum import format_tum
    from shared.geometry import make_pose, so3_exp
    from shared.trajectory import Trajectory

    rng = np.random.default_rng(8)
    stamps = T0_NS + np.arange(12, dtype=np.int64) * 33_333_333
    poses = make_pose(so3_exp(rng.normal(size=(12, 3))), rng.normal(size=(12, 3)))
    return [("format_tum", format_tum(Trajectory(stamps_ns=stamps, poses=poses)).encode())]


def _parse_tum(path: Path) -> None:
    from shared.formats.tum import format_tum, read_tum

    format_tum(read_tum(path))


@functools.cache
def _svin_seeds() -> list[tuple[str, bytes]]:
    """SVIn2's pose-graph text (unpadded nanoseconds) and an OKVIS CSV, as those tools write."""
    rng = np.random.default_rng(10)
    stamps = T0_NS + np.cumsum(rng.integers(10**7, 4 * 10**8, size=12))
    svin = ["#timestamp tx ty tz qx qy qz qw"]
    okvis = ["timestamp, p_WS_W_x, p_WS_W_y, p_WS_W_z, q_WS_x, q_WS_y, q_WS_z, q_WS_w"]
    for stamp in stamps.tolist():
        sec, nsec = divmod(stamp, 10**9)
        q = rng.normal(size=4)
        numbers = [*rng.normal(size=3), *(q / np.linalg.norm(q))]
        svin.append(f"{sec}.{nsec} " + " ".join(f"{v:.9f}" for v in numbers))
        okvis.append(f"{stamp}, " + ", ".join(f"{v:.18e}" for v in numbers))
    return [
        ("svin2 pose graph", ("\n".join(svin) + "\n").encode()),
        ("okvis csv", ("\n".join(okvis) + "\n").encode()),
    ]


def _parse_trajectory_text(path: Path) -> None:
    from shared.formats.svin import read_trajectory
    from shared.formats.tum import format_tum

    format_tum(read_trajectory(path).trajectory)


@functools.cache
def _euroc_files() -> dict[str, bytes]:
    import tempfile

    from shared.calibration.cameras import PinholeRadtan
    from shared.calibration.kalibr import CameraCalibration, ImuNoise
    from shared.formats.euroc import EurocWriter
    from shared.geometry import make_pose, so3_exp
    from shared.trajectory import Trajectory

    rng = np.random.default_rng(9)
    camera = CameraCalibration(
        camera=PinholeRadtan(64, 48, 50.5, 50.25, 31.7, 23.9, -0.1, 0.02, 0.001, -0.002),
        cam_from_imu=make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 0.1),
    )
    noise = ImuNoise(2.0e-3, 3.0e-3, 1.6968e-4, 1.9393e-5, 200.0, "/imu0")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "euroc"
        with EurocWriter(folder, camera=camera, imu_noise=noise) as writer:
            for k in range(2):
                writer.add_image(T0_NS + k * 50_000_000, np.full((48, 64), 9 * k, np.uint8))
            stamps = T0_NS + np.arange(20, dtype=np.int64) * 5_000_000
            writer.add_imu(stamps, rng.normal(size=(20, 3)), rng.normal(size=(20, 3)))
            poses = make_pose(so3_exp(rng.normal(size=(5, 3))), rng.normal(size=(5, 3)))
            writer.set_groundtruth(Trajectory(stamps_ns=stamps[:5], poses=poses))
        return {
            str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()
        }


def _euroc_target(relpath: str, mutate: Callable[[random.Random, bytes], bytes]) -> Target:
    def template() -> dict[str, bytes]:
        return {k: v for k, v in _euroc_files().items() if k != relpath}

    def parse(path: Path) -> None:
        from shared.formats.euroc import read_euroc

        root = path
        while root.name != "mav0":
            root = root.parent
        read_euroc(root.parent)

    return Target(
        name=f"euroc {relpath.removeprefix('mav0/')}",
        relpath=relpath,
        seeds=lambda: [(relpath, _euroc_files()[relpath])],
        mutate=mutate,
        parse=parse,
        template=template,
    )


@functools.cache
def _dive_folder() -> dict[str, bytes]:
    import tempfile

    from field.divecomputer.simulator import synthetic_dives
    from shared.formats.diveprofile import write_dive

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "dives"
        for profile in synthetic_dives(2, seed=6, duration_s=200.0):
            write_dive(folder, profile)
        return {p.name: p.read_bytes() for p in folder.iterdir()}


def _dive_csv_name() -> str:
    return sorted(n for n in _dive_folder() if n.endswith(".csv"))[0]


def _parse_dive_folder(path: Path) -> None:
    from shared.formats.diveprofile import (
        read_dive_csv,
        read_dive_folder,
        read_profile,
        write_dive,
    )

    profiles = read_dive_folder(path.parent)
    for csv_path in sorted(path.parent.glob("*.csv")):
        read_dive_csv(csv_path)
    # The same CSV alone (no dives.json): its start then comes from its first stamp.
    if path.suffix == ".csv":
        alone = path.parent / "alone" / path.name
        alone.parent.mkdir()
        alone.write_bytes(path.read_bytes())
        read_profile(alone)
    for profile in profiles:
        _ = profile.duration_s, profile.max_depth_m
        write_dive(path.parent / "copy", profile)


def _dive_csv_target() -> Target:
    name = "dive.csv"

    def template() -> dict[str, bytes]:
        files = dict(_dive_folder())
        original = _dive_csv_name()
        files.pop(original)
        files["dives.json"] = files["dives.json"].replace(original.encode(), name.encode())
        return files

    return Target(
        name="dive csv",
        relpath=name,
        seeds=lambda: [("write_dive csv", _dive_folder()[_dive_csv_name()])],
        mutate=mut.mutate_table,
        parse=_parse_dive_folder,
        template=template,
    )


def _dives_json_target() -> Target:
    return Target(
        name="dives.json",
        relpath="dives.json",
        seeds=lambda: [("write_dive index", _dive_folder()["dives.json"])],
        mutate=mut.mutate_json,
        parse=_parse_dive_folder,
        template=lambda: {k: v for k, v in _dive_folder().items() if k != "dives.json"},
    )


def _gpmf_target() -> Target:
    return Target("gpmf", "payload.gpmf", _gpmf_seeds, mut.mutate_gpmf, _parse_gpmf)


TARGETS: dict[str, Target] = {
    t.name: t
    for t in (
        _gpmf_target(),
        Target("mp4", "chapter.mp4", _mp4_seeds, _mutate_mp4, _parse_mp4, time_limit_s=10.0),
        Target(
            "gopro salvage",
            "unfinalised.mp4",
            lambda: [("karma.mp4 without moov", _unfinalised_seed()[0])],
            mut.mutate_overwrite,
            _parse_unfinalised,
            time_limit_s=10.0,
        ),
        Target(
            "gopro import",
            "GOPR0001.MP4",
            _mp4_seeds,
            _mutate_mp4,
            _parse_import,
            time_limit_s=20.0,
        ),
        Target("shearwater pnf", "dive.pnf", _pnf_seeds, mut.mutate_pnf, _parse_pnf),
        Target(
            "shearwater protocol",
            "wire.bin",
            _wire_seeds,
            lambda rng, d: mut.mutate_bytes(rng, d, rounds=rng.randrange(1, 6)),
            _parse_wire,
            wire=True,
        ),
        Target("uddf", "log.uddf", _divelog("test42.uddf"), mut.mutate_xml, _parse_logbook),
        Target(
            "uddf (shearwater)",
            "log.uddf",
            _divelog("shearwater-perdix2-dive68.uddf"),
            mut.mutate_xml,
            _parse_logbook,
        ),
        Target(
            "subsurface xml",
            "log.xml",
            _divelog("test-42-uddf-import-reference.xml"),
            mut.mutate_xml,
            _parse_logbook,
        ),
        Target(
            "subsurface xml (ostc)", "log.xml", _divelog("ostc.xml"), mut.mutate_xml, _parse_logbook
        ),
        Target(
            "shearwater csv",
            "log.csv",
            _divelog("shearwater-petrel3-dive88.csv"),
            mut.mutate_table,
            _parse_logbook,
        ),
        Target(
            "mcap",
            "rec.mcap",
            _mcap_seeds,
            mut.mutate_mcap,
            functools.partial(_read_archive, salvage=False),
        ),
        Target(
            "mcap salvage",
            "rec.mcap",
            _mcap_seeds,
            mut.mutate_mcap,
            functools.partial(_read_archive, salvage=True),
        ),
        Target(
            "kalibr camchain",
            "camchain.yaml",
            _kalibr_seed("camchain.yaml"),
            mut.mutate_yaml,
            _parse_camchain,
        ),
        Target(
            "kalibr imu", "imu.yaml", _kalibr_seed("imu.yaml"), mut.mutate_yaml, _parse_imu_yaml
        ),
        Target(
            "kalibr target",
            "target.yaml",
            _kalibr_seed("target.yaml"),
            mut.mutate_yaml,
            _parse_target_yaml,
        ),
        Target(
            "tum",
            "traj.tum",
            _tum_seeds,
            functools.partial(mut.mutate_table, delimiter=" "),
            _parse_tum,
        ),
        Target(
            "trajectory text",
            "traj.txt",
            _svin_seeds,
            functools.partial(mut.mutate_table, delimiter=" "),
            _parse_trajectory_text,
        ),
        _euroc_target("mav0/imu0/data.csv", mut.mutate_table),
        _euroc_target("mav0/cam0/data.csv", mut.mutate_table),
        _euroc_target("mav0/state_groundtruth_estimate0/data.csv", mut.mutate_table),
        _euroc_target("mav0/imu0/sensor.yaml", mut.mutate_yaml),
        _euroc_target("mav0/cam0/sensor.yaml", mut.mutate_yaml),
        _dive_csv_target(),
        _dives_json_target(),
    )
}


def regression_dir(target: Target) -> Path:
    """tests/fuzz/regressions/<target name as a folder name>."""
    return REGRESSIONS / target.name.replace(" ", "-").replace("(", "").replace(")", "").replace(
        "/", "-"
    )


def mutated(target: Target, seed: int) -> tuple[str, bytes]:
    """The input number `seed` of a target: (label, bytes), reproducible."""
    rng = random.Random(seed)
    seeds = target.seeds()
    label, data = seeds[rng.randrange(len(seeds))]
    return f"{label} #{seed}", target.mutate(rng, data)


def apply_patch(document: dict[str, object]) -> bytes:
    """A regression stored as edits of a shared-data file: {"base": "gopro/karma.mp4",
    "truncate": n or null, "edits": [[offset, "hex"], ...]}."""
    data = bytearray((SHARED_DATA / str(document["base"])).read_bytes())
    truncate = document.get("truncate")
    if isinstance(truncate, int):
        del data[truncate:]
    edits = document.get("edits", [])
    assert isinstance(edits, list)
    for offset, hex_bytes in edits:
        raw = bytes.fromhex(hex_bytes)
        data[offset : offset + len(raw)] = raw
    return bytes(data)


def make_patch(base_name: str, base: bytes, data: bytes) -> dict[str, object] | None:
    """Edits turning `base` into `data` when it is an overwrite and/or a cut, else None."""
    if len(data) > len(base):
        return None
    a = np.frombuffer(base[: len(data)], np.uint8)
    b = np.frombuffer(data, np.uint8)
    diff = np.flatnonzero(a != b)
    if diff.size > 4096:
        return None
    edits: list[list[object]] = []
    for index in diff.tolist():
        if edits and int(str(edits[-1][0])) + len(bytes.fromhex(str(edits[-1][1]))) == index:
            edits[-1][1] = str(edits[-1][1]) + f"{data[index]:02x}"
        else:
            edits.append([index, f"{data[index]:02x}"])
    return {
        "base": base_name,
        "truncate": len(data) if len(data) < len(base) else None,
        "edits": edits,
    }


def load_regression(path: Path) -> bytes:
    if path.name.endswith(".patch.json"):
        return apply_patch(json.loads(path.read_text(encoding="utf-8")))
    return path.read_bytes()


def save_regression(target: Target, label: str, data: bytes, seed_label: str) -> Path:
    """Store a failing input under regressions/<target>/ (a patch for big shared-data seeds)."""
    folder = regression_dir(target)
    folder.mkdir(parents=True, exist_ok=True)
    stem = "".join(c if c.isalnum() else "-" for c in label).strip("-")[:60]
    if len(data) > 65536 and seed_label.split(" ")[0].endswith(".mp4"):
        base_name = seed_label.split(" ")[0]
        base = (SHARED_DATA / "gopro" / base_name).read_bytes()
        patch = make_patch(f"gopro/{base_name}", base, data)
        if patch is not None:
            path = folder / f"{stem}.patch.json"
            path.write_text(json.dumps(patch) + "\n", encoding="utf-8")
            return path
    path = folder / f"{stem}{Path(target.relpath).suffix}"
    path.write_bytes(data)
    return path


def struct_u32(value: int) -> bytes:
    return struct.pack(">I", value)
