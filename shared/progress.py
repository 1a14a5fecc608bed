"""Progress bars for long work: a rate and an ETA on stderr.

A thin layer over tqdm so every stage shows progress the same way and tests
can silence it with WRECKMAP_PROGRESS=0.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

T = TypeVar("T")

MapFn = Callable[[Callable[[Any], Any], list[Any]], list[Any]]
"""A map over per-image work: `map_fn(fn, items) -> [fn(item) for item in items]`, in
order, wherever it runs (`serial_map` here, a process pool or Dask workers from
`postproc.pipeline.parallel`)."""


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


def serial_map(
    fn: Callable[[Any], Any], items: list[Any], *, desc: str | None = None, unit: str = "item"
) -> list[Any]:
    """`[fn(item) for item in items]` in this process, showing progress (`desc` defaults
    to the function's name)."""
    name = desc if desc is not None else getattr(fn, "__name__", "task")
    return [fn(item) for item in progress(items, total=len(items), desc=name, unit=unit)]


def progress_bar(*, total: float | None, desc: str = "", unit: str = "it", **kwargs: Any) -> Any:
    """A manual bar (`.update(n)`, `.close()`), for byte counts and nested loops."""
    from tqdm import tqdm

    return tqdm(
        total=total, desc=desc, unit=unit, disable=not _enabled(), mininterval=0.5, **kwargs
    )
