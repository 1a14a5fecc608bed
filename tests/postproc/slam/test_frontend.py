"""The KLT frontend on images rendered from a textured wall with known poses."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from postproc.slam.frontend import FrontendOptions, KltFrontend, scale_for_width, track_ids_in_both
from sim.features import (
    DiverMotion,
    WallRenderer,
    default_camera,
    default_imu_from_cam,
    make_wall_texture,
)


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, np.ndarray, list[np.ndarray], WallRenderer]:
    camera = default_camera().scaled(2 / 3)  # recorded at 640 px, tracked at 480 px
    renderer = WallRenderer(camera, make_wall_texture(np.random.default_rng(7)))
    motion = DiverMotion()
    stamps = motion.start_ns + np.arange(20, dtype=np.int64) * 66_666_667
    world_from_cam = motion.world_from_body(stamps) @ default_imu_from_cam()
    images = [renderer.render(T) for T in world_from_cam]
    return stamps, world_from_cam, images, renderer


def _wall_point(T_W_C: np.ndarray, ray_c: np.ndarray, plane_y: float) -> np.ndarray:
    ray_w = T_W_C[:3, :3] @ ray_c
    s = (plane_y - T_W_C[1, 3]) / ray_w[1]
    point: np.ndarray = T_W_C[:3, 3] + s * ray_w
    return point


def test_tracks_follow_the_true_motion(rendered) -> None:
    stamps, world_from_cam, images, renderer = rendered
    frontend = KltFrontend(FrontendOptions(width_px=480), renderer.camera)
    assert frontend.image_size == (480, 270)
    assert frontend.focal_px == pytest.approx(225.0, rel=1e-3)
    frames = [frontend.track(int(s), im) for s, im in zip(stamps, images, strict=True)]
    counts = [len(f.track_ids) for f in frames]
    assert min(counts) >= 250
    assert max(counts) <= 400
    # Features that lived from the first to the last frame land where the geometry says.
    ia, ib = track_ids_in_both(frames[0], frames[-1])
    assert len(ia) >= 100
    plane_y = renderer.texture.plane_y_m
    errors = []
    for a, b in zip(ia, ib, strict=True):
        ray = np.append(frames[0].xy_normalised[a], 1.0)
        X = _wall_point(world_from_cam[0], ray, plane_y)
        T_C_W = np.linalg.inv(world_from_cam[-1])
        p = T_C_W[:3, :3] @ X + T_C_W[:3, 3]
        errors.append(
            np.linalg.norm(p[:2] / p[2] - frames[-1].xy_normalised[b]) * frontend.focal_px
        )
    # Sub-pixel tracking after 19 frames (1.3 s) of drift; measured median 0.15 px.
    assert np.median(errors) < 0.5
    assert np.percentile(errors, 95) < 2.0
    # Normalised and pixel coordinates agree with the scaled camera (to the
    # undistortion table's interpolation error, 2e-5 normalised = 0.005 px here).
    f = frames[5]
    np.testing.assert_allclose(
        frontend.camera.unproject(f.pixels)[:, :2], f.xy_normalised, atol=2e-5
    )


def test_rotation_prior_and_rejection(rendered) -> None:
    stamps, world_from_cam, images, renderer = rendered
    frontend = KltFrontend(FrontendOptions(width_px=480, clahe=False), renderer.camera)
    first = frontend.track(int(stamps[0]), images[0])
    # Skip 6 frames (0.4 s): a big jump. The true rotation seeds the flow.
    R_now_prev = world_from_cam[6][:3, :3].T @ world_from_cam[0][:3, :3]
    second = frontend.track(int(stamps[6]), images[6], cam_rotation_now_from_prev=R_now_prev)
    ia, _ = track_ids_in_both(first, second)
    assert len(ia) > 0.5 * len(first.track_ids)
    # A frame of noise: (almost) nothing survives the forward-backward and RANSAC checks.
    noise = np.random.default_rng(1).integers(0, 255, size=images[0].shape, dtype=np.uint8)
    third = frontend.track(int(stamps[7]), noise)
    ia, _ = track_ids_in_both(second, third)
    assert len(ia) < 0.1 * len(second.track_ids)
    assert frontend.lost_tracks + frontend.rejected_tracks > 0


def test_colour_input_and_full_width() -> None:
    camera = default_camera().scaled(1 / 3)
    assert scale_for_width(camera, 0) == 1.0
    assert scale_for_width(camera, camera.width) == 1.0
    assert scale_for_width(camera, 2 * camera.width) == 1.0  # never enlarged
    assert scale_for_width(camera, camera.width // 2) == pytest.approx(0.5, abs=0.01)
    renderer = WallRenderer(camera, make_wall_texture(np.random.default_rng(2)))
    grey = renderer.render(
        DiverMotion().world_from_body(np.array([DiverMotion().start_ns]))[0]
        @ default_imu_from_cam()
    )
    colour = np.dstack([grey, grey, grey])
    frontend = KltFrontend(FrontendOptions(width_px=0), camera)
    frame = frontend.track(0, colour)
    assert frame.image_size == (camera.width, camera.height)
    assert len(frame.track_ids) > 50
    # BGRA and 16-bit grey give the same image to the tracker.
    bgra = np.dstack([grey, grey, grey, np.full_like(grey, 255)])
    np.testing.assert_array_equal(frontend.prepare(bgra), frontend.prepare(colour))
    wide = grey.astype(np.uint16) * 257
    # prepare() takes 16-bit grey too, though its parameter is annotated as 8-bit.
    wide_image = cast("npt.NDArray[np.uint8]", wide)
    np.testing.assert_array_equal(frontend.prepare(wide_image), frontend.prepare(grey))


def test_undistort_table_matches_the_exact_model() -> None:
    from postproc.slam.frontend import _UndistortTable
    from sim.features import default_camera

    camera = default_camera()  # 960 px, barrel distortion k1 = -0.05
    table = _UndistortTable(camera)
    rng = np.random.default_rng(5)
    pixels = rng.uniform([-20.0, -20.0], [camera.width + 20.0, camera.height + 20.0], (2000, 2))
    exact = camera.unproject(pixels)[:, :2]
    looked_up = table.normalised(pixels)
    # Measured 1e-3 px at the corners (1 px is the feature noise); outside the image
    # the exact solve is used.
    assert np.max(np.abs(looked_up - exact)) * camera.fx < 3e-3
    assert table.normalised(np.zeros((0, 2))).shape == (0, 2)


def test_tracks_come_back_after_a_dark_drought(rendered) -> None:
    stamps, world_from_cam, images, renderer = rendered
    dark = np.full_like(images[0], 3)  # the light went out: nothing to track for 0.2 s

    def run(options: FrontendOptions) -> tuple[list, KltFrontend]:  # type: ignore[type-arg]
        frontend = KltFrontend(options, renderer.camera)
        frames = []
        for k, (stamp, image) in enumerate(zip(stamps[:14], images[:14], strict=True)):
            R_now_prev = world_from_cam[k][:3, :3].T @ world_from_cam[k - 1][:3, :3] if k else None
            frames.append(
                frontend.track(
                    int(stamp),
                    dark if 8 <= k <= 10 else image,
                    cam_rotation_now_from_prev=R_now_prev,
                )
            )
        return frames, frontend

    frames, frontend = run(FrontendOptions(width_px=480))
    assert max(len(f.track_ids) for f in frames[8:11]) < 40  # the drought
    ia, ib = track_ids_in_both(frames[7], frames[11])
    assert len(ia) > 0.5 * len(frames[7].track_ids)
    assert frontend.recovered_tracks >= len(ia)
    # The tracks brought back land where the geometry says (as in the test above).
    plane_y = renderer.texture.plane_y_m
    T_C_W = np.linalg.inv(world_from_cam[11])
    errors = []
    for a, b in zip(ia, ib, strict=True):
        X = _wall_point(world_from_cam[7], np.append(frames[7].xy_normalised[a], 1.0), plane_y)
        p = T_C_W[:3, :3] @ X + T_C_W[:3, 3]
        errors.append(
            np.linalg.norm(p[:2] / p[2] - frames[11].xy_normalised[b]) * frontend.focal_px
        )
    assert np.median(errors) < 0.5
    # Without the bridge every track after the drought is new.
    frames, _ = run(FrontendOptions(width_px=480, drought_min_tracks=0))
    ia, _ = track_ids_in_both(frames[7], frames[11])
    assert len(ia) < 10


def test_flat_cells_fill_from_weaker_corners() -> None:
    # A faint texture everywhere and one bright dot per grid cell: the dot sets the
    # cell's bar so high that the texture stays below it at the usual quality level.
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.standard_normal((270, 480)), (0, 0), 2.0)  # std 0.14
    image = np.clip(120 + 40 * texture, 0, 255).astype(np.uint8)  # +-6 grey levels
    for x in np.linspace(30, 450, 8).astype(int):
        for y in np.linspace(27, 243, 5).astype(int):
            cv2.circle(image, (int(x), int(y)), 2, 255, -1)
    camera = default_camera().scaled(480 / default_camera().width)
    counts = {}
    for factor in (1.0, 0.1):
        frontend = KltFrontend(
            FrontendOptions(width_px=0, clahe=False, weak_quality_factor=factor), camera
        )
        counts[factor] = len(frontend.track(0, image).track_ids)
    # Measured: 40 (the dots alone) and 400 (the budget, from the texture).
    assert counts[1.0] < 100
    assert counts[0.1] > 3 * counts[1.0]


def test_new_corners_wait_until_enough_features_are_missing(rendered) -> None:
    stamps, _, images, _ = rendered
    budget = 200
    refills_by_missing = {}
    for missing in (1, 8):
        frontend = KltFrontend(
            FrontendOptions(width_px=0, max_features=budget, replenish_missing=missing),
            default_camera().scaled(2 / 3),
        )
        refills = 0
        next_id = 0
        for stamp, image in zip(stamps, images, strict=True):
            frame = frontend.track(int(stamp), image)
            survivors = int(np.count_nonzero(frame.track_ids < next_id))
            if next_id and frontend._next_id > next_id:
                refills += 1
                # New corners only once `missing` of the budget are gone.
                assert survivors <= budget - missing
            elif next_id:
                assert survivors > budget - missing
            next_id = frontend._next_id
        refills_by_missing[missing] = refills
    # Some track is lost in most frames: refilled in most with 1, far fewer with 8.
    assert refills_by_missing[1] >= len(stamps) // 2
    assert 1 <= refills_by_missing[8] <= refills_by_missing[1] // 2


def test_normalised_coordinates_are_the_tables_of_the_pixels(rendered) -> None:
    """The frontend keeps each point's normalised coordinates from where it was tracked
    (or found) instead of undistorting every point again each frame: what it returns
    must still be the table's undistortion of the returned pixels, exactly, through
    tracking, new corners and a bridged drought."""
    stamps, world_from_cam, images, renderer = rendered
    frontend = KltFrontend(FrontendOptions(width_px=480), renderer.camera)
    noise = np.random.default_rng(3).integers(0, 255, size=images[0].shape, dtype=np.uint8)
    sequence = [*images[:8], noise, *images[8:12]]
    times = [*stamps[:8], stamps[8] - 1, *stamps[8:12]]
    poses = [*world_from_cam[:8], world_from_cam[7], *world_from_cam[8:12]]
    previous = None
    for stamp, image, pose in zip(times, sequence, poses, strict=True):
        rotation = None if previous is None else pose[:3, :3].T @ previous[:3, :3]
        frame = frontend.track(int(stamp), image, cam_rotation_now_from_prev=rotation)
        previous = pose
        np.testing.assert_array_equal(frame.xy_normalised, frontend._lut.normalised(frame.pixels))
    assert frontend.recovered_tracks > 0  # the drought bridge ran


def test_the_check_runs_on_klt_check_levels(rendered, monkeypatch) -> None:
    """The backward (checking) pass uses `klt_check_levels`, never more than the forward."""
    levels: list[int] = []
    real = cv2.calcOpticalFlowPyrLK

    def spy(*args, **kwargs):
        levels.append(kwargs["maxLevel"])
        return real(*args, **kwargs)

    # The frontend calls it through the cv2 module: patched there, for this test only.
    monkeypatch.setattr(cv2, "calcOpticalFlowPyrLK", spy)
    stamps, _, images, renderer = rendered
    for check, expected in ((1, [3, 1]), (5, [3, 3])):
        levels.clear()
        options = FrontendOptions(width_px=480, klt_levels=3, klt_check_levels=check)
        frontend = KltFrontend(options, renderer.camera)
        frontend.track(int(stamps[0]), images[0])
        frontend.track(int(stamps[1]), images[1])
        assert levels == expected


def test_the_window_is_smaller_only_when_the_gyro_seeds_the_flow(rendered, monkeypatch) -> None:
    """A gyro-seeded KLT uses `klt_window_px`, an unseeded one `klt_window_unseeded_px`
    (both passes of each), and the seeded small window lands where the unseeded large one
    does."""
    windows: list[tuple[int, int]] = []
    real = cv2.calcOpticalFlowPyrLK

    def spy(*args, **kwargs):
        windows.append(tuple(kwargs["winSize"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(cv2, "calcOpticalFlowPyrLK", spy)
    stamps, poses, images, renderer = rendered
    options = FrontendOptions(width_px=480, klt_window_px=9, klt_window_unseeded_px=17)
    unseeded = KltFrontend(options, renderer.camera)
    unseeded.track(int(stamps[0]), images[0])
    wide = unseeded.track(int(stamps[1]), images[1])
    assert windows == [(17, 17), (17, 17)]
    windows.clear()
    seeded = KltFrontend(options, renderer.camera)
    seeded.track(int(stamps[0]), images[0])
    rotation = poses[1][:3, :3].T @ poses[0][:3, :3]  # R_Cnow_Cprev
    frame = seeded.track(int(stamps[1]), images[1], cam_rotation_now_from_prev=rotation)
    assert windows == [(9, 9), (9, 9)]
    assert len(frame.track_ids) > 100
    shared, in_wide, in_seeded = np.intersect1d(
        wide.track_ids, frame.track_ids, return_indices=True
    )
    assert len(shared) > 0.9 * len(frame.track_ids)
    gaps = np.linalg.norm(wide.pixels[in_wide] - frame.pixels[in_seeded], axis=1)
    assert np.median(gaps) < 0.1
