"""deploy/: the example logger config, the zenoh TLS + access-control files, unit and udev."""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from field.record.preview_bus import PreviewOptions, zenoh_config
from field.record.recorder import RecorderOptions
from field.record.sources.base import build_options
from field.record.sources.oak import OakOptions
from field.record.sources.sim import SimOptions
from shared.errors import InputError

DEPLOY = Path(__file__).resolve().parents[3] / "deploy"


def test_logger_yaml_builds_every_option_and_comments_every_key() -> None:
    text = (DEPLOY / "logger.yaml").read_text()
    doc = yaml.safe_load(text)
    build_options(RecorderOptions, doc["recorder"], "recorder")
    build_options(OakOptions, doc["sources"]["oak"], "oak")
    build_options(SimOptions, doc["sources"]["sim"], "sim")
    preview = dict(doc["preview"])
    assert preview.pop("enabled") is False
    build_options(PreviewOptions, preview, "preview")
    for line in text.splitlines():
        if re.match(r"^\s*[a-z_]+:\s*\S", line):  # a key with a value
            assert "#" in line, f"key without a comment: {line.strip()}"
    # The defaults documented are the code's defaults.
    assert doc["recorder"]["flush_interval_s"] == RecorderOptions().flush_interval_s
    assert doc["sources"]["oak"]["imu_rate_hz"] == OakOptions().imu_rate_hz


def test_unit_and_udev_rules() -> None:
    unit = (DEPLOY / "wreckmap-logger.service").read_text()
    for line in ("Restart=on-failure", "KillSignal=SIGINT", "[Install]"):
        assert line in unit
    assert "wreckmap-field record" in unit
    rules = (DEPLOY / "udev" / "99-wreckmap.rules").read_text()
    for vendor in ("03e7", "0403", "10c4", "067b", "1a86"):
        assert f'ATTRS{{idVendor}}=="{vendor}"' in rules


def test_zenoh_configs_parse_and_bad_ones_are_named(tmp_path: Path) -> None:
    for name in ("recorder.json5", "preview-client.json5"):
        zenoh_config(listen=[], connect=[], config_file=str(DEPLOY / "zenoh" / name))
    with pytest.raises(InputError, match="not found"):
        zenoh_config(listen=[], connect=[], config_file=str(tmp_path / "none.json5"))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(InputError, match="not a valid zenoh config"):
        zenoh_config(listen=[], connect=[], config_file=str(bad))
    with pytest.raises(InputError, match="expected PROTOCOL/ADDRESS"):
        zenoh_config(listen=["127.0.0.1:7447"], connect=[])


def _certificates(folder: Path) -> None:
    """A CA, the recorder (127.0.0.1), a preview client and an intruder with another name."""

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=folder)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    run(
        "req",
        "-x509",
        *ec,
        "-days",
        "2",
        "-subj",
        "/CN=test-ca",
        "-keyout",
        "ca-key.pem",
        "-out",
        "ca.pem",
    )
    (folder / "server.ext").write_text("subjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    (folder / "client.ext").write_text("extendedKeyUsage=clientAuth\n")
    for name, cn, ext in (
        ("recorder", "wreckmap-recorder", "server.ext"),
        ("preview", "wreckmap-preview", "client.ext"),
        ("intruder", "someone-else", "client.ext"),
    ):
        run("req", *ec, "-subj", f"/CN={cn}", "-keyout", f"{name}-key.pem", "-out", f"{name}.csr")
        run(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca-key.pem",
            "-CAcreateserial",
            "-days",
            "2",
            "-extfile",
            ext,
            "-out",
            f"{name}.pem",
        )


def test_tls_and_access_control_on_loopback(tmp_path: Path, tools: Any) -> None:
    import zenoh

    if shutil.which("openssl") is None:
        pytest.fail("openssl is not installed (it is in deploy/system-packages.txt)")
    _certificates(tmp_path)
    recorder_cfg = tmp_path / "recorder.json5"
    recorder_cfg.write_text(
        (DEPLOY / "zenoh" / "recorder.json5")
        .read_text()
        .replace("/etc/wreckmap/tls", str(tmp_path))
    )
    client_text = (
        (DEPLOY / "zenoh" / "preview-client.json5")
        .read_text()
        .replace("/etc/wreckmap/tls", str(tmp_path))
    )
    (tmp_path / "preview.json5").write_text(client_text)
    (tmp_path / "intruder.json5").write_text(
        client_text.replace("preview.pem", "intruder.pem").replace(
            "preview-key.pem", "intruder-key.pem"
        )
    )
    endpoint = f"tls/127.0.0.1:{tools.free_port()}"
    recorder = zenoh.open(
        zenoh_config(listen=[endpoint], connect=[], config_file=str(recorder_cfg))
    )
    try:
        publisher = recorder.declare_publisher("wreckmap/rig0/s1/health")
        received: dict[str, int] = {"preview": 0, "intruder": 0}
        clients = []
        for name in received:
            client = zenoh.open(
                zenoh_config(
                    listen=[],
                    connect=[endpoint],
                    config_file=str(tmp_path / f"{name}.json5"),
                    mode="client",
                )
            )

            def count(_sample: Any, name: str = name) -> None:
                received[name] += 1

            client.declare_subscriber("wreckmap/**", count)
            clients.append(client)
        with pytest.raises(zenoh.ZError):  # no client certificate, unknown CA: refused
            zenoh.open(zenoh_config(listen=[], connect=[endpoint], mode="client"))
        time.sleep(0.5)
        for i in range(20):
            publisher.put(f"{i}".encode())
            time.sleep(0.02)
        time.sleep(0.5)
        assert received["preview"] >= 15
        assert received["intruder"] == 0  # connected (valid certificate) but not allowed
        for client in clients:
            client.close()
    finally:
        recorder.close()
