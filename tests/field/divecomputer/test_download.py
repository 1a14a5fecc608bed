"""The downloader against the simulated unit: as a subprocess, in a thread, under faults."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from field.divecomputer.download import DownloadOptions, download_dives
from field.divecomputer.simulator import (
    FaultOptions,
    LineFaults,
    SimulatedShearwater,
    serving_pty,
    synthetic_dives,
)
from shared.errors import DeviceError
from shared.formats.diveprofile import read_dive_folder, read_dive_index, write_dive

REPO = Path(__file__).resolve().parents[3]
FAST = DownloadOptions(
    settle_s=0.02, read_timeout_s=0.3, backoff_s=0.01, backoff_max_s=0.05, session_retries=2
)


@contextlib.contextmanager
def simulator_process(*args: str) -> Iterator[str]:
    """`wreckmap-field dc simulate ARGS` as a real process; yields its pty path."""
    command = [sys.executable, "-m", "field.cli", "dc", "simulate", *args]
    process = subprocess.Popen(
        command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert process.stdout is not None
        path = process.stdout.readline().strip()
        assert path.startswith("/dev/"), process.stderr.read() if process.stderr else path
        yield path
    finally:
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=10)
    assert process.returncode == 0, stderr


@contextlib.contextmanager
def simulator_thread(
    device: SimulatedShearwater, faults: FaultOptions | LineFaults | None = None
) -> Iterator[str]:
    with serving_pty(device, faults) as port:
        yield port


def _answer(device: SimulatedShearwater, payload: bytes) -> bytes:
    """The device's answer to one request payload (one is expected)."""
    reply = device.handle(payload)
    assert reply is not None
    return reply


def assert_same_dives(truth: Path, downloaded: Path) -> None:
    """Byte-identical CSVs and raw logs, and the same index apart from the source."""
    truth_index = read_dive_index(truth)
    got_index = read_dive_index(downloaded)
    assert len(got_index) == len(truth_index)
    for want, got in zip(truth_index, got_index, strict=True):
        assert {k: v for k, v in got.items() if k != "source"} == {
            k: v for k, v in want.items() if k != "source"
        }
        for key in ("csv", "raw"):
            assert (downloaded / got[key]).read_bytes() == (truth / want[key]).read_bytes()


def test_subprocess_perdix_ai_two_pages_with_deleted(tmp_path: Path) -> None:
    truth, out = tmp_path / "truth", tmp_path / "dives"
    args = ["--model", "perdix-ai", "--dives", "50", "--duration-s", "60", "--deleted", "3"]
    with simulator_process(*args, "--truth-out", str(truth)) as port:
        options = DownloadOptions(expected_model="perdix-ai", settle_s=0.02, read_timeout_s=1.0)
        result = download_dives(port, out, options)
        # 53 records: the list needs a second manifest page; deleted records are skipped.
        assert result.listed == 50 and len(result.written) == 50
        again = download_dives(port, out, options)
        assert again.written == [] and again.listed == 0
    assert_same_dives(truth, out)
    dive = read_dive_folder(out)[0]
    assert dive.model == "Shearwater Perdix AI" and dive.serial == "1234ABCD"
    assert dive.stamps_s.size == 6 and dive.sample_interval_s == 10.0
    assert dive.stamps_s[0] - dive.start_s == 10.0  # first sample one interval in


def test_subprocess_petrel2_imperial_via_cli(tmp_path: Path) -> None:
    truth, out = tmp_path / "truth", tmp_path / "dives"
    (given,) = synthetic_dives(1, seed=99, duration_s=300, first_start_iso="2024-07-01T10:00:00")
    write_dive(tmp_path / "given", given)
    args = ["--model", "petrel2", "--units", "imperial", "--dives", "2", "--duration-s", "300"]
    args += ["--profile", str(tmp_path / "given")]
    with simulator_process(*args, "--seed", "5", "--truth-out", str(truth)) as port:
        command = [
            sys.executable, "-m", "field.cli", "dc", "download", "--port", port,
            "--model", "petrel2", "--out", str(out), "--settle-s", "0.02",
        ]  # fmt: skip
        done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "Shearwater Petrel 2 serial 1234ABCD" in done.stdout and "3 downloaded" in done.stdout
    assert_same_dives(truth, out)
    assert read_dive_index(out)[-1]["start"] == given.start_iso  # the --profile dive
    for dive in read_dive_folder(out):
        assert dive.model == "Shearwater Petrel 2"
        # Imperial logs: 0.1 ft depth steps, whole-°F temperatures.
        steps = dive.depth_m / (0.1 * 0.3048)
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
        fahrenheit = dive.temperature_c * 9 / 5 + 32
        np.testing.assert_allclose(fahrenheit, np.round(fahrenheit), atol=1e-6)
        assert 5.0 < dive.max_depth_m < 41.0 and dive.stamps_s.size == 30


