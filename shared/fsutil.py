"""Never lose what is already on disk: atomic writes and no clobbering.

Every output is written under a temporary name beside its final place and
renamed when complete, so a crash leaves either the old file, the new file,
or a stray temporary, never a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from shared.errors import OutputExistsError


def fsync_dir(path: Path) -> None:
    """Flush a directory entry (makes a rename durable on POSIX filesystems)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: Path | str, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it to `path` when the block succeeds.

    Works for a file or a directory written at the temporary path. Raises
    `OutputExistsError` if `path` exists and `overwrite` is false. On an
    exception the temporary is removed and `path` is untouched.
    """
    final = Path(path)
    if final.exists() and not overwrite:
        raise OutputExistsError(f"{final}: already exists (refusing to overwrite)")
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()
    try:
        yield tmp
        if tmp.is_file():
            with tmp.open("rb") as f:
                os.fsync(f.fileno())
        if final.is_dir() and not final.is_symlink():
            # A directory cannot be replaced atomically; move the old one aside first.
            old = final.with_name(f".{final.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            final.rename(old)
            tmp.rename(final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.replace(final)
        fsync_dir(final.parent)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: Path | str, data: bytes, *, overwrite: bool = False) -> Path:
    """Write `data` to `path` through a temporary file and a rename."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: Path | str, text: str, *, overwrite: bool = False) -> Path:
    """Write `text` (UTF-8) to `path` through a temporary file and a rename."""
    return write_bytes_atomic(path, text.encode("utf-8"), overwrite=overwrite)
