"""The order tests/conftest.py gives the suite on several workers: the longest files first."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import pytest

from tests.conftest import expected_seconds, longest_files_first


@dataclass
class FakeItem:
    nodeid: str
    marks: dict[str, Any] = field(default_factory=dict)

    def get_closest_marker(self, name: str) -> Any:
        return self.marks.get(name)


def item(nodeid: str, slow: dict[str, float] | None = None) -> pytest.Item:
    marks = {} if slow is None else {"slow": pytest.mark.slow(**slow).mark}
    return cast(pytest.Item, FakeItem(nodeid, marks))


def test_expected_seconds_come_from_the_slow_mark() -> None:
    assert expected_seconds(item("a.py::t")) == 0.0
    assert expected_seconds(item("a.py::t", {})) == 20.0
    assert expected_seconds(item("a.py::t", {"seconds": 240})) == 240.0


def test_files_are_ordered_by_their_tests_seconds_and_keep_their_own_order() -> None:
    items = [
        item("tests/a.py::fast"),
        item("tests/b.py::one", {}),
        item("tests/a.py::other"),
        item("tests/c.py::x", {}),
        item("tests/c.py::y", {}),
        item("tests/d.py::demo", {"seconds": 240}),
        item("tests/e.py::fast"),
        item("tests/b.py::two"),
    ]
    order = [i.nodeid for i in longest_files_first(items)]
    assert order == [
        "tests/d.py::demo",
        "tests/c.py::x",
        "tests/c.py::y",
        "tests/b.py::one",
        "tests/b.py::two",
        "tests/a.py::fast",
        "tests/a.py::other",
        "tests/e.py::fast",
    ]