def test_only_new_dives_are_downloaded(tmp_path: Path) -> None:
    out = tmp_path / "dives"
    older = synthetic_dives(3, seed=2, duration_s=120)
    with simulator_thread(SimulatedShearwater("perdix-ai", older)) as port:
        assert len(download_dives(port, out, FAST).written) == 3
    newer = synthetic_dives(5, seed=2, duration_s=120)  # the same 3, then 2 more
    device = SimulatedShearwater("perdix-ai", newer, deleted=[0, 2])
    with simulator_thread(device) as port:
        result = download_dives(port, out, FAST)
    assert result.listed == 2 and len(result.written) == 2
    truth = tmp_path / "truth"
    for profile, raw in device.held_dives():
        write_dive(truth, profile, raw=raw)
    assert_same_dives(truth, out)


def test_profile_put_into_the_unit_comes_back() -> None:
    (profile,) = synthetic_dives(1, seed=9, duration_s=600, sample_interval_s=2.0)
    device = SimulatedShearwater("petrel2", [profile], sample_interval_s=10.0)
    ((held, _),) = device.held_dives()
    assert held.start_iso == profile.start_iso and held.sample_interval_s == 10.0
    want = np.interp(held.stamps_s, profile.stamps_s, profile.depth_m)
    np.testing.assert_allclose(held.depth_m, want, atol=0.05 + 1e-9)  # 0.1 m steps
    assert held.stamps_s[-1] == profile.stamps_s[-1]


def fresh_truth(tmp_path: Path, device: SimulatedShearwater) -> Path:
    truth = tmp_path / "truth"
    for profile, raw in device.held_dives():
        write_dive(truth, profile, raw=raw)
    return truth


def test_one_percent_corruption_gives_identical_dives(tmp_path: Path) -> None:
    device = SimulatedShearwater("perdix-ai", synthetic_dives(3, seed=4, duration_s=180))
    faults = LineFaults(FaultOptions(corrupt_rate=0.01, seed=11))
    options = DownloadOptions(
        settle_s=0.02, read_timeout_s=0.2, backoff_s=0.0, backoff_max_s=0.0,
        block_retries=60, verify=True,
    )  # fmt: skip
    with simulator_thread(device, faults) as port:
        result = download_dives(port, tmp_path / "dives", options)
    assert len(result.written) == 3 and faults.corrupted > 20
    assert_same_dives(fresh_truth(tmp_path, device), tmp_path / "dives")


def test_dropped_bytes_and_a_stall_are_survived(tmp_path: Path) -> None:
    device = SimulatedShearwater("petrel2", synthetic_dives(3, seed=6, duration_s=180))
    faults = LineFaults(FaultOptions(drop_rate=0.01, stall_after_packets=9, stall_s=1.0, seed=3))
    options = DownloadOptions(
        settle_s=0.02, read_timeout_s=0.25, backoff_s=0.0, backoff_max_s=0.0, block_retries=60
    )
    with simulator_thread(device, faults) as port:
        result = download_dives(port, tmp_path / "dives", options)
    assert len(result.written) == 3 and faults.dropped > 20 and faults.stalled
    assert_same_dives(fresh_truth(tmp_path, device), tmp_path / "dives")


def test_disconnect_fails_cleanly_and_a_rerun_resumes(tmp_path: Path) -> None:
    out = tmp_path / "dives"
    dives = synthetic_dives(4, seed=8, duration_s=120)
    # Identity (4) + manifest (1 + 7 + 1) + first dive (1 + 1 + 1) + 3 into the second.
    with (
        simulator_thread(
            SimulatedShearwater("perdix-ai", dives), FaultOptions(disconnect_after_packets=17)
        ) as port,
        pytest.raises(DeviceError, match=r"download failed .* 1 complete dive\(s\) saved"),
    ):
        download_dives(port, out, FAST)
    partial = read_dive_index(out)
    assert len(partial) == 1  # the complete newest dive, nothing half-written
    assert not (out / "download-state.json").exists()
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [partial[0]["csv"], partial[0]["raw"], "dives.json"]
    )
    device = SimulatedShearwater("perdix-ai", dives)
    with simulator_thread(device) as port:
        result = download_dives(port, out, FAST)
    assert result.already_present == 1 and len(result.written) == 3
    assert_same_dives(fresh_truth(tmp_path, device), out)


