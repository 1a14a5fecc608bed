"""The SLAM stage: a recording in, a SLAM result folder out (docs/conventions.md).

`run(options, input_path, out_dir)` tracks every image (frontend), picks
keyframes, estimates the visual-inertial trajectory (backend) and writes:

    trajectory.tum      body (IMU) poses T_S_B at every image, camera-clock stamps
    keyframes.tum       camera poses T_S_C of the keyframes
    keyframes/<ns>.png  keyframe images, distorted and at the resolution recorded
    calib/camchain.yaml the camera model used (Kalibr), calib/imu.yaml the IMU noise
    map.ply             sparse landmarks in S (binary little-endian PLY, float32 xyz)
    stats.json          frames, keyframes, run time, real-time factor (wall clock, and
                        per CPU second with the load average beside it), the CPU
                        seconds of each thread ("cpu_time_threads_s"), loop closures,
                        tracking failures, sliding-window and estimator counters, the
                        start ("init*"), map segments, the images the IMU covers
                        ("frames_before_imu", "frames_after_imu") and the IMU rows
                        merged, dropped or interpolated ("imu_*")

The session frame S: z up (gravity (0, 0, -9.81)), origin at the body (IMU)
position of the first keyframe, yaw such that the first keyframe's body x
axis, projected on the horizontal, points along +x. So `trajectory.tum`
starts at (0, 0, 0) and its z is height above the first keyframe.

Time stamps in both TUM files are the image stamps on the camera clock, as
recorded; the estimator runs on the IMU clock (t_imu = t_cam + Kalibr's
timeshift_cam_imu).

A calibration guess (a GoPro import without --calib) is first checked
against the gyro over the first seconds (postproc.slam.gyro_check): when the
images turn with the IMU, the measured time shift and focal scale replace the
guess; when they do not (electronically stabilised video), the path comes from
the images alone, gravity-aligned by the IMU (postproc.slam.stabilised).
stats.json reports the check ("gyro_check*", "camera_imu_rigid", "mode").

Images are decoded one thread ahead and tracked one more thread ahead of the
estimator (`prefetch`, `BiasBoard`), which can run in a second process
(`SlamOptions.estimator_process`, postproc.slam.estimator_process). A trajectory whose
keyframes move faster than `SlamOptions.max_speed_m_s` has diverged and is
refused with a StageError rather than written.

The folder is written under a temporary name and swapped in when complete
(`shared.folders.rebuild`, the resume rule of every stage): a complete result of
the same inputs and options is kept; another is refused unless overwrite.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import queue
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

from postproc.slam.estimator import SlamResult
from postproc.slam.estimator_process import (
    BusyProbe,
    EstimatorProcess,
    EstimatorRunner,
    EstimatorSetup,
    InProcessEstimator,
    use_a_process,
)
from postproc.slam.frontend import FrontendOptions, Image, KltFrontend
from postproc.slam.gyro_check import (
    GyroCheck,
    GyroCheckOptions,
    check_gyro_against_images,
    visual_rotation,
)
from postproc.slam.initialization import gyro_rotation
from postproc.slam.inputs import Frame, SlamInput, open_input
from postproc.slam.options import SlamOptions as SlamOptions
from postproc.slam.stabilised import gravity_and_scale
from postproc.slam.types import FloatArray, FrameTracks, ImuSamples, IntArray
from shared.calibration.kalibr import (
    CameraCalibration,
    ImuNoise,
    read_camchain,
    read_imu_yaml,
)
from shared.clock import NS_PER_S, ns_from_seconds, seconds_from_ns
from shared.errors import InputError, StageError
from shared.folders import SlamFolder, rebuild, result_stamp
from shared.formats.ply import PlyData, ply_bytes
from shared.formats.png import encode_png
from shared.progress import progress_bar
from shared.trajectory import Trajectory

LOG = logging.getLogger(__name__)
LANDMARKS_PLY_COMMENT = "wreckmap SLAM landmarks, session frame S, metres"

T = TypeVar("T")


def _resolve_calibration(
    source: SlamInput, camchain: Path | None, imu_yaml: Path | None, *, need_imu: bool
) -> tuple[CameraCalibration, ImuNoise | None]:
    if camchain is not None:
        calibration = read_camchain(camchain)[0]
    elif source.calibration is not None:
        calibration = source.calibration
    else:
        raise InputError(
            f"{source.name}: no camera calibration in the input (pass --calib camchain.yaml)"
        )
    noise: ImuNoise | None
    if imu_yaml is not None:
        noise = read_imu_yaml(imu_yaml)
    elif source.imu_noise is not None or not need_imu:
        noise = source.imu_noise
    else:
        raise InputError(f"{source.name}: no IMU noise model in the input (pass --imu imu.yaml)")
    return calibration, noise


def _gyro_rotation(
    imu: ImuSamples,
    calibration: CameraCalibration,
    t0_ns: int,
    t1_ns: int,
    gyro_bias_rad_s: FloatArray,
) -> FloatArray | None:
    """`R_Cnow_Cprev` between two images from the gyro (None when the IMU does not cover)."""
    shift = ns_from_seconds(calibration.timeshift_cam_imu_s)
    a, b = t0_ns + shift, t1_ns + shift
    if a < imu.stamps_ns[0] or b > imu.stamps_ns[-1] or b <= a:
        return None
    R_prev_now = gyro_rotation(imu, a, b, gyro_bias_rad_s)
    R_B_C = calibration.imu_from_cam[:3, :3]
    rotation: FloatArray = R_B_C.T @ R_prev_now.T @ R_B_C
    return rotation


@dataclass(frozen=True)
class ProbeRotations:
    """The image rotations of a clip's first seconds, as the gyro check compares them.

    starts_ns, ends_ns (P,): each frame pair's stamps; now_from_prev (P, 3, 3): its
    rotation `R_Cnow_Cprev` from the tracked features; focal_px: the frontend's focal.
    """

    starts_ns: IntArray
    ends_ns: IntArray
    now_from_prev: FloatArray
    focal_px: float


def probe_gyro(
    source: SlamInput,
    calibration: CameraCalibration,
    frontend_options: FrontendOptions,
    options: GyroCheckOptions,
) -> GyroCheck:
    """Track the first `options.probe_s` seconds (no gyro seeding) and compare rotations."""
    pairs = probe_rotations(source, calibration, frontend_options, options.probe_s)
    return check_probe(source, calibration, pairs, options)


def check_probe(
    source: SlamInput,
    calibration: CameraCalibration,
    pairs: ProbeRotations,
    options: GyroCheckOptions,
) -> GyroCheck:
    """The gyro check of `probe_rotations`' pairs against `source`'s IMU."""
    return check_gyro_against_images(
        starts_ns=pairs.starts_ns,
        ends_ns=pairs.ends_ns,
        visual_now_from_prev=pairs.now_from_prev,
        imu=source.imu,
        imu_from_cam_rotation=calibration.imu_from_cam[:3, :3],
        focal_px=pairs.focal_px,
        options=options,
    )


def probe_rotations(
    source: SlamInput,
    calibration: CameraCalibration,
    frontend_options: FrontendOptions,
    probe_s: float,
) -> ProbeRotations:
    """The frame pairs of the first `probe_s` seconds (tracked without gyro seeding)
    whose rotation at least 20 features agree on."""
    frontend = KltFrontend(frontend_options, calibration.camera)
    rng = np.random.default_rng(0)
    threshold_rad = 2.0 / frontend.focal_px
    starts: list[int] = []
    ends: list[int] = []
    rotations: list[FloatArray] = []
    previous: FrameTracks | None = None
    first: int | None = None
    frames = source.frames()
    try:
        for frame in frames:
            first = frame.stamp_ns if first is None else first
            if seconds_from_ns(frame.stamp_ns - first) > probe_s:
                break
            tracks = frontend.track(frame.stamp_ns, _pixels(frame))
            if previous is not None:
                _, ia, ib = np.intersect1d(
                    previous.track_ids, tracks.track_ids, return_indices=True
                )
                rotation, inliers = visual_rotation(
                    previous.xy_normalised[ia],
                    tracks.xy_normalised[ib],
                    rng=rng,
                    threshold_rad=threshold_rad,
                )
                if inliers >= 20:
                    starts.append(previous.stamp_ns)
                    ends.append(tracks.stamp_ns)
                    rotations.append(rotation)
            previous = tracks
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()
    return ProbeRotations(
        starts_ns=np.array(starts, dtype=np.int64),
        ends_ns=np.array(ends, dtype=np.int64),
        now_from_prev=np.array(rotations).reshape(-1, 3, 3),
        focal_px=float(frontend.focal_px),
    )


def _apply_gyro_check(calibration: CameraCalibration, check: GyroCheck) -> CameraCalibration:
    """The calibration with the measured time shift and focal length (rigid verdict only)."""
    camera = calibration.camera
    fields = {f.name for f in dataclasses.fields(camera)}  # type: ignore[arg-type]
    if not {"fx", "fy"} <= fields:
        return calibration
    corrected = dataclasses.replace(  # type: ignore[type-var]
        camera,
        fx=camera.intrinsic_matrix[0, 0] * check.focal_scale,
        fy=camera.intrinsic_matrix[1, 1] * check.focal_scale,
    )
    return dataclasses.replace(
        calibration, camera=corrected, timeshift_cam_imu_s=check.time_shift_s
    )


def run(
    options: SlamOptions,
    input_path: Path | str,
    out_dir: Path | str,
    *,
    camchain: Path | str | None = None,
    imu_yaml: Path | str | None = None,
    overwrite: bool = False,
) -> Path:
    """Run SLAM on an EuRoC or session folder; write the SLAM result folder `out_dir`.

    `camchain` / `imu_yaml` replace the calibration the input carries.
    Returns `out_dir`. The resume rule of every stage (`shared.folders.rebuild`): a
    complete result of the same inputs and options is kept; another is refused unless
    `overwrite`, then rebuilt beside it and swapped in. Raises InputError for unreadable
    inputs or missing calibration, StageError when no trajectory can be estimated.
    """
    folder = SlamFolder(out_dir)
    stamp = result_stamp(
        "slam", options, recording=input_path, camchain=camchain, imu_yaml=imu_yaml
    )
    # Whether a core is free for the estimator's process, measured while the setup runs.
    probe = BusyProbe() if options.estimator_process == "auto" else None
    try:
        with rebuild(folder, stamp, overwrite=overwrite) as work:
            if work is not None:
                _build(
                    options,
                    Path(input_path),
                    work,
                    camchain=camchain,
                    imu_yaml=imu_yaml,
                    probe=probe,
                )
    finally:
        if probe is not None:
            probe.cancel()  # (a run that never asked, or failed before it did)
    return folder.path


def _build(
    options: SlamOptions,
    input_path: Path,
    folder: SlamFolder,
    *,
    camchain: Path | str | None,
    imu_yaml: Path | str | None,
    probe: BusyProbe | None = None,
) -> None:
    """The SLAM run itself, written into the empty folder `folder`; `probe`: the busy-core
    check started by `run` ("auto")."""
    # The images to use (a bad rate is refused before any work).
    thinning = RateThinning(options.min_rate_hz, min_step_ns=min_frame_step_ns(options.max_rate_hz))
    if options.max_speed_m_s is not None and not options.max_speed_m_s > 0:
        raise InputError(
            f"max_speed_m_s {options.max_speed_m_s:g}: expected a positive speed (m/s), "
            "or none (--max-speed 0) to turn the check off"
        )
    source = open_input(input_path)
    if options.use_imu and len(source.imu) < 2:
        raise InputError(
            f"{source.name}: no IMU data in the input (expected mav0/imu0 or /imu0); "
            "run the visual-only path (--no-imu)"
        )
    calibration, noise = _resolve_calibration(
        source,
        Path(camchain) if camchain is not None else None,
        Path(imu_yaml) if imu_yaml is not None else None,
        need_imu=options.use_imu,
    )
    if options.gyro_check not in ("auto", "on", "off"):
        raise ValueError(f"gyro_check {options.gyro_check!r}: expected 'auto', 'on' or 'off'")
    check: GyroCheck | None = None
    wanted = options.gyro_check == "on" or (
        options.gyro_check == "auto" and camchain is None and source.calibration_is_guess
    )
    stabilised = False
    if options.use_imu and wanted:
        check = probe_gyro(source, calibration, options.frontend, options.gyro_check_options)
        if check.verdict == "rigid":
            LOG.info(
                "%s: the images turn with the gyro (%.0f %% unexplained); measured time shift "
                "%.3f s and focal x%.3f replace the guessed calibration",
                source.name,
                100 * check.unexplained,
                check.time_shift_s,
                check.focal_scale,
            )
            calibration = _apply_gyro_check(calibration, check)
        elif check.verdict == "not rigid":
            stabilised = True
            LOG.warning(
                "%s: the images do not turn with the gyro (%.0f %% of its rotation unexplained, "
                "apparent focal x%.2f, best lag %.3f s): an electronically stabilised video "
                "(or wrong IMU axes). No rigid camera-IMU model holds; the path comes from "
                "the images alone, with gravity (and, when it can, the scale) from the IMU",
                source.name,
                100 * check.unexplained,
                check.focal_scale,
                check.time_shift_s,
            )
        else:
            LOG.info(
                "%s: gyro check of the first %.0f s inconclusive (%s); the IMU is kept",
                source.name,
                options.gyro_check_options.probe_s,
                check.reason,
            )
    frontend = KltFrontend(options.frontend, calibration.camera)
    inertial = options.use_imu and not stabilised
    if inertial:
        assert noise is not None  # _resolve_calibration raised otherwise
    setup = EstimatorSetup(
        options=dataclasses.replace(
            options.estimator, timeshift_cam_imu_s=calibration.timeshift_cam_imu_s
        ),
        focal_px=frontend.focal_px,
        imu_from_cam=calibration.imu_from_cam,
        imu=source.imu if inertial else None,
        imu_noise=noise if inertial else None,
        image_shape=(frontend.image_size[1], frontend.image_size[0]),
    )
    started = time.monotonic()
    started_cpu = time.process_time()
    keyframe_dir = folder.keyframes
    keyframe_dir.mkdir(parents=True)
    total = source.frame_count
    if options.max_frames is not None:
        total = min(total, options.max_frames)
    in_a_process = use_a_process(options.estimator_process, total, probe=probe)
    tracking_failures = 0
    coverage = (
        ImuCoverage.of(source.imu, ns_from_seconds(calibration.timeshift_cam_imu_s))
        if options.use_imu
        else None
    )
    # CPU seconds of each thread (stats.json "cpu_time_threads_s"): decoding and image
    # preparation, tracking, and the estimator: in-process this thread, from here to
    # its result; in a second process, the worker's start and estimation and the
    # thread that takes its answers ("estimator-link"), this thread then tracking.
    thread_cpu_s: dict[str, float] = {}
    main_cpu_start = time.thread_time()
    lag = pipeline_lag_frames(calibration.camera.width, calibration.camera.height)
    biases = BiasBoard(setup.initial_gyro_bias(), lag=lag)
    tracked = _track_frames(
        # (Images the rate cap or thinning drops are not even decoded where the recording
        # allows.)
        source.frames(keep=thinning.keep),
        frontend,
        imu=setup.imu,
        calibration=calibration,
        biases=biases,
        max_frames=options.max_frames,
        cpu_s=thread_cpu_s,
    )
    first_stamp: int | None = None
    last_stamp = 0
    # The frontend (and, one thread further, the decoder) runs ahead of the estimator;
    # OpenCV and the decoders release the GIL, so on two cores they overlap the backend.
    # With the estimator in a second process this thread tracks (and hands each image
    # over): a thread of its own would only add a hand-off per image.
    stream = (
        tracked
        if in_a_process
        else prefetch(tracked, depth=lag, name="slam-frontend", cpu_s=thread_cpu_s)
    )
    # These threads are the parallelism: OpenCV's own worker threads on top of them
    # took 65 s of CPU time against 48 s for the same result (one pair of runs, 40 s
    # of 960x540 video, 2 shared cores).
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    save = functools.partial(_save_keyframe, folder) if options.keyframe_images else _no_image
    # With a second process the estimator runs beside the frontend's threads instead of
    # taking turns with them for the GIL (postproc.slam.estimator_process).
    runner: EstimatorRunner = (
        EstimatorProcess(setup, publish=biases.publish, on_keyframe=save, slots=lag + 4)
        if in_a_process
        else InProcessEstimator(setup, publish=biases.publish, on_keyframe=save)
    )
    # The bar counts the recording's images, used or not, so a rate cap or thinning still
    # ends at 100 % with a true ETA (with `max_frames`, the images used).
    bar = progress_bar(total=total or None, desc="slam", unit="frame")
    try:
        try:
            for sequence, item in enumerate(stream):
                frame, tracks = item.frame, item.tracks
                bar.update(
                    (sequence if options.max_frames is not None else frame.index) + 1 - bar.n
                )
                if len(tracks.track_ids) < options.min_tracks_ok:
                    tracking_failures += 1
                # (Outside the IMU's span an image is tracked, so the tracks run on, but
                # not estimated.)
                estimate = coverage is None or coverage.covers(frame.stamp_ns)
                runner.submit(sequence, frame, tracks if estimate else None, item.image)
                if estimate:
                    first_stamp = frame.stamp_ns if first_stamp is None else first_stamp
                    last_stamp = frame.stamp_ns
            if bar.total is not None and options.max_frames is None:
                bar.update(bar.total - bar.n)  # the images after the last one used were read
        finally:
            bar.close()
            biases.close()
            close = getattr(stream, "close", None)
            if close is not None:
                close()
            cv2.setNumThreads(opencv_threads)
        if coverage is not None:
            coverage.warn(source.name)
        try:
            result = runner.finish()
        except StageError as error:
            raise StageError(f"{source.name}: {error}") from error
    finally:
        runner.close()
    main_cpu_s = time.thread_time() - main_cpu_start
    thread_cpu_s["slam-frontend" if in_a_process else "slam-estimator"] = main_cpu_s
    thread_cpu_s.update(runner.cpu_seconds())
    if stabilised:
        result = gravity_and_scale(
            result,
            source.imu,
            shift_ns=ns_from_seconds(calibration.timeshift_cam_imu_s),
            gravity_m_s2=options.estimator.backend.gravity_m_s2,
        )
    result.stats["frame_stride"] = thinning.stride
    if check is not None:
        result.stats.update(check.as_stats())
        result.stats["camera_imu_rigid"] = {"rigid": "yes", "not rigid": "no"}.get(
            check.verdict, "unknown"
        )
    if stabilised and not result.stats.get("metric_scale"):
        LOG.warning(
            "%s: the IMU cannot fix the scale of the stabilised video's path (scale fit "
            "%.3g +- %.2g): the trajectory is gravity-aligned but NOT in metres",
            source.name,
            result.stats["imu_scale_fit"],
            result.stats["imu_scale_standard_error"],
        )
    metric = options.use_imu and result.stats.get("metric_scale", True)
    if options.max_speed_m_s is not None and metric:  # VO scale is arbitrary
        _check_speed(result, options.max_speed_m_s, source.name)
    run_time_s = time.monotonic() - started
    cpu_time_s = time.process_time() - started_cpu + runner.worker_cpu_s
    duration_s = seconds_from_ns(last_stamp - (first_stamp or last_stamp))
    _write_result(
        folder,
        result,
        calibration,
        noise,
        stats={
            "input": source.name,
            "run_time_s": run_time_s,
            "sequence_duration_s": duration_s,
            "real_time_factor": duration_s / run_time_s if run_time_s > 0 else 0.0,
            # CPU seconds of this process (all its threads) and of the estimator's
            # process if it has one: on a shared machine the wall-clock factor also
            # measures the other load.
            "cpu_time_s": cpu_time_s,
            "estimator_process": in_a_process,
            "real_time_factor_cpu": duration_s / cpu_time_s if cpu_time_s > 0 else 0.0,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
            "cpu_time_threads_s": {
                key.removeprefix("slam-"): value for key, value in thread_cpu_s.items()
            },
            "tracking_failures": tracking_failures,
            **(coverage.as_stats() if coverage is not None else {}),
            **source.imu_cleaning.as_stats(),
            "frontend_width_px": frontend.image_size[0],
            "lost_tracks": frontend.lost_tracks,
            "rejected_tracks": frontend.rejected_tracks,
            "recovered_tracks": frontend.recovered_tracks,
            "options": asdict(options),
        },
    )
    # Only keyframes the estimator kept have images (frames outside the IMU span do not).
    kept = {folder.keyframe_image(s) for s in result.keyframe_stamps_ns.tolist()}
    for path in keyframe_dir.iterdir():
        if path not in kept:
            path.unlink()


@dataclass
class ImuCoverage:
    """Which images the IMU covers, on the camera clock (int64 ns).

    An IMU often starts after the first image or stops before the last (a GoPro's
    first IMU sample can come 59 ms after its first frame). The visual-inertial
    estimate uses only the images inside the IMU's span; the others are counted and
    reported (stats.json: `frames_before_imu`, `frames_after_imu`).
    """

    start_cam_ns: int
    end_cam_ns: int
    before: int = 0
    after: int = 0
    inside: int = 0
    first_frame_ns: int | None = None
    last_frame_ns: int | None = None

    @classmethod
    def of(cls, imu: ImuSamples, shift_ns: int) -> ImuCoverage:
        """The span of `imu` moved to the camera clock (t_cam = t_imu - shift)."""
        return cls(int(imu.stamps_ns[0]) - shift_ns, int(imu.stamps_ns[-1]) - shift_ns)

    def covers(self, stamp_ns: int) -> bool:
        """Whether the image at `stamp_ns` (camera clock) lies in the IMU's span; counts it."""
        self.first_frame_ns = stamp_ns if self.first_frame_ns is None else self.first_frame_ns
        self.last_frame_ns = stamp_ns
        if stamp_ns < self.start_cam_ns:
            self.before += 1
            return False
        if stamp_ns > self.end_cam_ns:
            self.after += 1
            return False
        self.inside += 1
        return True

    def warn(self, name: str) -> None:
        """Log what the IMU left out (nothing when it covers every image)."""
        if self.before or self.after:
            LOG.warning(
                "%s: the IMU covers %d of %d images (it starts %.3f s after the first and "
                "ends %.3f s before the last); SLAM uses the images it covers",
                name,
                self.inside,
                self.inside + self.before + self.after,
                seconds_from_ns(max(self.start_cam_ns - (self.first_frame_ns or 0), 0)),
                seconds_from_ns(max((self.last_frame_ns or 0) - self.end_cam_ns, 0)),
            )

    def as_stats(self) -> dict[str, float | int]:
        """The stats.json entries."""
        first = self.first_frame_ns if self.first_frame_ns is not None else self.start_cam_ns
        last = self.last_frame_ns if self.last_frame_ns is not None else self.end_cam_ns
        return {
            "frames_before_imu": self.before,
            "frames_after_imu": self.after,
            "frames_in_imu_span": self.inside,
            "imu_starts_after_first_frame_s": seconds_from_ns(max(self.start_cam_ns - first, 0)),
            "imu_ends_before_last_frame_s": seconds_from_ns(max(last - self.end_cam_ns, 0)),
        }


