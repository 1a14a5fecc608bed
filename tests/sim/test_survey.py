"""The whole simulated survey: layout, truth, determinism, and the CLI as a subprocess."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.errors import OutputExistsError
from sim.survey import SurveyOptions, SurveySimulator, depth_png_mm, run

REPO = Path(__file__).resolve().parents[3]


def tiny(**overrides: object) -> SurveyOptions:
    values: dict[str, object] = {
        "sessions": 2, "duration_s": 1.0, "seed": 7, "width": 64, "height": 36, "fps": 10.0,
        "texel_m": 0.05, "seafloor_texel_m": 0.2, "workers": 1,
    }  # fmt: skip
    values.update(overrides)
    return SurveyOptions(**values)  # type: ignore[arg-type]


def digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return run(tiny(), tmp_path_factory.mktemp("survey") / "out")


def test_layout_and_truth(survey: Path) -> None:
    from field.gopro.cameras import body_from_file_axes
    from field.gopro.telemetry import read_telemetry
    from shared.calibration.kalibr import read_camchain, read_target_yaml
    from shared.formats.diveprofile import read_dive_folder
    from shared.formats.euroc import read_euroc

    truth = json.loads((survey / "truth.json").read_text())
    assert truth["format"] == "wreckmap-sim-truth"
    assert {t["tag_id_offset"] for t in truth["targets"]} == {0, 100}
    for target in truth["targets"]:
        grid = read_target_yaml(survey / target["yaml"])
        assert grid.tag_id_offset == target["tag_id_offset"]
        assert (grid.tag_rows, grid.tag_cols) in {(2, 4), (4, 5)}
    (cam,) = read_camchain(survey / "calib" / "camchain.yaml")
    np.testing.assert_allclose(cam.cam_from_imu, truth["camera"]["cam_from_imu"], atol=1e-9)
    assert cam.timeshift_cam_imu_s == truth["camera"]["timeshift_cam_imu_s"]
    assert (survey / "truth_mesh.ply").read_bytes().startswith(b"ply\n")
    sim = SurveySimulator(tiny())
    for k, session in enumerate(truth["sessions"]):
        data = read_euroc(survey / session["files"]["euroc"])
        assert len(data.image_stamps_ns) == 10
        assert data.image_stamps_ns[0] == session["first_frame_cam_ns"]
        assert data.groundtruth is not None
        # The ground truth is the simulator's body pose at the IMU stamps.
        np.testing.assert_allclose(
            data.groundtruth.poses, sim.world_from_body(k, data.groundtruth.stamps_ns), atol=1e-6
        )
        # Images were taken at t_cam + timeshift: the stored first camera pose says so.
        np.testing.assert_allclose(
            sim.world_from_cam(k, [session["first_frame_cam_ns"]])[0],
            session["world_from_first_cam"], atol=1e-12,
        )  # fmt: skip
        (dive,) = read_dive_folder(survey / session["files"]["dive"])
        clock = session["clocks"]["dive_computer"]
        film_start_dc_s = (session["start_ns"] + clock["offset_ns"]) * 1e-9
        assert dive.stamps_s[0] < film_start_dc_s < dive.stamps_s[-1]
        telemetry = read_telemetry(survey / session["files"]["gopro"])
        accl = telemetry.stream("ACCL")
        # Media time t of an IMU sample is its true time minus timeshift minus frame 0.
        first_true = accl.times_ns[0] + session["first_frame_cam_ns"] + sim.timeshift_ns
        index = np.searchsorted(data.imu_stamps_ns, first_true)
        assert abs(int(data.imu_stamps_ns[index]) - int(first_true)) < 1000
        # The file holds GoPro axes (ORIN), as a camera writes them; mapped back they are B's.
        body = accl.values[:50] @ body_from_file_axes(accl.orientation_in or "").T
        np.testing.assert_allclose(body, data.accel_m_s2[index : index + 50], atol=0.01)


def test_same_seed_same_bytes(tmp_path: Path, survey: Path) -> None:
    again = run(tiny(workers=2), tmp_path / "again")
    assert digest(again) == digest(survey)
    other = run(tiny(seed=8, video=False, save_depth=True), tmp_path / "other")
    assert not (other / "session_00" / "gopro").exists()
    # Depth maps are the renderer's depth in millimetres.
    sim = SurveySimulator(tiny(seed=8))
    stamp = int(sim.sessions[1].frame_stamps_cam_ns[3])
    stored = cv2.imread(str(other / f"session_01/depth/{stamp}.png"), cv2.IMREAD_UNCHANGED)
    rendered = sim.render_frame(1, stamp, frame_index=3).depth_m
    assert stored is not None
    assert stored.dtype == np.uint16
    np.testing.assert_array_equal(stored, depth_png_mm(rendered))
    assert 500 < np.median(stored) < 10000
    a = digest(survey)
    b = digest(other)
    assert a["session_00/euroc/mav0/imu0/data.csv"] != b["session_00/euroc/mav0/imu0/data.csv"]


def test_video_crf_sets_the_video_quality(tmp_path: Path, survey: Path) -> None:
    """A higher CRF spends fewer bits on the same frames; the rest of the folder is unchanged."""
    coarser = run(tiny(video_crf=SurveyOptions().video_crf + 10), tmp_path / "coarser")
    a, b = digest(survey), digest(coarser)
    videos = [name for name in a if name.endswith(".MP4")]
    assert videos
    for name in videos:
        assert 1.5 * (coarser / name).stat().st_size < (survey / name).stat().st_size
    assert {k: v for k, v in a.items() if k not in videos} == {
        k: v for k, v in b.items() if k not in videos
    }


def test_refuses_to_overwrite(survey: Path) -> None:
    with pytest.raises(OutputExistsError):
        run(tiny(), survey)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("sessions", 0, "sessions"),
        ("duration_s", 0.0, "duration_s"),
        ("width", 63, "even"),
        ("fps", 0.0, "fps"),
        ("timeshift_cam_imu_s", 2.0, "timeshift"),
        ("start_utc", "yesterday", "ISO 8601"),
        ("cam_from_imu", np.ones((4, 4)), "rigid"),
        ("video_crf", 52, "video_crf"),
    ],
)
def test_bad_options_raise(field: str, value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        tiny(**{field: value})


def test_cli_runs_as_a_subprocess(tmp_path: Path) -> None:
    out = tmp_path / "cli"
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    command = [
        sys.executable, "-m", "field.cli", "sim", "survey", "--out", str(out), "--sessions", "1",
        "--duration", "0.5", "--width", "48", "--height", "32", "--fps", "8", "--texel-mm", "50",
        "--seed", "3", "--workers", "1", "--depth",
    ]  # fmt: skip
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert (out / "truth.json").is_file()
    assert len(list((out / "session_00/euroc/mav0/cam0/data").glob("*.png"))) == 4
    assert (out / "session_00/gopro/GX010001.MP4").is_file()
    assert len(list((out / "session_00/depth").glob("*.png"))) == 4
    again = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert again.returncode == 1
    assert "already exists" in again.stderr
    bad = subprocess.run(
        [*command[:5], "--out", str(tmp_path / "bad"), "--width", "47"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert bad.returncode == 1
    assert "even" in bad.stderr


def test_extrinsic_and_time_offset_are_parameters() -> None:
    offset = np.eye(4)
    offset[:3, 3] = (0.1, 0.0, 0.0)
    sim = SurveySimulator(tiny(cam_from_imu=offset, timeshift_cam_imu_s=-0.02))
    np.testing.assert_array_equal(sim.calibration.cam_from_imu, offset)
    stamp = int(sim.sessions[0].frame_stamps_cam_ns[2])
    body = sim.world_from_body(0, [stamp - 20_000_000])[0]
    np.testing.assert_allclose(
        sim.world_from_cam(0, [stamp])[0], body @ np.linalg.inv(offset), atol=1e-12
    )


def test_render_worker_needs_a_simulator() -> None:
    import sim.survey as survey_module

    saved = survey_module._WORKER_SIM
    survey_module._WORKER_SIM = None
    try:
        with pytest.raises(RuntimeError, match="simulator"):
            survey_module._render_task((0, 0, 0))
    finally:
        survey_module._WORKER_SIM = saved
