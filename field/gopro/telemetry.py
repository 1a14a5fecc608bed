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
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from field.gopro.gpmf import GPMFError, GPMFPayload, GPMFStream, decode_value, parse_payload
from field.gopro.mp4 import MP4File, read_mp4
from field.gopro.timing import PayloadSamples, stream_times
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
        return self.times_ns.astype(np.float64) * 1e-9

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
    """All numeric telemetry of one MP4, with what the file says about the camera."""

    path: Path
    camera: str | None
    firmware: str | None
    serial: str | None
    creation_time: datetime | None
    video_duration_s: float
    payloads: int
    streams: dict[str, TelemetryStream] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)

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


def iter_gpmf_payloads(mp4: MP4File) -> Iterator[tuple[int, float, float, GPMFPayload]]:
    """(index, start_s, duration_s, parsed payload) for each sample of the gpmd track.

    Times are media seconds from the gpmd track's sample table. Raises
    `InputError` when the file has no gpmd track or a payload is corrupt.
    """
    track = mp4.gpmf_track()
    starts = track.decode_times / float(track.timescale)
    durations = track.durations / float(track.timescale)
    for index, (offset, data) in enumerate(mp4.iter_samples(track)):
        payload = parse_payload(data, source=mp4.name, base_offset=offset)
        yield index, float(starts[index]), float(durations[index]), payload


def _stream_name(stream: GPMFStream, first_device: int | None) -> str:
    if stream.device_id is None or stream.device_id == first_device:
        return stream.key
    return f"{stream.key}@{stream.device_id}"


def read_telemetry(path: Path | str, *, keys: Collection[str] | None = None) -> GoProTelemetry:
    """Read every numeric GPMF stream of a GoPro MP4 (or only `keys`, e.g. {"ACCL"}).

    Reads only the moov index and the telemetry payloads (never the video).
    Non-numeric streams (strings, FourCCs, dates) and streams whose structure
    changes between payloads are left out and listed in `skipped` with why.
    """
    mp4 = read_mp4(path)
    collected: dict[str, list[tuple[int, float, float, GPMFStream]]] = {}
    first_device: int | None = None
    camera: str | None = None
    origin_us: int | None = None
    payload_count = 0
    for index, start_s, duration_s, payload in iter_gpmf_payloads(mp4):
        payload_count += 1
        for stream in payload.streams:
            if first_device is None:
                first_device = stream.device_id
                camera = stream.device_name
            if (
                origin_us is None
                and stream.key in FRAME_LOCKED_KEYS
                and stream.samples
                and stream.timestamp_us is not None
            ):
                # Its first sample is the first frame of this payload, at the payload's
                # media time (GoPro stores each second's frames' metadata in that payload).
                origin_us = stream.timestamp_us - round(start_s * 1e6)
            name = _stream_name(stream, first_device)
            if keys is not None and name not in keys and stream.key not in keys:
                continue
            collected.setdefault(name, []).append((index, start_s, duration_s, stream))
    streams: dict[str, TelemetryStream] = {}
    skipped: dict[str, str] = {}
    for name, parts in collected.items():
        try:
            streams[name] = _assemble(name, parts, origin_us or 0, mp4.name)
        except InputError as error:
            skipped[name] = str(error)
    if keys is not None:
        for key in keys:
            if key not in streams and key not in skipped:
                present = ", ".join(sorted(collected)) or "none"
                skipped[key] = f"{mp4.name}: no GPMF stream {key!r} (present: {present})"
    settings = global_settings(mp4)
    video_duration = 0.0
    for track in mp4.tracks:
        if track.handler == "vide":
            video_duration = track.duration_s
            break
    return GoProTelemetry(
        path=Path(path),
        camera=settings.get("MINF") or camera,
        firmware=mp4.text_atom("FIRM") or settings.get("FMWR"),
        serial=settings.get("CASN"),
        creation_time=mp4.creation_time,
        video_duration_s=video_duration,
        payloads=payload_count,
        streams=streams,
        skipped=skipped,
    )


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
        times_ns=np.round(timing.times_s * 1e9).astype(np.int64),
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
    return "\n".join(lines)


__all__ = [
    "GPMFError",
    "GoProTelemetry",
    "TelemetryStream",
    "format_summary",
    "global_settings",
    "iter_gpmf_payloads",
    "read_telemetry",
    "telemetry_csv_text",
    "write_telemetry_csv",
]
