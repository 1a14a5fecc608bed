"""The SLAM stage and `wreckmap-post slam` on a tiny rendered EuRoC folder."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Generator
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from postproc.slam.frontend import FrontendOptions
from postproc.slam.inputs import open_input
from postproc.slam.stage import (
    THINNING_PROBE_FRAMES,
    RateThinning,
    SlamOptions,
    min_frame_step_ns,
    run,
)
from shared.calibration.kalibr import read_camchain, read_imu_yaml, write_camchain, write_imu_yaml
from shared.errors import InputError, OutputExistsError, StageError
from shared.formats.euroc import read_euroc
from shared.formats.tum import read_tum
from shared.trajectory import ate

REPO = Path(__file__).resolve().parents[3]


def test_cli_writes_the_slam_result_folder(wall_euroc: Path, tmp_path: Path) -> None:
    out = tmp_path / "slam"
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "postproc.cli",
            "slam",
            str(wall_euroc),
            "--out",
            str(out),
            "--width",
            "0",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(out)
    trajectory = read_tum(out / "trajectory.tum")
    keyframes = read_tum(out / "keyframes.tum")
    truth = read_euroc(wall_euroc)
    assert len(trajectory) == len(truth.image_stamps_ns)
    np.testing.assert_array_equal(trajectory.stamps_ns, truth.image_stamps_ns)
    np.testing.assert_allclose(trajectory.positions[0], 0.0, atol=1e-6)
    # Metric and accurate: measured 3.3 mm over the 3.2 m path.
    assert truth.groundtruth is not None
    assert ate(trajectory, truth.groundtruth, align="se3").rmse_m < 0.03
    # Keyframe images: one per keyframe pose, byte-identical to the recorded PNGs.
    images = sorted((out / "keyframes").glob("*.png"))
    assert [int(p.stem) for p in images] == keyframes.stamps_ns.tolist()
    recorded = {int(p.stem): p for p in truth.image_paths}
    assert images[1].read_bytes() == recorded[int(images[1].stem)].read_bytes()
    assert truth.camera is not None
    camera = read_camchain(out / "calib" / "camchain.yaml")[0]
    assert camera.camera == truth.camera.camera
    assert read_imu_yaml(out / "calib" / "imu.yaml") == truth.imu_noise
    # Keyframe poses are camera poses: T_S_C = T_S_B T_B_C at the keyframe stamps.
    idx = np.searchsorted(trajectory.stamps_ns, keyframes.stamps_ns)
    np.testing.assert_allclose(
        keyframes.poses, trajectory.poses[idx] @ truth.camera.imu_from_cam, atol=1e-6
    )
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] == len(trajectory)
    assert stats["keyframes"] == len(keyframes)
    assert stats["loop_closures"] == 0
    assert stats["tracking_failures"] == 0
    assert stats["real_time_factor"] > 0
    # CPU seconds of each of the three threads, within the process's total.
    threads = stats["cpu_time_threads_s"]
    assert set(threads) == {"decode", "frontend", "estimator"}
    assert all(v > 0 for v in threads.values())
    assert sum(threads.values()) <= stats["cpu_time_s"] + 0.5
    header, _, body = (out / "map.ply").read_bytes().partition(b"end_header\n")
    assert f"element vertex {stats['landmarks']}".encode() in header
    assert len(body) == 12 * stats["landmarks"] > 0


def test_existing_result_is_kept_unless_overwrite(wall_euroc: Path, tmp_path: Path) -> None:
    options = SlamOptions(frontend=FrontendOptions(width_px=0), max_frames=60)
    out = run(options, wall_euroc, tmp_path / "slam")
    stats = (out / "stats.json").read_text()
    assert json.loads(stats)["frames"] == 60
    # Complete result of the same inputs and options: returned as is, nothing recomputed.
    assert run(options, wall_euroc, out) == out
    assert (out / "stats.json").read_text() == stats
    # Other options: refused (the result is not returned as if it were theirs).
    other = SlamOptions(frontend=FrontendOptions(width_px=0), max_frames=50)
    with pytest.raises(OutputExistsError, match="other inputs or options"):
        run(other, wall_euroc, out)
    assert (out / "stats.json").read_text() == stats
    # Incomplete folder in the way: refused.
    (out / "stats.json").unlink()
    with pytest.raises(OutputExistsError):
        run(options, wall_euroc, out)
    run(options, wall_euroc, out, overwrite=True)
    assert (out / "stats.json").is_file()


def test_frame_step_keeps_every_third_image_of_a_jittery_30_fps_stream() -> None:
    rng = np.random.default_rng(4)
    stamps = np.arange(300) * 33_333_333 + rng.integers(-2_000_000, 2_000_000, 300)
    step = min_frame_step_ns(10.0)
    kept = [int(stamps[0])]
    for stamp in stamps[1:]:
        if stamp - kept[-1] >= step:
            kept.append(int(stamp))
    assert len(kept) == 100
    assert min_frame_step_ns(None) == 0
    with pytest.raises(InputError, match="max_rate_hz 0: expected a positive rate"):
        min_frame_step_ns(0)


def test_max_and_min_rate_use_part_of_the_images_and_stay_accurate(
    wall_euroc: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("WRECKMAP_PROGRESS", "1")
    options = SlamOptions(frontend=FrontendOptions(width_px=0), max_rate_hz=5.0)
    out = run(options, wall_euroc, tmp_path / "slam")
    trajectory = read_tum(out / "trajectory.tum")
    truth = read_euroc(wall_euroc)
    # 10 fps recorded, 5 used: every other image, each on its own stamp.
    assert len(trajectory) == pytest.approx(len(truth.image_stamps_ns) / 2, abs=2)
    assert set(trajectory.stamps_ns.tolist()) <= set(truth.image_stamps_ns.tolist())
    assert truth.groundtruth is not None
    assert ate(trajectory, truth.groundtruth, align="se3").rmse_m < 0.05
    # The bar counted the recording's images, not only the ones used: it ended full.
    images = len(truth.image_stamps_ns)
    assert f"{images}/{images}" in capfd.readouterr().err
    # A floor instead: 10 fps is twice 5 Hz, so every other image after the first 16.
    options = SlamOptions(frontend=FrontendOptions(width_px=0), min_rate_hz=5.0)
    out = run(options, wall_euroc, tmp_path / "thinned")
    thinned = read_tum(out / "trajectory.tum")
    stamps = truth.image_stamps_ns.tolist()
    assert json.loads((out / "stats.json").read_text())["frame_stride"] == 2
    probe = THINNING_PROBE_FRAMES + 1
    assert thinned.stamps_ns.tolist() == stamps[:probe] + stamps[probe + 1 :: 2]
    assert ate(thinned, truth.groundtruth, align="se3").rmse_m < 0.05
    with pytest.raises(InputError, match="max_rate_hz -1"):
        run(SlamOptions(max_rate_hz=-1.0), wall_euroc, tmp_path / "bad")
    with pytest.raises(InputError, match="min_rate_hz -1"):
        run(SlamOptions(min_rate_hz=-1.0), wall_euroc, tmp_path / "bad")
    with pytest.raises(InputError, match="max_speed_m_s -2: expected a positive speed"):
        run(SlamOptions(max_speed_m_s=-2.0), wall_euroc, tmp_path / "bad")
    assert not (tmp_path / "bad").exists()


def test_without_keyframe_images_the_same_trajectory_and_sfm_refuses_the_folder(
    wall_euroc: Path, tmp_path: Path
) -> None:
    from postproc.sfm.inputs import read_inputs

    outputs = {}
    for images in (True, False):
        options = SlamOptions(
            frontend=FrontendOptions(width_px=0), max_rate_hz=5.0, keyframe_images=images
        )
        outputs[images] = run(options, wall_euroc, tmp_path / f"slam_{images}")
    with_images, without = outputs[True], outputs[False]
    for name in ("trajectory.tum", "keyframes.tum"):
        assert (without / name).read_bytes() == (with_images / name).read_bytes()
    assert any((with_images / "keyframes").iterdir())
    assert not any((without / "keyframes").iterdir())
    stats = json.loads((without / "stats.json").read_text())
    assert stats["options"]["keyframe_images"] is False
    with pytest.raises(InputError, match="keyframe images missing"):
        read_inputs([without])


def test_errors(wall_euroc: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"missing: no such file or folder .*EuRoC"):
        run(SlamOptions(), tmp_path / "missing", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"empty: not a recording \(expected an EuRoC folder"):
        open_input(tmp_path / "empty")
    assert not (tmp_path / "out").exists()


def test_visual_only_baseline_through_the_cli(wall_euroc: Path, tmp_path: Path) -> None:
    out = tmp_path / "vo"
    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "postproc.cli",
            "slam",
            str(wall_euroc),
            "--out",
            str(out),
            "--width",
            "0",
            "--no-imu",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    trajectory = read_tum(out / "trajectory.tum")
    truth = read_euroc(wall_euroc).groundtruth
    assert truth is not None
    sim3 = ate(trajectory, truth, align="sim3")
    # Shape right, scale arbitrary (the first baseline is 1): measured 7 mm.
    assert sim3.rmse_m < 0.05
    assert abs(sim3.scale - 1.0) > 0.05
    assert "visual only" in json.loads((out / "stats.json").read_text())["init"]


def test_calibration_from_flags(wall_euroc: Path, tmp_path: Path) -> None:
    # An EuRoC folder without sensor.yaml files: the calibration must come from flags.
    bare = tmp_path / "bare"
    for sub in ("cam0", "imu0"):
        (bare / "mav0" / sub).mkdir(parents=True)
        shutil.copy(wall_euroc / "mav0" / sub / "data.csv", bare / "mav0" / sub / "data.csv")
    (bare / "mav0" / "cam0" / "data").symlink_to(wall_euroc / "mav0" / "cam0" / "data")
    options = SlamOptions(frontend=FrontendOptions(width_px=0), max_frames=60)
    with pytest.raises(InputError, match="--calib"):
        run(options, bare, tmp_path / "out")
    truth = read_euroc(wall_euroc)
    assert truth.camera is not None and truth.imu_noise is not None
    camchain = write_camchain(tmp_path / "camchain.yaml", [truth.camera])
    with pytest.raises(InputError, match="--imu"):
        run(options, bare, tmp_path / "out", camchain=camchain)
    imu_yaml = write_imu_yaml(tmp_path / "imu.yaml", truth.imu_noise)
    out = run(options, bare, tmp_path / "out", camchain=camchain, imu_yaml=imu_yaml)
    assert read_camchain(out / "calib" / "camchain.yaml")[0].camera == truth.camera.camera


def test_too_short_fails_cleanly(wall_euroc: Path, tmp_path: Path) -> None:
    with pytest.raises(StageError, match="keyframe"):
        run(SlamOptions(max_frames=1), wall_euroc, tmp_path / "short")
    assert not (tmp_path / "short").exists()


def test_prefetch_keeps_order_raises_producer_errors_and_stops_early() -> None:
    import threading

    from postproc.slam.stage import prefetch

    assert list(prefetch(range(50), depth=3)) == list(range(50))

    def failing():
        yield 1
        raise InputError("frame 2: broken PNG")

    got = []
    with pytest.raises(InputError, match="broken PNG"):
        for item in prefetch(failing()):
            got.append(item)
    assert got == [1]
    produced = []

    def endless():
        n = 0
        while True:
            produced.append(n)
            yield n
            n += 1

    # prefetch is a generator (annotated as returning an Iterator); close() stops it.
    stream = cast("Generator[int, None, None]", prefetch(endless(), depth=2))
    assert next(stream) == 0
    stream.close()  # stops the producer thread
    assert not any(t.name == "slam-prefetch" for t in threading.enumerate())
    assert len(produced) <= 5


def _slam_threads() -> list[str]:
    import threading

    return [t.name for t in threading.enumerate() if t.name.startswith("slam-")]


def test_an_error_in_the_pipelined_frontend_reaches_the_caller_and_stops_the_threads(
    wall_euroc: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cv2

    from postproc.slam.frontend import KltFrontend

    calls = []
    track = KltFrontend.track

    def failing_track(self: KltFrontend, *args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 25:
            raise RuntimeError("frontend broke at image 25")
        return track(self, *args, **kwargs)

    monkeypatch.setattr(KltFrontend, "track", failing_track)
    threads = cv2.getNumThreads()
    with pytest.raises(RuntimeError, match="image 25"):
        run(SlamOptions(), wall_euroc, tmp_path / "slam")
    assert not _slam_threads()
    assert cv2.getNumThreads() == threads  # the run's setting is undone
    assert not (tmp_path / "slam").exists()


def test_an_error_in_the_estimator_stops_the_frontend_and_decoder_threads(
    wall_euroc: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from postproc.slam.estimator import SlamEstimator

    process = SlamEstimator.process
    calls = []

    def failing_process(self: SlamEstimator, *args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 3:  # the frontend is several images ahead by now, or waiting
            raise KeyboardInterrupt
        return process(self, *args, **kwargs)

    monkeypatch.setattr(SlamEstimator, "process", failing_process)
    with pytest.raises(KeyboardInterrupt):  # (a patch the estimator's own process misses)
        run(SlamOptions(estimator_process="off"), wall_euroc, tmp_path / "slam")
    assert not _slam_threads()


def test_the_frontend_takes_the_bias_of_lag_images_before() -> None:
    import threading

    from postproc.slam.stage import BiasBoard

    board = BiasBoard(np.zeros(3), lag=2)
    assert np.all(board.bias_for(0) == 0) and np.all(board.bias_for(1) == 0)
    board.publish(0, np.full(3, 0.5))
    assert np.all(board.bias_for(2) == 0.5)
    got: list[Any] = []
    waiter = threading.Thread(target=lambda: got.append(board.bias_for(3)))
    waiter.start()
    waiter.join(timeout=0.2)
    assert waiter.is_alive()  # image 3 needs the bias after image 1
    board.publish(1, np.full(3, 1.0))
    waiter.join(timeout=5)
    assert not waiter.is_alive() and np.all(got[0] == 1.0)
    # Closing wakes a waiting frontend, which goes on unseeded (None).
    late = threading.Thread(target=lambda: got.append(board.bias_for(10)))
    late.start()
    board.close()
    late.join(timeout=5)
    assert not late.is_alive() and got[-1] is None
    with pytest.raises(ValueError, match="lag"):
        BiasBoard(None, lag=0)


def test_the_lag_shortens_for_large_images_to_bound_the_memory_in_flight() -> None:
    from postproc.slam.stage import (
        PIPELINE_LAG_FRAMES,
        PIPELINE_MEMORY_BYTES,
        pipeline_lag_frames,
    )

    assert pipeline_lag_frames(960, 540) == PIPELINE_LAG_FRAMES == 30
    assert pipeline_lag_frames(1920, 1080) == 30
    two_k = pipeline_lag_frames(2704, 1520)  # GoPro 2.7K
    assert 8 < two_k < 30
    assert (two_k + 4) * 2704 * 1520 * 3 <= PIPELINE_MEMORY_BYTES
    assert pipeline_lag_frames(3840, 2160) == 8  # 4K: the floor (the lag before stop 45)
    assert pipeline_lag_frames(5312, 2988) == 8


def test_the_pipeline_gives_the_same_result_as_running_in_turn(
    wall_euroc: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import postproc.slam.stage as stage

    run(SlamOptions(), wall_euroc, tmp_path / "a")
    run(SlamOptions(), wall_euroc, tmp_path / "b")
    # However the threads ran, the same seeds: the same trajectory, byte for byte.
    assert (tmp_path / "a" / "trajectory.tum").read_bytes() == (
        tmp_path / "b" / "trajectory.tum"
    ).read_bytes()
    # With a lag of one image the frontend waits for the estimator after every image:
    # the sequential order of before the pipeline (the seeds differ from lag 30's, the
    # accuracy does not).
    monkeypatch.setattr(stage, "PIPELINE_LAG_FRAMES", 1)
    run(SlamOptions(), wall_euroc, tmp_path / "c")
    truth = read_euroc(wall_euroc).groundtruth
    assert truth is not None
    errors = []
    for name in ("a", "c"):
        estimate = read_tum(tmp_path / name / "trajectory.tum")
        errors.append(ate(estimate, truth, align="se3").rmse_m)
    assert max(errors) < 2 * min(errors) + 0.005


def test_a_diverged_trajectory_is_refused_with_the_speed_named() -> None:
    from types import SimpleNamespace

    from postproc.slam.stage import _check_speed, keyframe_speeds_m_s

    stamps = np.array([0, 500_000_000, 1_000_000_000], dtype=np.int64)
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[1, 0, 3] = 0.4  # 0.8 m/s
    poses[2, 0, 3] = 8.4  # 16 m/s: diverged
    np.testing.assert_allclose(keyframe_speeds_m_s(stamps, poses), [0.8, 16.0])
    result = SimpleNamespace(
        keyframe_stamps_ns=stamps,
        keyframe_session_from_body=poses,
        stats={"landmarks": 12, "keyframes": 3},
    )
    _check_speed(result, 20.0, "clip")  # type: ignore[arg-type]
    with pytest.raises(StageError, match=r"clip: the trajectory diverged: 16.0 m/s .* 1 and 2"):
        _check_speed(result, 10.0, "clip")  # type: ignore[arg-type]


def test_gyro_check_on_a_calibrated_rig(wall_euroc: Path, tmp_path: Path) -> None:
    """Forced on, the check finds the simulated rig rigid (or too still to say) and
    reports it; an unknown setting is refused."""
    out = run(
        SlamOptions(frontend=FrontendOptions(width_px=0), gyro_check="on", max_frames=90),
        wall_euroc,
        tmp_path / "slam",
    )
    stats = json.loads((out / "stats.json").read_text())
    assert stats["gyro_check"] in ("rigid", "unknown")
    assert stats["camera_imu_rigid"] == {"rigid": "yes", "unknown": "unknown"}[stats["gyro_check"]]
    if stats["gyro_check"] == "rigid":  # the simulator's clocks and focal are exact
        assert abs(stats["gyro_check_time_shift_s"]) < 0.01
        assert abs(stats["gyro_check_focal_scale"] - 1.0) < 0.05
    with pytest.raises(ValueError, match="gyro_check 'yes'"):
        # A value the Literal type refuses, on purpose: the run must reject it.
        run(SlamOptions(gyro_check=cast(Any, "yes")), wall_euroc, tmp_path / "other")


def _children() -> list[str]:
    import multiprocessing

    return [p.name for p in multiprocessing.active_children()]


def test_the_estimator_process_gives_the_same_result_as_in_process(
    wall_euroc: Path, tmp_path: Path
) -> None:
    inside = run(SlamOptions(estimator_process="off"), wall_euroc, tmp_path / "inside")
    apart = run(SlamOptions(estimator_process="on"), wall_euroc, tmp_path / "apart")
    for name in ("trajectory.tum", "keyframes.tum", "map.ply"):
        assert (inside / name).read_bytes() == (apart / name).read_bytes(), name
    images = sorted(p.name for p in (inside / "keyframes").iterdir())
    assert images and images == sorted(p.name for p in (apart / "keyframes").iterdir())
    for name in images:
        assert (inside / "keyframes" / name).read_bytes() == (
            apart / "keyframes" / name
        ).read_bytes()
    stats = json.loads((apart / "stats.json").read_text())
    assert stats["estimator_process"] is True
    threads = stats["cpu_time_threads_s"]
    assert {"decode", "frontend", "estimator", "estimator-start", "estimator-link"} <= set(threads)
    # The worker's CPU time counts in the run's.
    assert stats["cpu_time_s"] >= threads["estimator"] + threads["estimator-start"]
    assert json.loads((inside / "stats.json").read_text())["estimator_process"] is False
    assert not _children() and not _slam_threads()


def test_the_estimator_process_logs_through_the_parent(
    wall_euroc: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import logging

    caplog.set_level(logging.DEBUG, logger="postproc.slam")
    run(SlamOptions(estimator_process="on", max_frames=40), wall_euroc, tmp_path / "slam")
    # The backend's debug line of every keyframe, logged in the worker.
    assert any(
        r.name == "postproc.slam.backend" and "new landmarks" in r.getMessage()
        for r in caplog.records
    )


def test_an_error_in_the_estimator_process_is_raised_as_itself(
    wall_euroc: Path, tmp_path: Path
) -> None:
    # Too short to start: the estimator's StageError, from the worker, as a StageError.
    with pytest.raises(StageError, match=r"wall_euroc: .*keyframe") as raised:
        run(SlamOptions(max_frames=1, estimator_process="on"), wall_euroc, tmp_path / "short")
    cause = raised.value.__cause__
    assert isinstance(cause, StageError)  # the worker's own error, with its traceback
    assert any("estimator process" in note for note in cause.__notes__)
    assert not (tmp_path / "short").exists()
    assert not _children() and not _slam_threads()


def test_the_estimator_process_ends_with_an_error_or_interrupt_in_the_parent(
    wall_euroc: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from postproc.slam.estimator_process import EstimatorProcess

    submit = EstimatorProcess.submit
    calls = []

    def interrupted(self: EstimatorProcess, *args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 20:
            raise KeyboardInterrupt
        return submit(self, *args, **kwargs)

    monkeypatch.setattr(EstimatorProcess, "submit", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(SlamOptions(estimator_process="on"), wall_euroc, tmp_path / "slam")
    assert not _children() and not _slam_threads()
    assert not (tmp_path / "slam").exists()


def test_a_dead_estimator_process_is_a_stage_error(wall_euroc: Path, tmp_path: Path) -> None:
    import os
    import signal

    import postproc.slam.estimator_process as estimator_process

    class Killed(estimator_process.EstimatorProcess):
        def submit(self, sequence: int, *args: Any) -> None:
            if sequence == 15:
                os.kill(self._process.pid or 0, signal.SIGKILL)
                self._process.join()
            super().submit(sequence, *args)

    import postproc.slam.stage as stage

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(stage, "EstimatorProcess", Killed)
        with pytest.raises(StageError, match="estimator process ended unexpectedly"):
            run(SlamOptions(estimator_process="on"), wall_euroc, tmp_path / "slam")
    assert not _children() and not _slam_threads()


def test_the_frontend_runs_ahead_of_a_busy_estimator_process_past_the_pipe() -> None:
    """A worker busy with a long keyframe must not stall the frontend while ring slots
    are free: 60 images' tracks (about 1 MB) are far more than a pipe holds (64 KiB)."""
    import signal
    import threading

    from postproc.slam.estimator_process import EstimatorProcess, EstimatorSetup
    from postproc.slam.inputs import Frame
    from postproc.slam.options import EstimatorOptions
    from postproc.slam.types import FrameTracks

    setup = EstimatorSetup(
        options=EstimatorOptions(),
        focal_px=400.0,
        imu_from_cam=np.eye(4),
        imu=None,
        imu_noise=None,
        image_shape=(48, 64),
    )
    answered: list[int] = []
    image = np.zeros((48, 64), np.uint8)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.5, 0.5, (400, 2))
    count = 60
    with EstimatorProcess(
        setup,
        publish=lambda seq, bias: answered.append(seq),
        on_keyframe=lambda f: None,
        slots=count + 4,
    ) as worker:
        pid = worker._process.pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)  # the worker in a long update
        try:

            def submit_all() -> None:
                for seq in range(count):
                    tracks = FrameTracks(
                        stamp_ns=seq * 33_000_000,
                        track_ids=np.arange(400, dtype=np.int64),
                        xy_normalised=xy,
                        pixels=(xy + 1.0) * 30.0,
                        image_size=(64, 48),
                    )
                    worker.submit(seq, Frame(seq, tracks.stamp_ns, image), tracks, image)

            feeding = threading.Thread(target=submit_all)
            feeding.start()
            feeding.join(timeout=60)  # a hang guard: the submits take milliseconds
            ran_ahead = not feeding.is_alive()
        finally:
            os.kill(pid, signal.SIGCONT)
        feeding.join()
        assert ran_ahead, "the frontend waited for a stopped estimator with ring slots free"
        assert not answered  # (nothing was estimated meanwhile)
        with pytest.raises(StageError):  # no parallax: nothing to start from
            worker.finish()
    assert answered == list(range(count))  # every image, in order, once it went on
    assert not _children() and not _slam_threads()


