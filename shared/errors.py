"""The one exception hierarchy of wreckmap.

The CLIs print any `WreckmapError` as one line and exit non-zero; anything
else is a bug and gets a traceback. Messages say what was expected and where,
for example "karma.mp4: no GPMF track (expected a 'gpmd' metadata track,
found: video, audio)".
"""

from __future__ import annotations


class WreckmapError(Exception):
    """Root of every error wreckmap raises on purpose."""


class InputError(WreckmapError):
    """A file or stream does not hold what was expected (names the file and the place)."""


class DeviceError(WreckmapError):
    """A device (camera, dive computer, serial link) failed or is missing."""


class StageError(WreckmapError):
    """A processing stage cannot produce a result from valid inputs (no overlap, no motion...)."""


class OutputExistsError(WreckmapError):
    """Refusing to write over something already recorded or computed."""
