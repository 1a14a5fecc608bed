"""Progress bars for long work: a rate and an ETA on stderr.

A thin layer over tqdm so every stage shows progress the same way and tests
can silence it with WRECKMAP_PROGRESS=0.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

T = TypeVar("T")


def _enabled() -> bool:
    return os.environ.get("WRECKMAP_PROGRESS", "1") != "0"


def progress(
    iterable: Iterable[T],
    *,
    total: int | None = None,
    desc: str = "",
    unit: str = "it",
) -> Iterator[T]:
    """Iterate over `iterable` showing count, rate and ETA (when `total` is known)."""
    from tqdm import tqdm

    yield from tqdm(
        iterable, total=total, desc=desc, unit=unit, disable=not _enabled(), mininterval=0.5
    )


def progress_bar(*, total: float | None, desc: str = "", unit: str = "it", **kwargs: Any) -> Any:
    """A manual bar (`.update(n)`, `.close()`), for byte counts and nested loops."""
    from tqdm import tqdm

    return tqdm(
        total=total, desc=desc, unit=unit, disable=not _enabled(), mininterval=0.5, **kwargs
    )