def test_auto_runs_the_estimator_apart_only_for_long_inputs_on_a_free_core() -> None:
    from postproc.slam.estimator_process import MIN_FRAMES, use_a_process

    two_cores = len(os.sched_getaffinity(0)) >= 2
    assert not use_a_process("auto", MIN_FRAMES - 1, busy_cores=0.0)
    assert use_a_process("auto", MIN_FRAMES, busy_cores=0.0) == two_cores
    # Every core busy with other work: the worker would only add its cost.
    cores = len(os.sched_getaffinity(0))
    assert not use_a_process("auto", MIN_FRAMES, busy_cores=float(cores))
    assert not use_a_process("auto", 10**6, busy_cores=cores - 0.5)
    assert use_a_process("on", 1) and not use_a_process("off", 10**6)
    with pytest.raises(ValueError, match="estimator_process 'yes'"):
        use_a_process("yes", 10)


def test_busy_cores_come_from_the_cpu_counters_not_the_lagging_load_average() -> None:
    from postproc.slam.estimator_process import busy_cores_between, busy_cores_now

    def stat(user: int, idle: int, iowait: int) -> str:
        # user nice system idle iowait irq softirq steal guest guest_nice, then 2 CPUs
        return (
            f"cpu  {user} 0 0 {idle} {iowait} 0 0 0 0 0\n"
            "cpu0 1 0 0 1 0 0 0 0 0 0\ncpu1 1 0 0 1 0 0 0 0 0 0\nintr 5\n"
        )

    # 100 ticks went by on 2 CPUs: 60 busy, 30 idle, 10 waiting on I/O (idle too).
    assert busy_cores_between(stat(1000, 500, 50), stat(1060, 530, 60)) == pytest.approx(1.2)
    assert busy_cores_between(stat(1000, 500, 50), stat(1000, 600, 50)) == 0.0
    assert busy_cores_between(stat(1, 1, 1), stat(1, 1, 1)) is None  # no tick went by
    assert busy_cores_between("intr 5\n", stat(1, 1, 1)) is None
    busy = busy_cores_now(0.05)
    if Path("/proc/stat").exists():
        assert busy is not None and 0.0 <= busy <= (os.cpu_count() or 1) + 1e-9
    else:
        assert busy is None


