"""The calibration stage: intrinsics, camera-IMU, two-rig sync; Kalibr YAML out.

Three entry points, each `run_*(options, inputs..., out_dir, *, overwrite=False) -> Path`:

- `run_camera`: AprilGrid views of a recording (session, EuRoC, image folder, video)
  -> `camchain.yaml` (Kalibr, one camera, `T_cam_imu` identity, shift 0),
  `camera_calibration.json` (fit, coverage, per-view errors), `coverage.png`.
- `run_imu`: a recording with camera and IMU plus its `camchain.yaml` ->
  `camchain-imucam.yaml` (Kalibr's name for the chain with the IMU: `T_cam_imu`
  rotation and `timeshift_cam_imu` estimated; the translation is kept from the input,
  which is the identity's zero when the input came from `run_camera`; a lever arm of a
  few centimetres is not observable from rotations), `camera_imu.json`, `camera_imu.png`.
- `run_rig`: two recordings of two rigidly joined rigs (each a camera with its own
  IMU, clocks not synchronised) and each rig's camchain -> `camchain-rig.yaml` (cam0
  and cam1 in the IMU frame of rig 0, cam1's time shift on rig 0's IMU clock; the
  translation between the rigs is not observable from gyros and is written as zero),
  `rig.json`.

The steps may share one folder (`shared.folders.CalibrationFolder` names the files).
Each follows the resume rule of every stage (`shared.folders.rebuild_files`): a result
of the same inputs and options is kept; another is refused unless `overwrite`, then
rebuilt under a temporary name and moved into place.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.calibrate.camera_imu import (
    CameraImuResult,
    GyroSignal,
    RotationIntervals,
    estimate_camera_imu,
)
from postproc.calibrate.frame_selection import (
    GridView,
    coverage_fraction,
    select_frames,
    sharpness,
)
from postproc.calibrate.intrinsics import (
    calibrate_intrinsics,
    reprojection_errors_px,
)
from postproc.calibrate.options import CalibrateOptions as CalibrateOptions
from postproc.calibrate.options import CameraCalibrationOptions as CameraCalibrationOptions
from postproc.calibrate.options import ImuCalibrationOptions as ImuCalibrationOptions
from postproc.calibrate.options import RigCalibrationOptions as RigCalibrationOptions
from postproc.calibrate.sources import open_frames, read_gyro
from postproc.calibrate.two_camera import estimate_rig_sync
from postproc.calibrate.visual_rotation import (
    rotation_from_features,
    target_from_cam,
)
from shared.calibration.aprilgrid import AprilGridTarget
from shared.calibration.aprilgrid_detection import DetectionOptions, detect_tags, group_by_target
from shared.calibration.kalibr import (
    CameraCalibration,
    read_camchain,
    read_target_yaml,
)
from shared.clock import NS_PER_S, seconds_from_ns
from shared.errors import InputError, StageError
from shared.folders import CalibrationFolder, rebuild_files, result_stamp
from shared.fsutil import write_text_atomic
from shared.geometry import so3_log
from shared.progress import progress

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


# ------------------------------------------------------------------------------ detection


def detect_grid(
    image: npt.NDArray[np.uint8],
    target: AprilGridTarget,
    *,
    index: int,
    stamp_ns: int,
    detection: DetectionOptions,
    min_tags: int,
) -> GridView | None:
    """The grid corners of one grey frame as a `GridView`, or None with fewer than
    `min_tags` tags of `target`."""
    observations, _foreign = group_by_target(detect_tags(image, detection), [target])
    if not observations or len(observations[0].tag_ids) < min_tags:
        return None
    observation = observations[0]
    return GridView(
        index=index,
        stamp_ns=int(stamp_ns),
        image_points_px=observation.image_points_px.reshape(-1, 2),
        object_points_m=observation.object_points_m.reshape(-1, 3),
        sharpness=sharpness(image),
    )


def _json(path: Path, document: dict[str, Any], overwrite: bool) -> None:
    write_text_atomic(path, json.dumps(document, indent=2) + "\n", overwrite=overwrite)


def _matrix(m: FloatArray) -> list[list[float]]:
    return [[float(v) for v in row] for row in m]


# ------------------------------------------------------------------------------ intrinsics


def collect_views(
    source_path: Path | str,
    target: AprilGridTarget,
    *,
    topic: str | None,
    max_rate_hz: float,
    detection: DetectionOptions,
    min_tags: int,
) -> tuple[list[GridView], tuple[int, int], int, str]:
    """Grid views of a recording: (views, image size (w, h), frames examined, topic)."""
    source = open_frames(source_path, topic=topic)
    views: list[GridView] = []
    size: tuple[int, int] | None = None
    examined = 0
    last_ns: int | None = None
    min_gap_ns = 0 if max_rate_hz <= 0 else round(NS_PER_S / max_rate_hz)
    frames = progress(source.frames(), total=source.frame_count(), desc="grid", unit="frame")
    for index, stamp_ns, image in frames:
        if size is None:
            size = (int(image.shape[1]), int(image.shape[0]))
        elif (image.shape[1], image.shape[0]) != size:
            raise InputError(
                f"{source_path}: frame {index} is {image.shape[1]}x{image.shape[0]}, "
                f"the first was {size[0]}x{size[1]} (one camera, one size)"
            )
        if last_ns is not None and stamp_ns - last_ns < min_gap_ns:
            continue
        last_ns = stamp_ns
        examined += 1
        view = detect_grid(
            image, target, index=index, stamp_ns=stamp_ns, detection=detection, min_tags=min_tags
        )
        if view is not None:
            views.append(view)
    if size is None:
        raise InputError(f"{source_path}: no frames")
    return views, size, examined, source.topic


def run_camera(
    options: CameraCalibrationOptions,
    source_path: Path | str,
    target_path: Path | str,
    out_dir: Path | str,
    *,
    overwrite: bool = False,
) -> Path:
    """Calibrate the intrinsics from the grid views of a recording; returns camchain.yaml.

    Raises InputError for unreadable inputs, StageError when too few usable views.
    """
    folder = CalibrationFolder(out_dir)
    stamp = result_stamp("calibrate camera", options, source=source_path, target=target_path)
    with rebuild_files(folder, folder.camchain, stamp, overwrite=overwrite) as work:
        if work is not None:
            _camera(options, Path(source_path), Path(target_path), work)
    return folder.camchain


def _camera(
    options: CameraCalibrationOptions, source_path: Path, target_path: Path, out: CalibrationFolder
) -> None:
    target = read_target_yaml(target_path)
    views, size, examined, topic = collect_views(
        source_path,
        target,
        topic=options.topic,
        max_rate_hz=options.max_candidate_rate_hz,
        detection=options.detection,
        min_tags=options.min_tags,
    )
    log.info("%d of %d frames examined show the grid", len(views), examined)
    chosen = select_frames(views, size, options.selection)
    if len(chosen) < options.intrinsics.min_views:
        raise StageError(
            f"{source_path}: {len(chosen)} usable view(s) of the grid in {examined} frames "
            f"examined ({len(views)} with >= {options.min_tags} tags; need "
            f"{options.intrinsics.min_views})"
        )
    selected = [views[i] for i in chosen]
    result = calibrate_intrinsics(selected, size, options.intrinsics)
    used = [selected[i] for i in result.views_used]
    coverage = coverage_fraction(used, size, options.coverage_cells)
    errors = [
        reprojection_errors_px(result.camera, pose, view)
        for pose, view in zip(result.cam_from_target, used, strict=True)
    ]
    from postproc.calibrate.plots import plot_coverage

    plot_coverage(
        out.coverage_plot,
        image_size=size,
        corners_px=[v.image_points_px for v in used],
        errors_px=errors,
        cells=options.coverage_cells,
        title=f"{options.intrinsics.model}: RMS {result.rms_px:.3f} px, "
        f"coverage {100 * coverage:.0f} % of {options.coverage_cells[0]}x"
        f"{options.coverage_cells[1]} cells",
    )
    camera = result.camera
    K = camera.intrinsic_matrix
    _json(
        out.camera_report,
        {
            "source": str(source_path),
            "target": str(target_path),
            "model": options.intrinsics.model,
            "resolution": list(size),
            "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "intrinsics_std_px": [float(v) for v in result.std_intrinsics],
            "distortion_coeffs": [float(v) for v in camera.opencv_distortion[:4]],
            "rms_px": result.rms_px,
            "coverage_fraction": coverage,
            "coverage_cells": list(options.coverage_cells),
            "frames_examined": examined,
            "frames_with_grid": len(views),
            "views_selected": len(selected),
            "views_used": len(used),
            "corners_used": result.corner_count,
            "views": [
                {
                    "frame_index": view.index,
                    "stamp_ns": view.stamp_ns,
                    "corners": view.corner_count,
                    "rms_px": float(rms),
                }
                for view, rms in zip(used, result.view_rms_px, strict=True)
            ],
            "views_dropped": [
                {"frame_index": selected[i].index, "stamp_ns": selected[i].stamp_ns}
                for i in result.views_dropped
            ],
        },
        False,
    )
    calibration = CameraCalibration(camera=camera, topic=topic, name="cam0")
    out.write_camchain([calibration])


# ------------------------------------------------------------------------------ camera-IMU


def camera_rotations(
    source_path: Path | str,
    calibration: CameraCalibration,
    target: AprilGridTarget | None,
    options: ImuCalibrationOptions,
) -> tuple[RotationIntervals, int, int]:
    """Relative rotations between consecutive frames: (intervals, from grid, from features)."""
    if options.frame_stride < 1:
        raise InputError(f"frame_stride {options.frame_stride}: expected an integer >= 1")
    topic = options.topic
    # A chain written from a session names its topic (/cam0/video, /cam0/image); Kalibr's
    # and EuRoC's "/cam0/image_raw" is no archive topic.
    if topic is None and calibration.topic.endswith(("/video", "/image")):
        topic = calibration.topic
    source = open_frames(source_path, topic=topic)
    camera = calibration.camera
    max_gap_ns = round(options.max_frame_gap_s * options.frame_stride * NS_PER_S)
    starts: list[int] = []
    ends: list[int] = []
    rotations: list[FloatArray] = []
    from_grid = from_features = 0
    previous: tuple[int, npt.NDArray[np.uint8], FloatArray | None] | None = None
    frames = progress(source.frames(), total=source.frame_count(), desc="rotations", unit="frame")
    for index, stamp_ns, image in frames:
        if index % options.frame_stride:
            continue
        if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
            raise InputError(
                f"{source_path}: frame {index} is {image.shape[1]}x{image.shape[0]}, the "
                f"calibration is for {camera.width}x{camera.height}"
            )
        pose = None
        if target is not None:
            view = detect_grid(
                image,
                target,
                index=index,
                stamp_ns=stamp_ns,
                detection=options.detection,
                min_tags=options.min_tags,
            )
            if view is not None:
                pose = target_from_cam(camera, view.object_points_m, view.image_points_px)
        if previous is not None and 0 < stamp_ns - previous[0] <= max_gap_ns:
            relative = None
            if pose is not None and previous[2] is not None:
                relative = previous[2][:3, :3].T @ pose[:3, :3]
                from_grid += 1
            elif options.use_features:
                relative = rotation_from_features(camera, previous[1], image, options.features)
                from_features += relative is not None
            if relative is not None:
                starts.append(previous[0])
                ends.append(stamp_ns)
                rotations.append(relative)
        previous = (stamp_ns, image, pose)
    intervals = RotationIntervals(
        np.array(starts, dtype=np.int64),
        np.array(ends, dtype=np.int64),
        np.array(rotations, dtype=np.float64).reshape(-1, 3, 3),
    )
    return intervals, from_grid, from_features


def _aligned_rates(
    intervals: RotationIntervals,
    stamps_ns: npt.NDArray[np.int64],
    gyro: FloatArray,
    result: CameraImuResult,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    origin = int(intervals.start_ns[0])
    signal = GyroSignal(stamps_ns, gyro, origin)
    start = seconds_from_ns(intervals.start_ns - origin)
    end = seconds_from_ns(intervals.end_ns - origin)
    camera_rates = so3_log(intervals.start_from_end) / (end - start)[:, None]
    shift = result.timeshift_cam_imu_s
    imu = signal.mean_rate(start + shift, end + shift) - result.gyro_bias_rad_s
    return 0.5 * (start + end), camera_rates, imu @ result.cam_from_imu_rotation.T


def run_imu(
    options: ImuCalibrationOptions,
    recording_path: Path | str,
    camchain_path: Path | str,
    target_path: Path | str | None,
    out_dir: Path | str,
    *,
    overwrite: bool = False,
) -> Path:
    """Estimate `T_cam_imu`'s rotation and `timeshift_cam_imu`; returns camchain-imucam.yaml.

    target_path: the AprilGrid YAML when the grid is in view (poses from it are far more
    accurate than from features); None: features only.
    """
    folder = CalibrationFolder(out_dir)
    stamp = result_stamp(
        "calibrate imu", options, recording=recording_path, camchain=camchain_path,
        target=target_path,
    )  # fmt: skip
    with rebuild_files(folder, folder.imu_camchain, stamp, overwrite=overwrite) as work:
        if work is not None:
            _imu(options, recording_path, camchain_path, target_path, work)
    return folder.imu_camchain


def _imu(
    options: ImuCalibrationOptions,
    recording_path: Path | str,
    camchain_path: Path | str,
    target_path: Path | str | None,
    out: CalibrationFolder,
) -> None:
    cameras = read_camchain(camchain_path)
    if not 0 <= options.camera_index < len(cameras):
        raise InputError(
            f"{camchain_path}: no camera {options.camera_index} (it has {len(cameras)})"
        )
    calibration = cameras[options.camera_index]
    target = read_target_yaml(target_path) if target_path is not None else None
    if target is None and not options.use_features:
        raise StageError("camera-IMU: no target and features disabled: no camera rotations")
    stamps_ns, gyro = read_gyro(recording_path, topic=options.imu_topic)
    intervals, from_grid, from_features = camera_rotations(
        recording_path, calibration, target, options
    )
    log.info(
        "%d frame pairs (%d from the grid, %d from features)",
        len(intervals),
        from_grid,
        from_features,
    )
    result = estimate_camera_imu(intervals, stamps_ns, gyro, options.estimate)
    old = calibration.cam_from_imu
    translation_kept = bool(np.linalg.norm(old[:3, 3]) > 0)
    cam_from_imu = np.eye(4)
    cam_from_imu[:3, :3] = result.cam_from_imu_rotation
    cam_from_imu[:3, 3] = old[:3, 3]
    calibration.cam_from_imu = cam_from_imu
    calibration.timeshift_cam_imu_s = result.timeshift_cam_imu_s
    times, camera_rates, imu_rates = _aligned_rates(intervals, stamps_ns, gyro, result)
    from postproc.calibrate.plots import plot_rates

    plot_rates(
        out.imu_plot,
        times_s=times,
        camera_rates=camera_rates,
        imu_rates=imu_rates,
        title=f"camera vs gyro after alignment: shift {1e3 * result.timeshift_cam_imu_s:.2f} ms, "
        f"residual {np.degrees(result.residual_rms_rad):.3f} deg RMS per frame pair",
    )
    _json(
        out.imu_report,
        {
            "recording": str(recording_path),
            "camchain": str(camchain_path),
            "camera": calibration.name,
            "cam_from_imu_rotation": _matrix(result.cam_from_imu_rotation),
            "timeshift_cam_imu_s": result.timeshift_cam_imu_s,
            "timeshift_convention": "t_imu = t_cam + timeshift_cam_imu_s (Kalibr)",
            "coarse_timeshift_s": result.coarse_timeshift_s,
            "rate_magnitude_correlation": result.peak_correlation,
            "gyro_bias_rad_s": [float(v) for v in result.gyro_bias_rad_s],
            "residual_rms_deg": float(np.degrees(result.residual_rms_rad)),
            "frame_pairs_used": result.intervals_used,
            "frame_pairs_total": result.intervals_total,
            "frame_pairs_from_grid": from_grid,
            "frame_pairs_from_features": from_features,
            "axis_excitation": result.axis_excitation,
            "explained_fraction": result.explained_fraction,
            "translation": (
                "kept from the input camchain (not estimated)"
                if translation_kept
                else "zero: not estimated (a lever arm is not observable from rotations)"
            ),
        },
        False,
    )
    out.write_imu_camchain(cameras)


# ------------------------------------------------------------------------------ two rigs


def run_rig(
    options: RigCalibrationOptions,
    recording0: Path | str,
    recording1: Path | str,
    camchain0: Path | str,
    camchain1: Path | str,
    out_dir: Path | str,
    *,
    overwrite: bool = False,
) -> Path:
    """Clock offset and rotation between two rigs; returns camchain-rig.yaml (cam0, cam1).

    Each camchain holds that rig's camera with its `T_cam_imu` and `timeshift_cam_imu`
    (from `run_imu`). In the output both cameras are expressed in rig 0's IMU frame and
    clock: cam1's `T_cam_imu` = cam1_from_imu1 * imu1_from_imu0 (translation zero: not
    observable), and its shift becomes shift1 - offset (t_imu0 = t_cam1 + shift).
    """
    folder = CalibrationFolder(out_dir)
    if Path(recording0).resolve() == Path(recording1).resolve() and (
        options.imu_topic0 == options.imu_topic1
    ):
        raise InputError(
            f"{recording0}: the same recording and IMU topic {options.imu_topic0!r} for both "
            "rigs (give two recordings or two IMU topics)"
        )
    stamp = result_stamp(
        "calibrate rig", options, recording0=recording0, recording1=recording1,
        camchain0=camchain0, camchain1=camchain1,
    )  # fmt: skip
    with rebuild_files(folder, folder.rig_camchain, stamp, overwrite=overwrite) as work:
        if work is not None:
            _rig(options, recording0, recording1, camchain0, camchain1, work)
    return folder.rig_camchain


def _rig(
    options: RigCalibrationOptions,
    recording0: Path | str,
    recording1: Path | str,
    camchain0: Path | str,
    camchain1: Path | str,
    out: CalibrationFolder,
) -> None:
    first = read_camchain(camchain0)[0]
    second = read_camchain(camchain1)[0]
    stamps0, gyro0 = read_gyro(recording0, topic=options.imu_topic0)
    stamps1, gyro1 = read_gyro(recording1, topic=options.imu_topic1)
    result = estimate_rig_sync(stamps0, gyro0, stamps1, gyro1, options.sync)
    imu1_from_imu0 = np.eye(4)
    imu1_from_imu0[:3, :3] = result.imu1_from_imu0
    cam1_from_imu0 = second.cam_from_imu @ imu1_from_imu0
    cam1_from_imu0[:3, 3] = 0.0
    first.name, second.name = "cam0", "cam1"
    second.cam_from_imu = cam1_from_imu0
    # t_imu1 = t_cam1 + shift1 and t_imu1 = t_imu0 + offset, so t_imu0 = t_cam1 + shift1 - offset.
    second.timeshift_cam_imu_s = second.timeshift_cam_imu_s - result.offset_s
    _json(
        out.rig_report,
        {
            "recording0": str(recording0),
            "recording1": str(recording1),
            "clock_offset_s": result.offset_s,
            "clock_offset_convention": "t_clock1 = t_clock0 + clock_offset_s (same instant)",
            "coarse_offset_s": result.coarse_offset_s,
            "rate_magnitude_correlation": result.peak_correlation,
            "imu1_from_imu0": _matrix(result.imu1_from_imu0),
            "bias_difference_rad_s": [float(v) for v in result.bias_difference_rad_s],
            "residual_rms_rad_s": result.residual_rms_rad_s,
            "overlap_s": result.overlap_s,
            "translation": "cam1 translation written as zero: not observable from gyros",
        },
        False,
    )
    out.write_rig_camchain([first, second])


# ------------------------------------------------------------------------------ pipeline