PIPELINE_LAG_FRAMES = 30
"""How far (images) the frontend may run ahead of the estimator; the gyro bias that seeds
its tracking is the one the estimator had this many images earlier (see `BiasBoard`).

The estimator's work comes in bursts: a keyframe's update takes 50-220 ms (10th to 90th
percentile) and up to a second, against 9 ms an image for the tracker, and nothing
between keyframes. With 8 images of slack the tracker stopped at every long update and
the estimator waited for it after: on the 3-minute cut of bench_pipeline's 10-minute
dive (960x540, 30 fps, estimator in a second process) the run took 83.5 s; with 30, 60,
100 and 150 images 66.1, 65.7, 67.7 and 66.7 s (one run each; 300: 78.4 s, its
estimator taking 55 s of CPU against 36-40). 30, the shortest lag that gave the whole
gain, is 1 s at 30 fps and 3 s at the quick look's 10 images a second.

A bias that old does not matter: it changes far too slowly (a seed moves by hundredths
of a pixel). What changes is which tracks survive the forward-backward and RANSAC
thresholds, and the ATE follows that draw: 1.5-2.2 cm over those lags on that cut, and
0.39, 0.41, 0.57, 1.07 and 0.51 % of the path on the real handheld_a for lags 8, 16, 30,
60 and 100 (karma.mp4: 1.01, 0.95 and 0.98 % for 8, 30 and 60). On the demo's two 10 fps
dives, lag 1 (the sequential order of before the pipeline) gave 8.0 and 19.1 mm, lag 8
13.5 and 32.6 mm, and lag 1 with the bias moved by 1e-5 rad/s (a seed change of 3e-4 px)
13.2 and 26.9 mm: the same spread, not a cost of the lag."""

