"""The CLI layer of record / recover / inspect / preview: argument and config errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from field.cli import main


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 1
    return capsys.readouterr().err


def test_record_argument_and_config_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = str(tmp_path / "s")
    assert "no source" in _error(capsys, ["record", "--out", out])
    assert "expected KIND.KEY=VALUE" in _error(
        capsys, ["record", "--source", "sim", "--out", out, "--source-option", "cameras=2"]
    )
    assert "unknown (expected one of" in _error(
        capsys, ["record", "--source", "gopro", "--out", out]
    )
    config = tmp_path / "logger.yaml"
    config.write_text("recorder: {}\ncamera: {}\n")
    assert "unknown section(s) camera" in _error(
        capsys, ["record", "--config", str(config), "--out", out]
    )
    config.write_text("- a list\n")
    assert "expected a mapping" in _error(capsys, ["record", "--config", str(config), "--out", out])
    assert "cannot read the logger config" in _error(
        capsys, ["record", "--config", str(tmp_path / "none.yaml"), "--out", out]
    )
    config.write_text("recorder:\n  flush_interval_s: 100\n")
    message = _error(capsys, ["record", "--config", str(config), "--source", "sim", "--out", out])
    assert "recorder: flush_interval_s must be in [0.05, 10]" in message
    assert "unknown key(s) color" in _error(
        capsys, ["record", "--source", "sim", "--out", out, "--source-option", "sim.color=1"]
    )
    assert not (tmp_path / "s").exists()


def test_preview_and_tools_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    message = _error(capsys, ["preview", "--connect", "tcp/127.0.0.1:7447", "--http", "8090"])
    assert "expected HOST:PORT" in message
    assert "no such file" in _error(capsys, ["inspect", str(tmp_path / "x.mcap")])
    assert "no .mcap.part file" in _error(capsys, ["recover", str(tmp_path)])
