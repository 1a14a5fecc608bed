"""Telemetry of the real files: physics and file-structure checks, CSV and the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from field.gopro.telemetry import format_summary, read_telemetry, write_telemetry_csv
from field.gopro.timing import PayloadSamples, stream_times
from shared.errors import InputError, OutputExistsError

G = 9.80665


@pytest.fixture(scope="module")
def karma(shared_data: Path):
    return read_telemetry(shared_data / "gopro" / "karma.mp4")


@pytest.fixture(scope="module")
def gopro_max(shared_data: Path):
    return read_telemetry(shared_data / "gopro" / "max-heromode.mp4")


@pytest.mark.parametrize("name", ["karma", "gopro_max"])
def test_accl_magnitude_is_gravity_on_average(name: str, request) -> None:
    accl = request.getfixturevalue(name).stream("ACCL")
    assert accl.units == "m/s²"
    magnitude = np.linalg.norm(accl.values, axis=1)
    # Hand-held / drone: the mean of |a| is gravity within a few percent.
    assert magnitude.mean() == pytest.approx(G, rel=0.02)


@pytest.mark.parametrize("name", ["karma", "gopro_max"])
def test_times_are_increasing_and_inside_the_video(name: str, request) -> None:
    telemetry = request.getfixturevalue(name)
    for key in ("ACCL", "GYRO"):
        stream = telemetry.stream(key)
        times = stream.times_s
        assert np.all(np.diff(times) > 0)
        assert -0.02 < times[0] < 0.02
        # The last payload ends with the video; the MAX stores ~24 ms more (its CORI has a
        # 316th sample for 315 frames), never a payload's worth.
        assert abs(times[-1] - telemetry.video_duration_s) < 0.05


def test_karma_hero5_rates_and_timing_method(karma) -> None:
    """HERO5: ACCL nominally 200 Hz and GYRO 400 Hz, measured a little lower; no STMP."""
    accl, gyro = karma.stream("ACCL"), karma.stream("GYRO")
    assert accl.timing_method == gyro.timing_method == "tsmp"
    assert 190 < accl.rate_hz < 205 and 380 < gyro.rate_hz < 410
    # Same crystal: GYRO is exactly twice ACCL (within the fit's noise).
    assert gyro.rate_hz / accl.rate_hz == pytest.approx(2.0, rel=2e-3)
    # TSMP of the last payload = number of samples read (2397 ACCL, 4795 GYRO).
    assert (accl.samples, gyro.samples) == (2397, 4795)
    assert gyro.units == "rad/s"
    # A drone in flight turns slowly: |w| well inside the +-35 rad/s sensor range, small mean.
    assert np.abs(gyro.values).max() < 5 and np.linalg.norm(gyro.values, axis=1).mean() < 0.5


def test_max_stmp_timing_agrees_with_the_tsmp_fit(gopro_max, shared_data: Path) -> None:
    """Two independent clocks for the same samples: STMP (minus CORI's first STMP, which is
    video frame 0) and the MP4 payload times. They agree within a sample period or two."""
    from field.gopro.mp4 import read_mp4
    from field.gopro.telemetry import iter_gpmf_payloads

    accl = gopro_max.stream("ACCL")
    assert accl.timing_method == "stmp"
    assert 190 < accl.rate_hz < 205 and gopro_max.stream("GYRO").rate_hz == accl.rate_hz
    parts = []
    for _, start, duration, payload in iter_gpmf_payloads(read_mp4(accl_path(shared_data))):
        (stream,) = payload.find("ACCL")
        parts.append(
            PayloadSamples(
                start_s=start, duration_s=duration, samples=stream.samples,
                total_samples=stream.total_samples,
            )
        )  # fmt: skip
    fit = stream_times(parts)
    assert np.max(np.abs(fit.times_s - accl.times_s)) < 0.012
    # CORI is locked to video frames: 29.97 Hz and its first sample at 0.
    assert (gopro_max.camera, gopro_max.serial) == ("GoPro Max", "C3353424500199")
    cori = gopro_max.stream("CORI")
    assert cori.times_s[0] == 0.0 and cori.rate_hz == pytest.approx(30000 / 1001, rel=1e-4)


def accl_path(shared_data: Path) -> Path:
    return shared_data / "gopro" / "max-heromode.mp4"


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(rotvec)
    if angle < 1e-15:
        return np.eye(3)
    k = rotvec / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rotation: np.ndarray = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    return rotation


def _quat_matrix(wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = wxyz / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))))


def test_max_gyro_is_rad_per_second_against_camera_orientation(gopro_max) -> None:
    """Integrating GYRO (rad/s) over 2..8 s turns the camera by the angle CORI reports.

    The rotation angle does not depend on the axis order, so file order is fine here;
    deg/s or a wrong SCAL would be off by 57x or more.
    """
    gyro, cori = gopro_max.stream("GYRO"), gopro_max.stream("CORI")
    t = gyro.times_s
    inside = (t >= 2.0) & (t < 8.0)
    rotation = np.eye(3)
    for w, dt in zip(gyro.values[inside][:-1], np.diff(t[inside]), strict=True):
        rotation = rotation @ _rotation(w * dt)
    ia = int(np.argmin(np.abs(cori.times_s - t[inside][0])))
    ib = int(np.argmin(np.abs(cori.times_s - t[inside][-1])))
    relative = _quat_matrix(cori.values[ia]).T @ _quat_matrix(cori.values[ib])
    assert _angle_deg(relative) > 3.0  # the camera did turn
    assert _angle_deg(rotation) == pytest.approx(_angle_deg(relative), abs=1.0)


def test_max_orientation_matrix_comes_from_mtrx(gopro_max) -> None:
    accl = gopro_max.stream("ACCL")
    assert accl.orientation_in == "XzY"
    np.testing.assert_array_equal(accl.orientation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]])


def test_only_requested_streams_and_errors(shared_data: Path, karma) -> None:
    only = read_telemetry(shared_data / "gopro" / "karma.mp4", keys={"GYRO", "NOPE"})
    assert set(only.streams) == {"GYRO"}
    with pytest.raises(InputError, match=r"karma\.mp4: no GPMF stream 'NOPE'"):
        only.stream("NOPE")
    # Streams of the Karma drone (a second device) are named with its DVID.
    assert "ATTD@16835857" in karma.streams
    with pytest.raises(InputError, match="non-numeric type 'c'"):
        karma.stream("FWVS@16835857")
    summary = format_summary(karma)
    assert "ACCL" in summary and "2397" in summary and "m/s²" in summary


def test_csv_round_trip_and_no_overwrite(tmp_path: Path, karma) -> None:
    accl = karma.stream("ACCL")
    path = write_telemetry_csv(accl, tmp_path / "accl.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == "t_s,v0,v1,v2" and len(lines) == 1 + accl.samples
    table = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, 0], accl.times_s, atol=1e-9)
    np.testing.assert_allclose(table[:, 1:], accl.values, rtol=1e-9)
    assert table[0, 1] == pytest.approx(4246 / 418)
    with pytest.raises(OutputExistsError):
        write_telemetry_csv(accl, path)


def test_cli_telemetry_csv_and_summary_as_subprocess(tmp_path: Path, shared_data: Path) -> None:
    video = shared_data / "gopro" / "max-heromode.mp4"
    out = tmp_path / "gyro.csv"
    command = [sys.executable, "-m", "field.cli", "gopro", "telemetry", str(video)]
    done = subprocess.run(
        [*command, "--stream", "GYRO", "--csv", str(out)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    assert table.shape == (2082, 4)
    assert table[0, 1:].tolist() == pytest.approx([68 / 939, 209 / 939, -146 / 939])
    again = subprocess.run(
        [*command, "--stream", "GYRO", "--csv", str(out)], capture_output=True, text=True
    )
    assert again.returncode == 1 and "already exists" in again.stderr
    summary = subprocess.run(command, capture_output=True, text=True)
    assert summary.returncode == 0
    assert "GoPro Max" in summary.stdout and "ACCL" in summary.stdout and "stmp" in summary.stdout
    bad = subprocess.run(
        [*command, "--csv", str(tmp_path / "x.csv")], capture_output=True, text=True
    )
    assert bad.returncode == 1 and "--csv needs --stream" in bad.stderr
    missing = subprocess.run(
        [*command[:-1], str(tmp_path / "none.mp4")], capture_output=True, text=True
    )
    assert missing.returncode == 1 and "cannot open" in missing.stderr