def test_the_background_probe_leaves_out_this_process_own_cpu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from postproc.slam import estimator_process
    from postproc.slam.estimator_process import MIN_FRAMES, BusyProbe, use_a_process

    def stat(user: int, idle: int) -> str:
        return f"cpu  {user} 0 0 {idle} 0 0 0 0 0 0\ncpu0 1 0 0 1\ncpu1 1 0 0 1\n"

    class Clock:  # a 1 s window in which this process used `own` CPU seconds
        def __init__(self, own: float) -> None:
            self.own, self.calls = own, 0

        def process_time(self) -> float:
            self.calls += 1
            return 0.0 if self.calls == 1 else self.own

        def monotonic(self) -> float:
            return 0.0 if self.calls <= 1 else 1.0

        def sleep(self, seconds: float) -> None:
            pass

    for own, expected in [(0.7, 0.5), (0.0, 1.2), (2.0, 0.0)]:
        readings = iter([stat(1000, 500), stat(1060, 540)])  # 1.2 of 2 cores busy
        monkeypatch.setattr(estimator_process, "_read_proc_stat", readings.__next__)
        monkeypatch.setattr(estimator_process, "time", Clock(own))
        probe = BusyProbe(0.01)
        assert probe.result() == pytest.approx(expected)
    # The stage's choice takes the probe's figure: 0 other cores busy here.
    two_cores = len(os.sched_getaffinity(0)) >= 2
    assert use_a_process("auto", MIN_FRAMES, probe=probe) == two_cores
    # A run that never asks (or fails first) ends the window at once: no thread left.
    monkeypatch.undo()
    waiting = BusyProbe(60.0)
    started = time.monotonic()
    waiting.cancel()
    assert time.monotonic() - started < 30.0  # (a hang guard: it returns at once)
    assert waiting.result() is None and not _slam_threads()


