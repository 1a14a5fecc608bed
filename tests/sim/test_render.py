"""The renderer: exact rays through the distortion, range images, AprilGrid corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shared.calibration.aprilgrid import OPENCV_CORNER_ORDER
from shared.calibration.cameras import PinholeEquidistant, PinholeRadtan
from shared.geometry import look_at
from sim.render import Renderer, WaterModel
from sim.scene import WreckScene

RADTAN = PinholeRadtan(
    width=480, height=270, fx=250.0, fy=251.0, cx=243.0, cy=131.0, k1=-0.22, k2=0.05,
    p1=3e-4, p2=-2e-4,
)  # fmt: skip


def test_hit_points_reproject_to_their_pixels(coarse_scene: WreckScene) -> None:
    renderer = Renderer(coarse_scene, RADTAN, WaterModel.clear())
    pose = look_at(np.array([-2.0, 6.5, -13.0]), np.array([-3.0, 0.0, -14.0]))
    frame = renderer.render(pose)
    v, u = np.nonzero(np.isfinite(frame.depth_m))
    assert len(u) > 0.9 * RADTAN.width * RADTAN.height
    rays = RADTAN.unproject(np.column_stack((u, v)).astype(float))
    points_cam = rays * frame.depth_m[v, u, None]
    pixels = RADTAN.project(points_cam)
    err = np.abs(pixels - np.column_stack((u, v))).max()
    assert err < 1e-3, f"reprojection error {err} px"
    # Range is the Euclidean distance along the ray.
    np.testing.assert_allclose(frame.range_m[v, u], np.linalg.norm(points_cam, axis=1), rtol=1e-5)


def test_range_to_the_hull_side_matches_the_plane(coarse_scene: WreckScene) -> None:
    # Looking straight at the starboard side of the fore hull (the plane y = 3.5) from 2 m.
    renderer = Renderer(coarse_scene, RADTAN, WaterModel.clear())
    pose = look_at(np.array([4.0, 5.5, -14.5]), np.array([4.0, 3.5, -14.5]))
    frame = renderer.render(pose)
    centre = frame.depth_m[RADTAN.height // 2 - 10 : RADTAN.height // 2 + 10, 200:280]
    np.testing.assert_allclose(centre, 2.0, atol=2e-5)
    assert np.all(frame.face[RADTAN.height // 2, 200:280] == 6 * 3 + 2 * 1 + 1)


def test_equidistant_camera_renders_without_invalid_rays(coarse_scene: WreckScene) -> None:
    fisheye = PinholeEquidistant(
        width=96, height=64, fx=40.0, fy=40.0, cx=47.5, cy=31.5, k1=0.02, k2=-0.01, k3=0.0, k4=0.0
    )
    frame = Renderer(coarse_scene, fisheye).render(
        look_at(np.array([4.0, 5.5, -14.5]), np.array([4.0, 3.5, -14.5])),
        rng=np.random.default_rng(0),
    )
    assert frame.image_rgb.shape == (64, 96, 3)
    assert np.isfinite(frame.depth_m).mean() > 0.95


@pytest.mark.parametrize("target_index", [0, 1])
def test_rendered_aprilgrid_corners_are_where_they_project(
    coarse_scene: WreckScene, target_index: int
) -> None:
    placement = coarse_scene.targets[target_index]
    target = placement.target
    width_m, height_m = target.extent_m
    centre_t = np.array([width_m / 2, height_m / 2, 0.0, 1.0])
    centre_w = (placement.world_from_target @ centre_t)[:3]
    normal_w = placement.world_from_target[:3, 2]
    # 0.6 m in front (code cells of about 4 px), a little off-axis so the view is oblique.
    eye = centre_w + 0.6 * normal_w + np.array([0.2, 0.0, 0.1])
    pose = look_at(eye, centre_w)
    renderer = Renderer(coarse_scene, RADTAN, WaterModel.clear())
    gray = cv2.cvtColor(renderer.render(pose).image_rgb, cv2.COLOR_RGB2GRAY)

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    params = cv2.aruco.DetectorParameters()
    params.markerBorderBits = 2
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(gray)
    assert ids is not None
    found = {int(i) for i in ids.ravel()}
    expected = set(target.tag_ids())
    # No false ids; aruco may miss a tag squeezed by the distortion near the image edge.
    assert found <= expected and len(found) >= 0.9 * len(expected), f"detected {sorted(found)}"

    truth = target.corner_points()
    cam_from_world = np.linalg.inv(pose)
    errors = []
    for tag_corners, tag_id in zip(corners, ids.ravel(), strict=True):
        refined = cv2.cornerSubPix(
            gray, tag_corners.reshape(-1, 1, 2).astype(np.float32), (4, 4), (-1, -1),
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4),
        ).reshape(4, 2)  # fmt: skip
        kalibr_order = refined[list(OPENCV_CORNER_ORDER)]
        points_t = np.column_stack((truth[int(tag_id)], np.ones(4)))
        points_c = (cam_from_world @ placement.world_from_target @ points_t.T).T[:, :3]
        errors.append(np.linalg.norm(kalibr_order - RADTAN.project(points_c), axis=1))
    err = np.concatenate(errors)
    print(f"target {placement.name}: {len(err)} corners, max {err.max():.3f} px, "
          f"mean {err.mean():.3f} px")  # fmt: skip
    assert err.max() < 0.5


def test_water_darkens_and_tints_with_range(coarse_scene: WreckScene) -> None:
    near = look_at(np.array([4.0, 4.5, -14.5]), np.array([4.0, 3.5, -14.5]))
    far = look_at(np.array([4.0, 9.5, -14.5]), np.array([4.0, 3.5, -14.5]))
    renderer = Renderer(coarse_scene, RADTAN)
    a = renderer.render(near).image_rgb[120:150, 220:260].reshape(-1, 3).mean(axis=0)
    b = renderer.render(far).image_rgb[120:150, 220:260].reshape(-1, 3).mean(axis=0)
    # Red is absorbed fastest: the red share drops with range.
    assert b[0] / b.sum() < a[0] / a.sum()


def test_noise_depends_only_on_the_rng(coarse_scene: WreckScene) -> None:
    renderer = Renderer(coarse_scene, RADTAN)
    pose = look_at(np.array([4.0, 5.5, -14.5]), np.array([4.0, 3.5, -14.5]))
    a = renderer.render(pose, rng=np.random.default_rng(5)).image_rgb
    b = renderer.render(pose, rng=np.random.default_rng(5)).image_rgb
    c = renderer.render(pose, rng=np.random.default_rng(6)).image_rgb
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_board_without_supersampling_shows_the_printed_grid(coarse_scene: WreckScene) -> None:
    placement = coarse_scene.targets[0]
    width_m, height_m = placement.target.extent_m
    centre_w = (placement.world_from_target @ np.array([width_m / 2, height_m / 2, 0.0, 1.0]))[:3]
    pose = look_at(centre_w + 0.6 * placement.world_from_target[:3, 2], centre_w)
    renderer = Renderer(coarse_scene, RADTAN, WaterModel.clear(), target_supersampling=1)
    frame = renderer.render(pose)
    board = frame.face == coarse_scene.seafloor_face + 1
    gray = frame.image_rgb[..., 1][board]
    # White paper and black ink, both present in quantity.
    assert (gray > 200).mean() > 0.3 and (gray < 60).mean() > 0.15
