"""Live sources behind one interface (`CameraSource`), by name in `SOURCES`.

Importing this package registers every source kind; device libraries (depthai, the
renderer) are imported only when a source is opened.
"""

from __future__ import annotations

from field.record.sources import oak, sim  # noqa: F401  (register the sources)
from field.record.sources.base import (
    SOURCES,
    CameraSource,
    SourceSample,
    StreamInfo,
    make_source,
    register_source,
)

__all__ = [
    "SOURCES",
    "CameraSource",
    "SourceSample",
    "StreamInfo",
    "make_source",
    "register_source",
]