CTRL_C_SCRIPT = """
import signal, sys, time
# As in a terminal's job: a test runner's worker may ignore SIGINT, and an ignored signal
# is inherited across exec (Python then installs no KeyboardInterrupt handler).
signal.signal(signal.SIGINT, signal.default_int_handler)
from postproc.slam import estimator_process
from postproc.slam.frontend import KltFrontend
from postproc.slam.stage import SlamOptions, run

track = KltFrontend.track
calls = 0
def slow_track(self, *args, **kwargs):
    global calls
    calls += 1
    if calls == 3:  # tracking, beside a started worker: the test's cue for its Ctrl-C
        print("tracking", flush=True)
    time.sleep(0.1)  # keeps the run going until the Ctrl-C
    return track(self, *args, **kwargs)
KltFrontend.track = slow_track
start = estimator_process.EstimatorProcess.__init__
def started(self, *args, **kwargs):
    start(self, *args, **kwargs)
    print("worker", self._process.pid, flush=True)
estimator_process.EstimatorProcess.__init__ = started
run(SlamOptions(estimator_process="on"), sys.argv[1], sys.argv[2])
"""


def test_ctrl_c_stops_the_stage_and_its_estimator_process(wall_euroc: Path, tmp_path: Path) -> None:
    import signal
    import time

    env = {**os.environ, "WRECKMAP_PROGRESS": "0"}
    child = subprocess.Popen(
        [sys.executable, "-c", CTRL_C_SCRIPT, str(wall_euroc), str(tmp_path / "slam")],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's job
    )
    try:
        assert child.stdout is not None
        worker = int(child.stdout.readline().split()[1])
        # Cued by the run itself, not by a fixed wait: on a loaded machine the worker's
        # start can take seconds.
        assert child.stdout.readline().strip() == "tracking"
        time.sleep(0.5)  # a few images into the estimator
        os.killpg(child.pid, signal.SIGINT)  # what Ctrl-C sends: every process of the job
        _, stderr = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
    assert child.returncode != 0, stderr
    assert stderr.count("KeyboardInterrupt") == 1, stderr  # the parent's, not the worker's
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and Path(f"/proc/{worker}").exists():
        time.sleep(0.1)
    assert not Path(f"/proc/{worker}").exists()
    assert not (tmp_path / "slam").exists()