PIPELINE_MEMORY_BYTES = 256 * 1024**2
"""What the images in flight between the decoder and the estimator may take: each is
held as recorded, to be written if it turns out a keyframe (the sum below counts BGR; a
video frame is held as its 4:2:0 planes, half that). A 960x540 image takes
1.5 MiB, a 1080p one 5.9 MiB (34 of them 202 MiB); a 2.7K GoPro frame takes 12 MiB, a 4K
one 24 MiB and a 5.3K one 45 MiB, so those run with a shorter lag (17 images at 2.7K, at
least 8, the lag before stop 45), where their decoding weighs more than the estimator's
bursts anyway."""


def pipeline_lag_frames(width_px: int, height_px: int) -> int:
    """The bias lag for recorded images of this size: `PIPELINE_LAG_FRAMES`, shortened
    so that the images in flight (about the lag and the ring's 4 more) fit
    `PIPELINE_MEMORY_BYTES`, to no fewer than 8 (nor more than `PIPELINE_LAG_FRAMES`)."""
    image_bytes = max(width_px * height_px * 3, 1)
    fits = PIPELINE_MEMORY_BYTES // image_bytes - 4
    return min(PIPELINE_LAG_FRAMES, max(fits, 8))


class _Failure:
    def __init__(self, error: BaseException) -> None:
        self.error = error


