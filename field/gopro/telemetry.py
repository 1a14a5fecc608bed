"""GoPro telemetry from an MP4: every GPMF stream as times + values, CSV export.

Time base of everything here: media time from the start of the video, as
int64 nanoseconds (`times_ns`) or float seconds (`times_s`); see
`field.gopro.timing` for how each sample's time is found.

    telemetry = read_telemetry("GX010001.MP4", keys={"ACCL", "GYRO"})
    accl = telemetry.streams["ACCL"]          # accl.times_ns, accl.values (m/s²)

Streams are named by their FourCC for the camera's own device (DVID 1, the
first device) and `"<FourCC>@<DVID>"` for other devices (a Karma drone).
Importers that also need the video use `field.gopro.mp4.read_mp4`: its video
`Track` gives each packet's file offset, size, pts and keyframe flag.
"""

from __future__ import annotations

import io
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from field.gopro.gpmf import GPMFError, GPMFPayload, GPMFStream, decode_value, parse_payload
from field.gopro.mp4 import MP4File, read_mp4
from field.gopro.timing import PayloadSamples, stream_times
from shared.clock import ns_from_seconds, seconds_from_ns
from shared.errors import InputError
from shared.fsutil import write_text_atomic

# Streams locked to video frames (one sample per frame, STMP = start of the frame): they
# tie the STMP clock to media time. See `field.gopro.timing` for the formulas.
FRAME_LOCKED_KEYS = ("CORI", "IORI", "GRAV")


@dataclass(frozen=True, kw_only=True)
class TelemetryStream:
    """One GPMF stream over the whole file.

    `times_ns`: int64 media time of each sample (ns from the start of the
    video); `values`: (samples, elements) float64, raw / SCAL, in the file's
    axis order and the stream's `units`; `raw`: the integers as stored;
    `orientation`: matrix from file order to the camera's axes (from MTRX or
    ORIN/ORIO, None when the file does not say); `timing_method`: "stmp" or
    "tsmp"; `rate_hz`: mean sampling rate; `temperature_c`: TMPC per payload
    (NaN where absent); `payload_index`: the gpmd sample each sample came from.
    """

    key: str
    name: str | None
    device_id: int | None
    device_name: str | None
    units: str | list[str] | None
    times_ns: np.ndarray
    values: np.ndarray
    raw: np.ndarray
    rate_hz: float
    timing_method: str
    orientation: np.ndarray | None
    orientation_in: str | None
    temperature_c: np.ndarray
    payload_index: np.ndarray
    scale: tuple[float, ...]

    @property
    def times_s(self) -> np.ndarray:
        return seconds_from_ns(self.times_ns)

    @property
    def samples(self) -> int:
        return int(self.times_ns.shape[0])

    @property
    def elements(self) -> int:
        return int(self.values.shape[1]) if self.values.ndim == 2 else 1

    def units_text(self) -> str:
        """Units as one readable string ("m/s²", or "deg,deg,m" for several)."""
        if self.units is None:
            return ""
        if isinstance(self.units, str):
            return self.units
        return ",".join(self.units)


@dataclass(frozen=True, kw_only=True)
class GoProTelemetry:
    """All numeric telemetry of one MP4, with what the file says about the camera.

    `payloads`: samples of the gpmd track; `corrupt_payloads`: how many of
    them did not parse and were skipped (their samples are missing, the
    others keep their times); `warnings`: one line per such finding.
    """

    path: Path
    camera: str | None
    firmware: str | None
    serial: str | None
    creation_time: datetime | None
    video_duration_s: float
    payloads: int
    streams: dict[str, TelemetryStream] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    corrupt_payloads: int = 0
    warnings: tuple[str, ...] = ()

    def stream(self, key: str) -> TelemetryStream:
        """The stream `key`; InputError listing what exists when it is absent."""
        if key not in self.streams and key in self.skipped:
            raise InputError(self.skipped[key])
        if key not in self.streams:
            present = ", ".join(sorted(self.streams)) or "none"
            raise InputError(
                f"{self.path.name}: no GPMF stream {key!r} (streams present: {present})"
            )
        return self.streams[key]