@pytest.mark.parametrize(
    ("fps", "stride"),
    [(30.0, 2), (30000 / 1001, 2), (60.0, 4), (24.0, 1), (20.0, 1), (45.0, 3)],
)
def test_rate_thinning_takes_every_kth_image_of_a_fast_recording(fps: float, stride: int) -> None:
    thinning = RateThinning(15.0)
    rng = np.random.default_rng(0)
    # 2 ms of stamp jitter, as a camera clock gives.
    stamps = (np.arange(300) / fps * 1e9 + rng.uniform(-2e6, 2e6, 300)).astype(np.int64)
    kept = [int(s) for s in stamps if thinning.keep(int(s))]
    assert thinning.stride == stride
    probe = THINNING_PROBE_FRAMES + 1
    assert kept[:probe] == stamps[:probe].tolist()  # the probe's images all go through
    assert kept[probe:] == stamps[probe - 1 + stride :: stride].tolist()


def test_rate_thinning_also_holds_the_rate_cap_from_the_first_image() -> None:
    stamps = [round(k * 1e9 / 30) for k in range(90)]
    capped = RateThinning(15.0, min_step_ns=min_frame_step_ns(10.0))
    assert [s for s in stamps if capped.keep(s)] == stamps[::3]  # 10 of 30 a second
    assert capped.stride == 2  # (the floor's step is the shorter one)
    alone = RateThinning(None, min_step_ns=min_frame_step_ns(10.0))
    assert [s for s in stamps if alone.keep(s)] == stamps[::3] and alone.stride == 1


def test_rate_thinning_keeps_a_camera_that_alternates_short_and_long_steps() -> None:
    # The real hand-held recording: 33 and 60 ms steps, about 19 images a second.
    steps = np.tile([33_000_000, 60_000_000], 100)
    stamps = np.concatenate([[0], np.cumsum(steps)])
    thinning = RateThinning(15.0)
    assert all(thinning.keep(int(s)) for s in stamps) and thinning.stride == 1
    every = RateThinning(None)
    assert all(every.keep(int(s)) for s in np.arange(100) * 10_000_000)
    with pytest.raises(InputError, match="min_rate_hz 0"):
        RateThinning(0.0)