class BiasBoard:
    """The gyro bias the estimator held after each image, for the frontend thread.

    The frontend seeds its optical flow with the gyro rotation between images, with the
    estimator's current gyro bias removed. Run ahead in its own thread, it takes for
    image n the bias published after image n - `lag` (the initial one before that),
    waiting for it if the estimator is further behind: the result is the same however
    the threads are scheduled (with `lag` 1, the same as running one after the other).
    `close` wakes a waiting frontend (its rotations go unseeded until the pipeline
    stops it).
    """

    def __init__(self, initial: FloatArray | None, *, lag: int) -> None:
        if lag < 1:
            raise ValueError(f"lag {lag}: expected at least 1 image")
        self.lag = lag
        self._initial = initial
        self._published: dict[int, FloatArray | None] = {}
        self._last = -1
        self._closed = False
        self._changed = threading.Condition()

    def publish(self, sequence: int, bias: FloatArray | None) -> None:
        """The estimator is done with image `sequence` (0, 1, ...) and now holds `bias`."""
        with self._changed:
            self._published[sequence] = bias
            self._last = sequence
            self._changed.notify_all()

    def bias_for(self, sequence: int) -> FloatArray | None:
        """The bias to seed image `sequence` with (waits for the estimator if needed;
        None once closed)."""
        wanted = sequence - self.lag
        if wanted < 0:
            return self._initial
        with self._changed:
            self._changed.wait_for(lambda: self._last >= wanted or self._closed)
            if self._last < wanted:
                return None
            for old in [k for k in self._published if k < wanted]:
                del self._published[old]
            return self._published[wanted]

    def close(self) -> None:
        """No more biases: wake a waiting frontend."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()


@dataclass(frozen=True)
class TrackedFrame:
    """One image after the frontend: the frame as read, its tracks, and the frontend image
    (grey, resized, equalised) that keyframe descriptors are computed on."""

    frame: Frame
    tracks: FrameTracks
    image: Image


def _track_frames(
    frames: Iterable[Frame],
    frontend: KltFrontend,
    *,
    imu: ImuSamples | None,
    calibration: CameraCalibration,
    biases: BiasBoard,
    max_frames: int | None,
    cpu_s: dict[str, float] | None = None,
) -> Iterator[TrackedFrame]:
    """Decoded and prepared (one thread ahead), then tracked images, in order, for the
    estimator.

    The first `max_frames` of `frames` are taken (None: all). With `imu`, the gyro
    rotation since the previous image seeds the tracking, less the bias `biases` gives
    for it.
    """
    previous_stamp: int | None = None
    sequence = 0
    # The decoding thread also makes the frontend image (grey, resized, CLAHE): the
    # tracking thread is the longest of the three.
    decoded = prefetch(
        _prepared(frames, frontend, max_frames=max_frames),
        name="slam-decode",
        cpu_s=cpu_s,
    )
    try:
        for frame, grey in decoded:
            rotation = None
            if previous_stamp is not None and imu is not None:
                bias = biases.bias_for(sequence)
                if bias is not None:
                    rotation = _gyro_rotation(
                        imu, calibration, previous_stamp, frame.stamp_ns, bias
                    )
            tracks = frontend.track(
                frame.stamp_ns, grey, cam_rotation_now_from_prev=rotation, prepared=True
            )
            previous_stamp = frame.stamp_ns
            sequence += 1
            yield TrackedFrame(frame, tracks, grey)
    finally:
        close = getattr(decoded, "close", None)
        if close is not None:
            close()


def _prepared(
    frames: Iterable[Frame], frontend: KltFrontend, *, max_frames: int | None
) -> Iterator[tuple[Frame, Image]]:
    """The frames to track (the first `max_frames`) with their frontend images."""
    for count, frame in enumerate(frames):
        if max_frames is not None and count >= max_frames:
            break
        yield frame, frontend.prepare(_pixels(frame))


def _pixels(frame: Frame) -> Image:
    """What the frontend makes its grey image of: a video frame's luma plane where it has
    one (no colour conversion), else the image."""
    luma = frame.luma
    return frame.image if luma is None else luma


THINNING_PROBE_FRAMES = 15


class RateThinning:
    """The images to use, as a recording's `keep` test: none closer than `min_step_ns` to
    the last one used (the `max_rate_hz` cap, `min_frame_step_ns`), and every k-th image
    of a recording at k or more times `min_rate_hz` (k whole; None: every image).

    The rate is the mean step of the first `THINNING_PROBE_FRAMES` + 1 stamps (only the
    cap thins those): a mean, so a camera that alternates 33 and 60 ms steps counts as
    the 19 fps it is; k allows 2 % (29.97 fps is twice 15 Hz). From then on an image is
    used when it is at least k - 1/2 mean steps (and the cap) after the last one used:
    stamp jitter does not drop a second one."""

    def __init__(self, min_rate_hz: float | None, *, min_step_ns: int = 0) -> None:
        if min_rate_hz is not None and not min_rate_hz > 0:
            raise InputError(f"min_rate_hz {min_rate_hz}: expected a positive rate (Hz), or none")
        self.min_rate_hz = min_rate_hz
        self.stride = 1
        """k, once the probe is over (1 until then, and for a slow recording)."""
        self._first: int | None = None
        self._seen = 0
        self._last_kept: int | None = None
        self._step_ns = min_step_ns

    def keep(self, stamp_ns: int) -> bool:
        """Whether to use the image of `stamp_ns` (asked once per image, in time order)."""
        use = self._last_kept is None or stamp_ns - self._last_kept >= self._step_ns
        if use:
            self._last_kept = stamp_ns
        self._seen += 1
        if self._first is None:
            self._first = stamp_ns
        elif (
            self.min_rate_hz is not None
            and self._seen == THINNING_PROBE_FRAMES + 1
            and stamp_ns > self._first
        ):
            mean_step_s = seconds_from_ns(stamp_ns - self._first) / THINNING_PROBE_FRAMES
            self.stride = max(int(1.02 / (mean_step_s * self.min_rate_hz)), 1)
            if self.stride > 1:
                stride_ns = ns_from_seconds((self.stride - 0.5) * mean_step_s)
                self._step_ns = max(self._step_ns, stride_ns)
        return use


def prefetch(
    items: Iterable[T],
    depth: int = 4,
    *,
    name: str = "slam-prefetch",
    cpu_s: dict[str, float] | None = None,
) -> Iterator[T]:
    """Iterate `items` in a background thread (named `name`), up to `depth` ahead.

    Image decoding (PNG or H.264) and the frontend's OpenCV calls release the GIL, so
    on two cores they overlap the work of the consuming thread instead of adding to it.
    An exception of the producer is raised here, at the item where it happened; closing
    the iterator early (or an exception in the consumer) stops the producer, closes
    `items` and waits for the thread to end. With `cpu_s`, the thread's CPU seconds are
    stored there under `name` when it ends.
    """
    handoff: queue.Queue[Any] = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def put(item: object) -> bool:
        while not stop.is_set():
            try:
                handoff.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        iterator = iter(items)
        try:
            for item in iterator:
                if not put(item):
                    return
            put(done)
        except BaseException as error:  # handed to the consumer, raised there
            put(_Failure(error))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()
            if cpu_s is not None:
                cpu_s[name] = time.thread_time()

    thread = threading.Thread(target=produce, name=name, daemon=True)
    thread.start()
    try:
        while True:
            item = handoff.get()
            if item is done:
                return
            if isinstance(item, _Failure):
                raise item.error
            yield item
    finally:
        stop.set()
        thread.join()


def keyframe_speeds_m_s(stamps_ns: IntArray, poses: FloatArray) -> FloatArray:
    """Speeds (m/s) between consecutive poses (N, 4, 4) at `stamps_ns` (int64 ns)."""
    stamps: IntArray = np.asarray(stamps_ns, dtype=np.int64)
    dt_s = seconds_from_ns(stamps[1:] - stamps[:-1])
    step_m = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    speeds: FloatArray = step_m / np.maximum(dt_s, 1e-9)
    return speeds


def _check_speed(result: SlamResult, max_speed_m_s: float, name: str) -> None:
    speeds = keyframe_speeds_m_s(result.keyframe_stamps_ns, result.keyframe_session_from_body)
    if len(speeds) and float(np.max(speeds)) > max_speed_m_s:
        worst = int(np.argmax(speeds))
        raise StageError(
            f"{name}: the trajectory diverged: {speeds[worst]:.1f} m/s between keyframes "
            f"{worst} and {worst + 1} (limit {max_speed_m_s:g} m/s); only "
            f"{result.stats['landmarks']} landmarks over {result.stats['keyframes']} keyframes "
            "held the IMU integration (scene too far or too poorly textured, or a wrong "
            "calibration guess)"
        )


def _no_image(frame: Frame) -> None:
    """A keyframe when `SlamOptions.keyframe_images` is off: nothing written."""


def _save_keyframe(folder: SlamFolder, frame: Frame) -> None:
    path = folder.keyframe_image(frame.stamp_ns)
    if frame.encoded_png is not None:
        path.write_bytes(frame.encoded_png)  # as recorded, byte for byte
        return
    image = frame.image
    if image.dtype == np.uint8:
        # (zlib-ng's level 1: the link thread's CPU 2.7 -> 1.7 s a minute of 960x540 video.)
        path.write_bytes(encode_png(image))
        return
    ok, data = cv2.imencode(".png", image)  # 16-bit images
    if not ok:
        raise StageError(f"cannot encode keyframe {frame.stamp_ns} as PNG")
    path.write_bytes(data.tobytes())


def min_frame_step_ns(max_rate_hz: float | None) -> int:
    """Images closer than this to the last one used are dropped (0: none are); a 10 %
    margin keeps every third image of a 30 fps video at 10 Hz despite stamp jitter."""
    if max_rate_hz is None:
        return 0
    if not max_rate_hz > 0:
        raise InputError(f"max_rate_hz {max_rate_hz}: expected a positive rate (Hz)")
    return round(0.9 * NS_PER_S / max_rate_hz)


def _write_result(
    folder: SlamFolder,
    result: SlamResult,
    calibration: CameraCalibration,
    noise: ImuNoise | None,
    *,
    stats: dict[str, object],
) -> None:
    folder.write_trajectory(Trajectory(result.frame_stamps_ns, result.session_from_body))
    folder.write_keyframes(Trajectory(result.keyframe_stamps_ns, result.keyframe_session_from_cam))
    folder.calib.mkdir()
    folder.write_camchain([calibration])
    if noise is not None:
        folder.write_imu_noise(noise)
    folder.map_ply.write_bytes(
        ply_bytes(PlyData(vertices=result.landmarks_s), comments=[LANDMARKS_PLY_COMMENT])
    )
    path_m = Trajectory(result.frame_stamps_ns, result.session_from_body).path_length_m()
    summary = {**stats, **result.stats, "path_length_m": path_m}
    # stats.json last: the folder's completeness marker.
    folder.write_stats(summary)