def test_cli_reports_a_lost_unit_in_one_line(tmp_path: Path) -> None:
    args = ["--model", "petrel2", "--dives", "2", "--duration-s", "60", "--disconnect-after", "6"]
    with simulator_process(*args) as port:
        command = [
            sys.executable, "-m", "field.cli", "dc", "download", "--port", port,
            "--out", str(tmp_path / "dives"), "--timeout-s", "0.3", "--retries", "1",
            "--backoff-s", "0.01", "--settle-s", "0.02",
        ]  # fmt: skip
        done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith("wreckmap-field: error: ") and "re-run to resume" in lines[-1]
    assert "Traceback" not in done.stderr


def test_unknown_expected_model_and_unopenable_port(tmp_path: Path) -> None:
    from shared.errors import InputError

    with pytest.raises(InputError, match="--model 'nerd9'"):
        download_dives("x", tmp_path, DownloadOptions(expected_model="nerd9"))
    options = DownloadOptions(session_retries=1, backoff_s=0.0, settle_s=0.0)
    with pytest.raises(DeviceError, match="cannot open"):
        download_dives(str(tmp_path / "no-such-port"), tmp_path / "dives", options)


@pytest.mark.hardware
def test_real_unit(tmp_path: Path) -> None:
    """A real Shearwater on WRECKMAP_DC_PORT (run with `-m hardware`)."""
    import os

    port = os.environ.get("WRECKMAP_DC_PORT")
    if not port:
        pytest.fail("set WRECKMAP_DC_PORT to the unit's serial port or pyserial URL")
    result = download_dives(port, tmp_path / "dives", DownloadOptions())
    assert result.identity is not None and result.identity.serial > 0
    for dive in read_dive_folder(tmp_path / "dives"):
        assert dive.stamps_s.size > 0 and np.nanmax(dive.depth_m) > 0.5


def test_cli_model_choices_match_the_registry(capsys: pytest.CaptureFixture[str]) -> None:
    from field import cli
    from field.commands import dc
    from field.divecomputer.simulator import MODELS, SIMULATED_MODELS

    assert set(dc.MODEL_KEYS) == set(MODELS) and set(SIMULATED_MODELS) <= set(MODELS)
    for command in ("download", "simulate", "import"):
        with pytest.raises(SystemExit) as exit_info:
            cli.main(["dc", command, "--help"])
        assert exit_info.value.code == 0
        assert "example:" in capsys.readouterr().out


