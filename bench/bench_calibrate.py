"""Calibration accuracy over several seeds: intrinsics, camera-IMU, two-rig sync, real photos.

Run: .venv/bin/python bench/bench_calibrate.py [--seeds 3] [--quick]

1. Intrinsics from rendered AprilGrid views (sim renderer, 6x6 grid of 88 mm
   tags, 1.5 DN sensor noise): pinhole-radtan at 640x480 (20 views) and
   pinhole-equidistant at 640x480 (14 views); relative errors of fx, fy, cx, cy and the
   RMS reprojection error. Target: < 0.5 %.
2. Camera-IMU rotation and time shift: (a) from noisy camera orientations (1 mrad per
   axis per frame, 6 s at 30 fps, 200 Hz IMU with Kalibr noise, shifts up to 0.3 s);
   (b) from a rendered 4 s sweep at 320x240 with grid poses and (c) with features only.
   Target: rotation < 0.5 deg, shift < 2 ms.
3. Two rigs: clock offset and rotation from two gyros (200 Hz and 197 Hz, 18 s
   overlap). Target: offset < 2 ms, rotation < 0.5 deg.
4. The two real AprilGrid photos (../shared/data/aprilgrid): focal length with the
   principal point fixed, fx = fy and no distortion; each photo alone and both.
5. The real GoPro clips (../shared/data/gopro), imported with field.gopro: camera-IMU
   from features only with the importer's guessed intrinsics. No truth: the importer's
   body frame is camera-aligned, so a rotation near the identity is what to expect; a
   refusal (stabilised video, too little rotation) is a valid outcome.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from postproc.calibrate.camera_imu import (  # noqa: E402
    CameraImuResult,
    RotationIntervals,
    estimate_camera_imu,
    intervals_from_orientations,
)
from postproc.calibrate.frame_selection import (  # noqa: E402
    FrameSelectionOptions,
    GridView,
    select_frames,
)
from postproc.calibrate.intrinsics import (  # noqa: E402
    CameraModelName,
    IntrinsicsOptions,
    calibrate_intrinsics,
)
from postproc.calibrate.stage import detect_grid  # noqa: E402
from postproc.calibrate.two_camera import estimate_rig_sync  # noqa: E402
from postproc.calibrate.visual_rotation import (  # noqa: E402
    rotation_from_features,
    target_from_cam,
)
from shared.calibration.aprilgrid import AprilGridTarget  # noqa: E402
from shared.calibration.aprilgrid_detection import DetectionOptions  # noqa: E402
from shared.calibration.cameras import CameraModel  # noqa: E402
from shared.geometry import rotation_angle_rad, so3_exp  # noqa: E402
from sim.calibration import (  # noqa: E402
    TARGET,
    Recording,
    board_views,
    equidistant_camera,
    radtan_camera,
    recording,
    two_gyros,
)


def _views(images: Sequence[npt.NDArray[np.uint8]]) -> list[GridView]:
    views = []
    for index, image in enumerate(images):
        view = detect_grid(
            image, TARGET, index=index, stamp_ns=index, detection=DetectionOptions(), min_tags=4
        )
        if view is not None:
            views.append(view)
    return views


def bench_intrinsics(seeds: list[int], quick: bool) -> None:
    print("== 1. intrinsics from rendered views (relative error %, RMS px)")
    cases: list[tuple[CameraModelName, Callable[[int, int], CameraModel], int, tuple[float, float]]]
    cases = [
        ("pinhole-radtan", radtan_camera, 20, (0.45, 0.9)),
        ("pinhole-equidistant", equidistant_camera, 14, (0.28, 0.5)),
    ]
    size = (320, 240) if quick else (640, 480)
    for model, make_camera, count, distance in cases:
        worst = 0.0
        for seed in seeds:
            camera = make_camera(*size)
            start = time.perf_counter()
            images, _ = board_views(camera, count, seed=seed, distance_m=distance)
            render_s = time.perf_counter() - start
            views = _views(images)
            chosen = select_frames(views, size, FrameSelectionOptions())
            start = time.perf_counter()
            result = calibrate_intrinsics(
                [views[i] for i in chosen], size, IntrinsicsOptions(model=model)
            )
            fit_s = time.perf_counter() - start
            errors = [
                100 * (getattr(result.camera, k) - getattr(camera, k)) / getattr(camera, k)
                for k in ("fx", "fy", "cx", "cy")
            ]
            worst = max(worst, *map(abs, errors))
            print(
                f"  {model:20s} {size[0]}x{size[1]} seed {seed}: views {len(chosen)}/{count}  "
                f"fx {errors[0]:+.3f}  fy {errors[1]:+.3f}  cx {errors[2]:+.3f}  "
                f"cy {errors[3]:+.3f} %  RMS {result.rms_px:.3f} px  "
                f"(render {render_s:.1f} s, fit {fit_s:.2f} s)"
            )
        print(f"  {model}: worst |error| {worst:.3f} % (target < 0.5 %)")


def _camera_imu_errors(
    rec: Recording, intervals: RotationIntervals
) -> tuple[float, float, CameraImuResult]:
    result = estimate_camera_imu(intervals, rec.imu_stamps_ns, rec.gyro_rad_s)
    rotation = float(
        np.degrees(rotation_angle_rad(result.cam_from_imu_rotation @ rec.cam_from_imu[:3, :3].T))
    )
    shift_ms = 1e3 * (result.timeshift_cam_imu_s - rec.timeshift_cam_imu_s)
    return rotation, shift_ms, result


def bench_camera_imu(seeds: list[int], quick: bool) -> None:
    print("== 2a. camera-IMU from noisy orientations (1 mrad/axis/frame, 6 s)")
    rows = []
    for seed in seeds:
        for shift in (0.0237, -0.1412, 0.3):
            rec = recording(seed=seed, duration_s=6.0, timeshift_cam_imu_s=shift, render=False)
            rng = np.random.default_rng(seed)
            noisy = rec.world_from_cam[:, :3, :3] @ so3_exp(
                rng.normal(0, 1e-3, (len(rec.world_from_cam), 3))
            )
            intervals = intervals_from_orientations(
                rec.frame_stamps_ns, noisy, max_gap_ns=50_000_000
            )
            rotation, shift_ms, result = _camera_imu_errors(rec, intervals)
            rows.append((rotation, abs(shift_ms)))
            print(
                f"  seed {seed} shift {1e3 * shift:+7.1f} ms: rotation {rotation:.3f} deg, "
                f"shift {shift_ms:+.3f} ms, residual {np.degrees(result.residual_rms_rad):.3f} "
                f"deg, correlation {result.peak_correlation:.3f}"
            )
    worst = np.max(rows, axis=0)
    print(f"  worst: rotation {worst[0]:.3f} deg, |shift| {worst[1]:.3f} ms")
    print("== 2b/c. camera-IMU from a rendered 4 s sweep (320x240, 30 fps)")
    for seed in seeds[: 1 if quick else len(seeds)]:
        rec = recording(seed=seed + 10, duration_s=4.0, camera=radtan_camera(320, 240))
        poses = []
        for image in rec.images:
            views = _views([image])
            poses.append(
                target_from_cam(rec.camera, views[0].object_points_m, views[0].image_points_px)
                if views
                else None
            )
        starts, ends, grid, features = [], [], [], []
        for k in range(len(rec.images) - 1):
            pose, following = poses[k], poses[k + 1]
            if pose is not None and following is not None:
                starts.append(rec.frame_stamps_ns[k])
                ends.append(rec.frame_stamps_ns[k + 1])
                grid.append(pose[:3, :3].T @ following[:3, :3])
        f_starts, f_ends = [], []
        for k in range(len(rec.images) - 1):
            relative = rotation_from_features(rec.camera, rec.images[k], rec.images[k + 1])
            if relative is not None:
                f_starts.append(rec.frame_stamps_ns[k])
                f_ends.append(rec.frame_stamps_ns[k + 1])
                features.append(relative)
        for name, s, e, rotations in (
            ("grid poses", starts, ends, grid),
            ("features", f_starts, f_ends, features),
        ):
            intervals = RotationIntervals(
                np.array(s, np.int64), np.array(e, np.int64), np.array(rotations)
            )
            rotation, shift_ms, result = _camera_imu_errors(rec, intervals)
            print(
                f"  seed {seed + 10} {name:10s}: pairs {result.intervals_used}/"
                f"{result.intervals_total}, rotation {rotation:.3f} deg, shift {shift_ms:+.3f} ms"
            )


def bench_rig(seeds: list[int]) -> None:
    print("== 3. two rigs from their gyros (18 s overlap)")
    worst_offset = worst_rotation = 0.0
    for seed in seeds:
        for offset in (3.1234567, -17.25):
            stamps0, gyro0, stamps1, gyro1, truth = two_gyros(seed, offset)
            start = time.perf_counter()
            result = estimate_rig_sync(stamps0, gyro0, stamps1, gyro1)
            elapsed = time.perf_counter() - start
            offset_ms = 1e3 * (result.offset_s - offset)
            rotation = np.degrees(rotation_angle_rad(result.imu1_from_imu0 @ truth.T))
            worst_offset = max(worst_offset, abs(offset_ms))
            worst_rotation = max(worst_rotation, rotation)
            print(
                f"  seed {seed} offset {offset:+9.4f} s: error {offset_ms:+.4f} ms, rotation "
                f"{rotation:.4f} deg ({elapsed:.2f} s)"
            )
    print(f"  worst: |offset| {worst_offset:.4f} ms, rotation {worst_rotation:.4f} deg")


def _fx(camera: CameraModel) -> float:
    return float(camera.intrinsic_matrix[0, 0])


def bench_photos() -> None:
    import cv2

    print("== 4. real photos (../shared/data/aprilgrid): fixed pp, fx = fy, no distortion")
    target = AprilGridTarget(tag_rows=6, tag_cols=6, tag_size_m=0.088, tag_spacing_ratio=0.3)
    folder = REPO.parent / "shared" / "data" / "aprilgrid"
    views = []
    size = (0, 0)
    for index, name in enumerate(("000.jpg", "001.jpg")):
        read = cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
        if read is None:
            print(f"  {name}: cannot read")
            return
        image = np.asarray(read, np.uint8)
        size = (image.shape[1], image.shape[0])
        view = detect_grid(
            image, target, index=index, stamp_ns=index, detection=DetectionOptions(), min_tags=4
        )
        if view is None:
            print(f"  {name}: no grid found")
            return
        views.append(view)
    simple = IntrinsicsOptions(
        fix_principal_point=True, fix_aspect_ratio=True, zero_distortion=True, min_views=1
    )
    for label, subset in (("000.jpg", views[:1]), ("001.jpg", views[1:]), ("both", views)):
        result = calibrate_intrinsics(subset, size, simple)
        sigma = result.std_intrinsics[1]
        print(
            f"  {label:8s}: f = {_fx(result.camera):.1f} px (1-sigma {sigma:.1f}),"
            f" RMS {result.rms_px:.2f} px, {result.corner_count} corners, image {size[0]}x{size[1]}"
        )
    with_distortion = calibrate_intrinsics(
        views, size, IntrinsicsOptions(fix_principal_point=True, fix_aspect_ratio=True, min_views=1)
    )
    d = with_distortion.camera.opencv_distortion
    print(
        f"  both, + radtan: f = {_fx(with_distortion.camera):.1f} px, k1 {d[0]:+.3f} k2 {d[1]:+.3f}"
        f", RMS {with_distortion.rms_px:.2f} px (4 more parameters from 2 views: not trusted)"
    )


def bench_gopro() -> None:
    import tempfile

    from field.gopro.importer import ImportOptions, import_recording
    from postproc.calibrate.stage import ImuCalibrationOptions, run_imu
    from shared.errors import StageError
    from shared.folders import CalibrationFolder, SessionFolder

    print("== 5. real GoPro clips: camera-IMU from features (guessed intrinsics)")
    folder = REPO.parent / "shared" / "data" / "gopro"
    with tempfile.TemporaryDirectory() as tmp:
        for clip in sorted(folder.glob("*.mp4")):
            session = SessionFolder(Path(tmp) / clip.stem)
            out = CalibrationFolder(session.path / "out")
            import_recording(ImportOptions(), [clip], session.path)
            start = time.perf_counter()
            try:
                run_imu(ImuCalibrationOptions(), session.path, session.camchain, None, out.path)
            except StageError as error:
                print(f"  {clip.name}: refused: {error}")
                continue
            report = out.read_json(out.imu_report)
            rotation = np.array(report["cam_from_imu_rotation"])
            print(
                f"  {clip.name}: {np.degrees(rotation_angle_rad(rotation)):.2f} deg from the "
                f"identity, shift {1e3 * report['timeshift_cam_imu_s']:+.1f} ms, correlation "
                f"{report['rate_magnitude_correlation']:.2f}, explained "
                f"{report['explained_fraction']:.2f}, pairs {report['frame_pairs_used']}/"
                f"{report['frame_pairs_total']} ({time.perf_counter() - start:.1f} s)"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="smaller images, one sweep")
    args = parser.parse_args()
    seeds = list(range(args.seeds))
    start = time.perf_counter()
    bench_photos()
    bench_gopro()
    bench_rig(seeds)
    bench_camera_imu(seeds, args.quick)
    bench_intrinsics(seeds, args.quick)
    print(f"total {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