@dataclass(frozen=True, kw_only=True)
class GPMFSample:
    """One stored GPMF payload, not parsed yet.

    `index`: its sample number in the gpmd track; `start_s` / `duration_s`:
    its media time and declared duration (seconds; for a salvaged file
    without a sample table, what the salvager assumes); `data`: the bytes;
    `offset`: their position in the file (for error messages; 0 if unknown).
    """

    index: int
    start_s: float
    duration_s: float
    data: bytes
    offset: int = 0


@dataclass(frozen=True, kw_only=True)
class TelemetryStreams:
    """The streams of a run of GPMF payloads (see `assemble_telemetry`)."""

    streams: dict[str, TelemetryStream]
    skipped: dict[str, str]
    payloads: int
    corrupt_payloads: int
    warnings: tuple[str, ...]
    camera: str | None
    clock_origin: str


def iter_gpmf_samples(mp4: MP4File) -> Iterator[GPMFSample]:
    """Each sample of the gpmd track as stored (times from the track's sample table).

    Raises `InputError` when the file has no gpmd track.
    """
    track = mp4.gpmf_track()
    starts = track.decode_times / float(track.timescale)
    durations = track.durations / float(track.timescale)
    for index, (offset, data) in enumerate(mp4.iter_samples(track)):
        yield GPMFSample(
            index=index,
            start_s=float(starts[index]),
            duration_s=float(durations[index]),
            data=bytes(data),
            offset=int(offset),
        )


def iter_gpmf_payloads(mp4: MP4File) -> Iterator[tuple[int, float, float, GPMFPayload]]:
    """(index, start_s, duration_s, parsed payload) for each sample of the gpmd track.

    Times are media seconds from the gpmd track's sample table. Raises
    `InputError` when the file has no gpmd track or a payload is corrupt.
    """
    for sample in iter_gpmf_samples(mp4):
        payload = parse_payload(sample.data, source=mp4.name, base_offset=sample.offset)
        yield sample.index, sample.start_s, sample.duration_s, payload


def _stream_name(stream: GPMFStream, first_device: int | None) -> str:
    if stream.device_id is None or stream.device_id == first_device:
        return stream.key
    return f"{stream.key}@{stream.device_id}"


def assemble_telemetry(
    samples: Iterable[GPMFSample], *, source: str, keys: Collection[str] | None = None
) -> TelemetryStreams:
    """Parse GPMF payloads and give every sample of every numeric stream its media time.

    The one place where payloads become timed streams (`read_telemetry` and
    the importer both come here). A corrupt payload is skipped and counted;
    the others keep their times: STMP is tied to media time by the first
    frame-locked sample of the camera's device (CORI, IORI or GRAV) *minus
    the media start of the payload that holds it*, so losing the first
    payload does not shift the rest; without STMP the TSMP fit works on the
    surviving payloads' own start times. Streams of the first device are
    named by FourCC, others `"<FourCC>@<DVID>"`; `keys` limits the result
    (a FourCC matches every device's stream of that key).
    """
    collected: dict[str, list[tuple[int, float, float, GPMFStream]]] = {}
    first_device: int | None = None
    camera: str | None = None
    origin_us: int | None = None
    origin_text = "none (no frame-locked stream): STMP taken as media time"
    payload_count = 0
    corrupt = 0
    first_error = ""
    for sample in samples:
        payload_count += 1
        try:
            payload = parse_payload(sample.data, source=source, base_offset=sample.offset)
        except GPMFError as error:
            corrupt += 1
            first_error = first_error or str(error)
            continue
        for stream in payload.streams:
            if first_device is None:
                first_device = stream.device_id
                camera = stream.device_name
            if (
                origin_us is None
                and stream.key in FRAME_LOCKED_KEYS
                and stream.samples
                and stream.timestamp_us is not None
                and (stream.device_id is None or stream.device_id == first_device)
            ):
                # Its first sample is the first frame of this payload, at the payload's
                # media time (GoPro stores each second's frames' metadata in that payload).
                origin_us = stream.timestamp_us - round(sample.start_s * 1e6)
                origin_text = (
                    f"{stream.key} STMP of payload {sample.index} minus its media start "
                    f"{sample.start_s:.6f} s"
                )
            name = _stream_name(stream, first_device)
            if keys is not None and name not in keys and stream.key not in keys:
                continue
            collected.setdefault(name, []).append(
                (sample.index, sample.start_s, sample.duration_s, stream)
            )
    warnings: list[str] = []
    if corrupt:
        warnings.append(
            f"{source}: {corrupt} of {payload_count} GPMF payloads corrupt and skipped "
            f"(first: {first_error})"
        )
    streams: dict[str, TelemetryStream] = {}
    skipped: dict[str, str] = {}
    for name, parts in collected.items():
        try:
            streams[name] = _assemble(name, parts, origin_us or 0, source)
        except InputError as error:
            skipped[name] = str(error)
    if keys is not None:
        for key in keys:
            if key not in streams and key not in skipped:
                present = ", ".join(sorted(collected)) or "none"
                skipped[key] = f"{source}: no GPMF stream {key!r} (present: {present})"
    return TelemetryStreams(
        streams=streams,
        skipped=skipped,
        payloads=payload_count,
        corrupt_payloads=corrupt,
        warnings=tuple(warnings),
        camera=camera,
        clock_origin=origin_text,
    )


