"""Keyframe images beside an export: linked when on the same filesystem, else copied."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable
from pathlib import Path

from shared.errors import InputError
from shared.progress import progress


def link_or_copy_images(names: Iterable[str], src_dir: Path, dst_dir: Path) -> int:
    """Put `src_dir/name` at `dst_dir/name` for every name (a hard link to the file, or a
    copy across filesystems; never a symbolic link); returns the count. Raises InputError
    naming the first missing image."""
    names = list(names)
    missing = [n for n in names if not (src_dir / n).is_file()]
    if missing:
        raise InputError(
            f"{src_dir}: {len(missing)} of {len(names)} images the model names are missing "
            f"(first: {missing[0]})"
        )
    for name in progress(names, total=len(names), desc="images", unit="image"):
        target = dst_dir / name
        target.parent.mkdir(parents=True, exist_ok=True)
        # The SfM stage's images/ are symbolic links: link (or copy) what they point to,
        # so the export stands on its own.
        source = (src_dir / name).resolve()
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)
    return len(names)