class QuirkyUnit(SimulatedShearwater):
    """A simulated unit with one answer changed (to reach the downloader's refusals)."""

    def __init__(self, *args: object, answers: dict[int, bytes], **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.answers = answers

    def handle(self, payload: bytes) -> bytes | None:
        if len(payload) == 3 and payload[0] == 0x22:
            identifier = int.from_bytes(payload[1:3], "big")
            if identifier in self.answers:
                return self.answers[identifier]
        return super().handle(payload)


def run_against(device: SimulatedShearwater, out: Path, options: DownloadOptions = FAST):
    with simulator_thread(device) as port:
        return download_dives(port, out, options)


def test_identity_refusals_and_names(tmp_path: Path) -> None:
    from field.divecomputer import protocol

    dives = synthetic_dives(1, seed=1, duration_s=60)
    nak = protocol.negative_response(protocol.RDBI, 0x31)
    refusing = QuirkyUnit("perdix-ai", dives, answers={protocol.ID_MODEL: nak})
    with pytest.raises(DeviceError, match=r"refused an identity read .*0x31"):
        run_against(refusing, tmp_path / "a")
    legacy_answer = protocol.rdbi_response(
        protocol.ID_LOG_UPLOAD, protocol.encode_log_upload(0xC0000000)
    )
    legacy = QuirkyUnit("perdix-ai", dives, answers={protocol.ID_LOG_UPLOAD: legacy_answer})
    with pytest.raises(DeviceError, match="log format legacy is not supported"):
        run_against(legacy, tmp_path / "b")
    two_bytes = protocol.rdbi_response(protocol.ID_MODEL, b"\x06\x00")
    with pytest.raises(DeviceError, match="model answer of 2 bytes"):
        run_against(
            QuirkyUnit("perdix-ai", dives, answers={protocol.ID_MODEL: two_bytes}), tmp_path
        )
    # Model 3 without a hardware type: Petrel and Petrel 2 cannot be told apart.
    old_petrel = QuirkyUnit(
        "petrel2", dives, answers={protocol.ID_HARDWARE: protocol.negative_response(0x22, 0x31)}
    )
    assert run_against(old_petrel, tmp_path / "c").identity.model_name == (
        "Shearwater Petrel / Shearwater Petrel 2"
    )
    odd = QuirkyUnit(
        "perdix-ai", dives, answers={protocol.ID_MODEL: protocol.rdbi_response(0x8060, b"\x63")}
    )
    assert run_against(odd, tmp_path / "d").identity.model_name == "Shearwater model 99"


def test_refused_dive_and_bad_fingerprints(tmp_path: Path) -> None:
    from field.divecomputer import protocol
    from shared.errors import InputError

    device = SimulatedShearwater("perdix-ai", synthetic_dives(2, seed=1, duration_s=60))
    device.manifest.insert(0, protocol.ManifestRecord(fingerprint=b"\x70\0\0\0", offset=0x999))
    with pytest.raises(DeviceError, match=r"dive 70000000: device refused service 0x35"):
        run_against(device, tmp_path / "a")
    options = DownloadOptions(settle_s=0.0, read_timeout_s=0.3, fingerprint="xyz")
    with pytest.raises(InputError, match="fingerprint 'xyz' is not 8 hex digits"):
        run_against(SimulatedShearwater("perdix-ai", []), tmp_path / "b", options)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "download-state.json").write_text("{")
    with pytest.raises(InputError, match=r"download-state\.json: not valid JSON"):
        run_against(SimulatedShearwater("perdix-ai", []), tmp_path / "c")
    (tmp_path / "c" / "download-state.json").write_text("[]")
    with pytest.raises(InputError, match="expected an object of units"):
        run_against(SimulatedShearwater("perdix-ai", []), tmp_path / "c")


def test_simulator_refusals() -> None:
    from field.divecomputer import protocol

    with pytest.raises(ValueError, match="unknown Shearwater model 'nerd9'"):
        SimulatedShearwater("nerd9", [])
    with pytest.raises(ValueError, match="units 'furlongs'"):
        SimulatedShearwater("petrel2", [], units="furlongs")
    with pytest.raises(ValueError, match="sample interval 100 s out of range"):
        SimulatedShearwater("petrel2", synthetic_dives(1), sample_interval_s=100)
    device = SimulatedShearwater("petrel2", synthetic_dives(1, duration_s=60))
    nak = protocol.NEGATIVE
    assert _answer(device, protocol.transfer_request(1))[:2] == bytes((nak, 0x36))
    assert _answer(device, protocol.exit_request())[:2] == bytes((nak, 0x37))
    assert _answer(device, protocol.rdbi_request(0x1234))[0] == nak
    assert _answer(device, protocol.wdbi_request(0x1234, b"\0"))[0] == nak
    assert _answer(device, b"\x99")[1:] == b"\x99\x11"
    assert device.handle(b"") is None
    assert _answer(device, b"\x35\x00")[2] == 0x13
    bad_size = protocol.upload_request(protocol.MANIFEST_ADDRESS, 0x100, compressed=False)
    assert _answer(device, bad_size)[0] == nak
    clock = protocol.wdbi_request(protocol.ID_LOCAL_CLOCK, (0x6B021CD7).to_bytes(4, "big"))
    assert device.handle(clock) == protocol.wdbi_response(protocol.ID_LOCAL_CLOCK)
    assert device.local_clock_s == 0x6B021CD7
    manifest = protocol.upload_request(protocol.MANIFEST_ADDRESS, 0x600, compressed=False)
    assert device.handle(manifest) == protocol.upload_response(0xFC)
    assert _answer(device, protocol.transfer_request(3))[2] == protocol.NRC_WRONG_BLOCK_COUNTER
    first = device.handle(protocol.transfer_request(1))
    assert device.handle(protocol.transfer_request(1)) == first  # a repeat: the same block
    for counter in range(2, 8):
        device.handle(protocol.transfer_request(counter))
    assert _answer(device, protocol.transfer_request(8))[2] == protocol.NRC_SEQUENCE_ERROR
    # Frames that are not requests get no answer.
    assert device.feed(protocol.encode_response(b"\x22\x80\x10")) == []
    assert device.feed(bytes.fromhex("FF 01 DB C0")) == []