def read_telemetry(path: Path | str, *, keys: Collection[str] | None = None) -> GoProTelemetry:
    """Read every numeric GPMF stream of a GoPro MP4 (or only `keys`, e.g. {"ACCL"}).

    Reads only the moov index and the telemetry payloads (never the video).
    Non-numeric streams (strings, FourCCs, dates) and streams whose structure
    changes between payloads are left out and listed in `skipped` with why.
    A corrupt payload is skipped (counted in `corrupt_payloads`, said in
    `warnings`); InputError when every payload is corrupt.
    """
    mp4 = read_mp4(path)
    found = assemble_telemetry(iter_gpmf_samples(mp4), source=mp4.name, keys=keys)
    if found.payloads and found.corrupt_payloads == found.payloads:
        raise InputError(f"{found.warnings[0]}; no telemetry left")
    settings = global_settings(mp4)
    video_duration = 0.0
    for track in mp4.tracks:
        if track.handler == "vide":
            video_duration = track.duration_s
            break
    return GoProTelemetry(
        path=Path(path),
        camera=settings.get("MINF") or found.camera,
        firmware=mp4.text_atom("FIRM") or settings.get("FMWR"),
        serial=settings.get("CASN"),
        creation_time=mp4.creation_time,
        video_duration_s=video_duration,
        payloads=found.payloads,
        streams=found.streams,
        skipped=found.skipped,
        corrupt_payloads=found.corrupt_payloads,
        warnings=found.warnings,
    )


def local_positions(path: Path | str) -> tuple[np.ndarray, np.ndarray] | None:
    """A drone's own position log in a GoPro MP4: (media time ns (N,) int64, NED m (N, 3)).

    The Karma writes its GPS/IMU filter's local position as the GPMF stream LNED
    (time, x, y, z, vx, vy, vz; north-east-down, metres from the take-off point). It
    is the nearest thing to truth a GoPro clip carries. None when the file has no
    such stream (every camera that is not on a drone) or fewer than three samples.
    """
    telemetry = read_telemetry(path, keys={"LNED"})
    stream = next((v for k, v in telemetry.streams.items() if k.startswith("LNED")), None)
    if stream is None or stream.samples < 3:
        return None
    return stream.times_ns.astype(np.int64), np.asarray(stream.values[:, 1:4], dtype=np.float64)


def global_settings(mp4: MP4File) -> dict[str, str]:
    """Text entries of the udta GPMF block (HERO8+, MAX): MINF model, CASN serial, FMWR
    firmware...; empty for older cameras. A corrupt block raises GPMFError."""
    raw = mp4.user_data.get("GPMF")
    if not raw:
        return {}
    out: dict[str, str] = {}
    for device in parse_payload(raw, source=f"{mp4.name} (udta GPMF)").klvs:
        for klv in device.children:
            if klv.type in ("c", "u") and klv.key not in out:
                value = decode_value(klv)
                if isinstance(value, str):
                    out[klv.key] = value
    return out


