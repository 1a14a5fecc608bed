"""The one interface every live source implements, and the registry of sources by name.

A source is opened, polled with `read(timeout_s)` from one thread (the recorder's pump
thread for that source) and closed. It raises `DeviceError` from `open` when the device is
missing (naming what was found) and from `read` when it is lost (unplugged); the recorder
then keeps the file open, logs it and calls `open` again until the device returns.

Every sample carries its archive message, whose `stamp_ns` is the sensor clock as ns since
the epoch (see `field.record.timing`), plus the host receive time (the MCAP log time) and,
when the device gives them, the raw device reading and the device's own host-synced stamp.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

from shared.archive import ArchiveMessage
from shared.errors import InputError

if TYPE_CHECKING:
    from shared.calibration.kalibr import CameraCalibration, ImuNoise


@dataclass(frozen=True)
class StreamInfo:
    """One stream a source produces.

    topic: archive topic (`/cam0/video`, `/imu0`, ...); kind: "video", "image", "imu" or
    "depth"; rate_hz: nominal sample rate; codec: "h264", "h265", "jpeg" for cameras;
    width_px, height_px: image size (0 for non-images); device: which device it comes from.
    """

    topic: str
    kind: str
    rate_hz: float
    codec: str = ""
    width_px: int = 0
    height_px: int = 0
    device: str = ""


@dataclass(frozen=True, slots=True)
class SourceSample:
    """One sample as received.

    message: the archive message; its `stamp_ns` is the sensor clock (ns since epoch).
    receive_ns: host wall-clock time at receipt (ns since epoch) -> MCAP log time.
    device_ns: the raw device-clock reading (ns since device boot), when there is one.
    host_sync_ns: the device library's own estimate of the capture time on the host clock
        (DepthAI `getTimestamp()`, ns since epoch), when there is one.
    keyframe: for video, whether the packet starts a group of pictures.
    """

    topic: str
    message: ArchiveMessage
    receive_ns: int
    device_ns: int | None = None
    host_sync_ns: int | None = None
    keyframe: bool = False

    @property
    def size_bytes(self) -> int:
        """Payload bytes (for the queue's memory budget); small constant for IMU/depth."""
        data = getattr(self.message, "data", None)
        return 128 + (len(data) if data is not None else 0)


@runtime_checkable
class CameraSource(Protocol):
    """A live source of camera / IMU / depth samples (see the module docstring)."""

    name: str
    """Registry name of the source kind ("oak", "sim")."""

    def open(self) -> None:
        """Connect and start streaming; DeviceError when the device is absent."""
        ...

    def streams(self) -> list[StreamInfo]:
        """The streams this source produces (valid before `open`)."""
        ...

    def read(self, timeout_s: float) -> list[SourceSample]:
        """Samples received since the last call, waiting up to `timeout_s` for the first.

        Returns [] on timeout; DeviceError when the device was lost.
        """
        ...

    def close(self) -> None:
        """Stop streaming and release the device (safe to call twice, or after a loss)."""
        ...

    def describe(self) -> dict[str, Any]:
        """Facts for session.yaml: device model, serial, settings, clock description."""
        ...

    def calibration(self) -> tuple[list[CameraCalibration], ImuNoise | None] | None:
        """Camera chain and IMU noise when known (written to calib/), else None."""
        ...


SourceFactory = Callable[..., CameraSource]
SOURCES: dict[str, type[Any]] = {}
"""Source kinds by name ("oak", "sim"); filled by `register_source`."""

T = TypeVar("T")


def register_source(name: str) -> Callable[[type[T]], type[T]]:
    """Class decorator adding a source class to `SOURCES` under `name`."""

    def add(cls: type[T]) -> type[T]:
        SOURCES[name] = cls
        return cls

    return add


def build_options(options_type: type[T], values: Mapping[str, Any] | None, where: str) -> T:
    """An options dataclass from a config mapping; InputError naming unknown or bad keys."""
    values = dict(values or {})
    known = {f.name for f in dataclasses.fields(options_type)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - known)
    if unknown:
        raise InputError(
            f"{where}: unknown key(s) {', '.join(unknown)} (expected: {', '.join(sorted(known))})"
        )
    try:
        return options_type(**values)
    except (TypeError, ValueError) as error:
        raise InputError(f"{where}: {error}") from None


def make_source(name: str, options: Mapping[str, Any] | None = None) -> CameraSource:
    """A source of kind `name` configured from `options` (a mapping of its option keys)."""
    import field.record.sources  # noqa: F401  (fills SOURCES)

    cls = SOURCES.get(name)
    if cls is None:
        raise InputError(
            f"source {name!r}: unknown (expected one of: {', '.join(sorted(SOURCES))})"
        )
    opts = build_options(cls.options_type, options, f"source {name!r}")
    source: CameraSource = cls(opts)
    return source
