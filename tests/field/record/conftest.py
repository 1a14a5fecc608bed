"""Fixtures for the logger tests: one small simulated clip, rendered once per test run."""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path
from typing import Any

import pytest

from field.record.sources.sim import SMALL_RIG

REPO = Path(__file__).resolve().parents[3]

# A small rig: 320x200 frames rendered at 160x100, 15 fps, 400 Hz IMU, 4 Hz depth.
SMALL_SIM: dict[str, Any] = SMALL_RIG


@pytest.fixture(scope="session")
def sim_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache folder holding the rendered SMALL_SIM clip (rendered once: ~10 s)."""
    from field.record.sources.sim import SimOptions, prepare_clip

    folder = tmp_path_factory.mktemp("sim-cache")
    prepare_clip(SimOptions(**SMALL_SIM, cache_dir=str(folder)))
    return folder


@pytest.fixture
def sim_options(sim_cache: Path) -> dict[str, Any]:
    """Options of the small simulated rig, using the cached clip."""
    return {**SMALL_SIM, "cache_dir": str(sim_cache)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cli_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "field.cli", *args]


def sim_args(options: dict[str, Any]) -> list[str]:
    """`--source-option sim.KEY=VALUE` for each option."""
    out = []
    for key, value in options.items():
        out += ["--source-option", f"sim.{key}={value}"]
    return out


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["WRECKMAP_PROGRESS"] = "0"
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.fixture
def tools() -> Any:
    """Helpers for subprocess tests: free_port(), cli(*args), sim_args(options), env()."""
    from types import SimpleNamespace

    return SimpleNamespace(
        free_port=free_port, cli=cli_command, sim_args=sim_args, env=subprocess_env
    )
