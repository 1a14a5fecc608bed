"""The environment `make test` builds: exactly one OpenCV, the pinned libraries importable."""

from __future__ import annotations

from importlib import metadata


def test_exactly_one_opencv() -> None:
    """Several packages pull the GUI OpenCV wheel; only the headless one may stay installed."""
    names = {dist.metadata["Name"].lower() for dist in metadata.distributions()}
    opencv = sorted(name for name in names if name.startswith("opencv"))
    assert opencv == ["opencv-python-headless"]


def test_pinned_majors() -> None:
    """The versions the issue asks for are the ones installed (numpy 2, pycolmap 4.2, gtsam 4.3)."""
    versions = {
        name: metadata.version(name)
        for name in ["numpy", "pycolmap", "gtsam", "depthai", "eclipse-zenoh", "mcap"]
    }
    assert versions["numpy"].startswith("2.")
    assert versions["pycolmap"].startswith("4.2")
    assert versions["gtsam"].startswith("4.3")
    assert versions["depthai"].startswith("3.")
    assert versions["eclipse-zenoh"].startswith("1.")
    assert versions["mcap"].startswith("1.6")