def _assemble(
    name: str,
    parts: list[tuple[int, float, float, GPMFStream]],
    origin_us: int,
    source: str,
) -> TelemetryStream:
    """Concatenate one stream's payloads and give each sample its time."""
    where = f"{source}: {name}"
    elements = {s.elements for _, _, _, s in parts if s.samples}
    if len(elements) > 1:
        raise InputError(f"{where}: values per sample change between payloads {sorted(elements)}")
    raws: list[np.ndarray] = []
    values: list[np.ndarray] = []
    payload_index: list[np.ndarray] = []
    samples: list[PayloadSamples] = []
    temperatures: list[float] = []
    for index, start_s, duration_s, stream in parts:
        if not stream.samples:
            continue
        raws.append(stream.raw())
        values.append(stream.scaled())
        payload_index.append(np.full(stream.samples, index, dtype=np.int32))
        temperatures.append(np.nan if stream.temperature_c is None else stream.temperature_c)
        samples.append(
            PayloadSamples(
                start_s=start_s,
                duration_s=duration_s,
                samples=stream.samples,
                total_samples=stream.total_samples,
                timestamp_us=stream.timestamp_us,
            )
        )
    if not samples:
        raise InputError(f"{where}: no samples")
    timing = stream_times(samples, stmp_origin_us=origin_us, source=where)
    last = parts[-1][3]
    return TelemetryStream(
        key=last.key,
        name=last.name,
        device_id=last.device_id,
        device_name=last.device_name,
        units=last.units,
        times_ns=ns_from_seconds(timing.times_s),
        values=np.concatenate(values),
        raw=np.concatenate(raws),
        rate_hz=timing.rate_hz,
        timing_method=timing.method,
        orientation=last.orientation_matrix(),
        orientation_in=last.orientation_in,
        temperature_c=np.array(temperatures),
        payload_index=np.concatenate(payload_index),
        scale=last.scale,
    )


def telemetry_csv_text(stream: TelemetryStream) -> str:
    """CSV text: header `t_s,v0,v1,...`, one row a sample, t_s with 9 decimals."""
    columns = ",".join(f"v{i}" for i in range(stream.elements))
    out = io.StringIO()
    out.write(f"t_s,{columns}\n")
    table = np.column_stack([stream.times_s, stream.values])
    fmt = ["%.9f"] + ["%.10g"] * stream.elements
    np.savetxt(out, table, fmt=fmt, delimiter=",")
    return out.getvalue()


def write_telemetry_csv(
    stream: TelemetryStream, path: Path | str, *, overwrite: bool = False
) -> Path:
    """Write `telemetry_csv_text(stream)` atomically; refuses an existing file unless overwrite."""
    return write_text_atomic(path, telemetry_csv_text(stream), overwrite=overwrite)


def format_summary(telemetry: GoProTelemetry) -> str:
    """A few lines for people: camera, duration, then one line per stream."""
    lines = [
        f"{telemetry.path.name}: {telemetry.camera or 'unknown camera'}"
        f" (firmware {telemetry.firmware or '?'}), video {telemetry.video_duration_s:.3f} s,"
        f" {telemetry.payloads} GPMF payloads",
        f"{'stream':<12} {'samples':>8} {'rate_hz':>9} {'timing':>6}  units  name",
    ]
    for name in sorted(telemetry.streams):
        s = telemetry.streams[name]
        lines.append(
            f"{name:<12} {s.samples:>8} {s.rate_hz:>9.3f} {s.timing_method:>6}  "
            f"{s.units_text() or '-'}  {s.name or ''}"
        )
    for name in sorted(telemetry.skipped):
        lines.append(f"{name:<12} skipped: {telemetry.skipped[name]}")
    lines.extend(f"warning: {line}" for line in telemetry.warnings)
    return "\n".join(lines)


__all__ = [
    "GPMFError",
    "GPMFSample",
    "GoProTelemetry",
    "TelemetryStream",
    "TelemetryStreams",
    "assemble_telemetry",
    "format_summary",
    "global_settings",
    "iter_gpmf_payloads",
    "iter_gpmf_samples",
    "read_telemetry",
    "telemetry_csv_text",
    "write_telemetry_csv",
]
