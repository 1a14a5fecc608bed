"""Atomic writes: no clobbering, nothing half-written under the final name."""

from __future__ import annotations

import pytest

from shared.errors import OutputExistsError
from shared.fsutil import atomic_path, write_text_atomic


def test_refuses_to_overwrite(tmp_path) -> None:
    target = tmp_path / "a.txt"
    write_text_atomic(target, "one")
    with pytest.raises(OutputExistsError, match=r"a\.txt"):
        write_text_atomic(target, "two")
    assert target.read_text() == "one"
    write_text_atomic(target, "two", overwrite=True)
    assert target.read_text() == "two"


def test_failure_leaves_nothing(tmp_path) -> None:
    target = tmp_path / "out"
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.mkdir()
        (tmp / "part").write_text("half")
        raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []


def test_directory_replaced_whole(tmp_path) -> None:
    target = tmp_path / "dir"
    with atomic_path(target) as tmp:
        tmp.mkdir()
        (tmp / "a").write_text("1")
    with atomic_path(target, overwrite=True) as tmp:
        tmp.mkdir()
        (tmp / "b").write_text("2")
    assert sorted(p.name for p in target.iterdir()) == ["b"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]
