"""Tracks built at known poses: keyframes registered and triangulated in keyframe order
continue the tracks of the keyframes before them, so a wall filmed on two passes gives
one track per point instead of fragments that track merging must join."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from postproc.sfm.database import KeyframeSet, colmap_camera, rigid3d_from_pose, write_database
from postproc.sfm.refine import RefineOptions, _load_cache, _Mapper, _pipeline_options
from shared.calibration.cameras import PinholeRadtan
from shared.geometry import invert_pose, make_pose

LAP_KEYFRAMES = 24
STEP_M = 0.25


def _two_passes() -> tuple[KeyframeSet, np.ndarray]:
    """Keyframes along a wall 3 m ahead, twice (the second pass 0.3 m higher); points."""
    rng = np.random.default_rng(4)
    poses = []
    for lap in range(2):
        for i in range(LAP_KEYFRAMES):
            poses.append(make_pose(np.eye(3), np.array([STEP_M * i, -0.3 * lap, 0.0])))
    n = len(poses)
    points = np.column_stack(
        [
            rng.uniform(-1.5, STEP_M * LAP_KEYFRAMES + 1.5, 3000),
            rng.uniform(-1.5, 1.2, 3000),
            rng.uniform(2.8, 3.2, 3000),
        ]
    )
    keyframes = KeyframeSet(
        names=[f"dive/{k:04d}.png" for k in range(n)],
        sources=[Path(f"{k:04d}.png") for k in range(n)],
        session=np.zeros(n, dtype=np.int64),
        camera=np.zeros(n, dtype=np.int64),
        stamps_ns=np.arange(n, dtype=np.int64) * 10**9,
        world_from_cam=np.stack(poses),
        placed=np.ones(n, dtype=bool),
        prior_sigma_m=np.full(n, 0.05),
    )
    return keyframes, points


@pytest.fixture(scope="module")
def two_passes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, KeyframeSet]:
    """A database of the two passes: keypoints are the points' projections (0.3 px noise);
    each keyframe is matched with its next three and with the keyframe at the same place
    on the other pass (a loop), with the true correspondences."""
    import pycolmap

    keyframes, points = _two_passes()
    model = PinholeRadtan(640, 480, 500.0, 500.0, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0)
    camera = colmap_camera(model, 1)
    path = tmp_path_factory.mktemp("tracks") / "database.db"
    ids = write_database(path, [model], keyframes)
    rng = np.random.default_rng(5)
    seen: list[dict[int, int]] = []  # per keyframe: point index -> keypoint index
    with pycolmap.Database.open(path) as db:
        for name, world_from_cam in zip(keyframes.names, keyframes.world_from_cam, strict=True):
            in_cam = (points - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]
            pixels = np.asarray(camera.img_from_cam(in_cam), dtype=np.float64)
            inside = np.flatnonzero(
                (in_cam[:, 2] > 0)
                & (pixels[:, 0] > 0)
                & (pixels[:, 0] < 640)
                & (pixels[:, 1] > 0)
                & (pixels[:, 1] < 480)
            )
            keypoints = pixels[inside] + rng.normal(0.0, 0.3, (inside.size, 2))
            db.write_keypoints(ids[name], keypoints.astype(np.float32))
            seen.append({int(p): k for k, p in enumerate(inside)})
        n = len(keyframes)
        pairs = [
            (a, a + d)
            for a in range(n)
            for d in (1, 2, 3)
            if a + d < n and a // LAP_KEYFRAMES == (a + d) // LAP_KEYFRAMES
        ]
        pairs += [(a, a + LAP_KEYFRAMES) for a in range(LAP_KEYFRAMES)]
        for a, b in pairs:
            common = sorted(seen[a].keys() & seen[b].keys())
            matches = np.array([[seen[a][p], seen[b][p]] for p in common], dtype=np.uint32)
            db.write_matches(ids[keyframes.names[a]], ids[keyframes.names[b]], matches)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            geometry.inlier_matches = matches
            db.write_two_view_geometry(ids[keyframes.names[a]], ids[keyframes.names[b]], geometry)
    return path, keyframes


def _all_registered_first(database: Path, keyframes: KeyframeSet, options: RefineOptions) -> int:
    """Points when every keyframe is registered before any is triangulated."""
    import pycolmap

    cache = _load_cache(database, options)
    reconstruction = pycolmap.Reconstruction()
    reconstruction.load(cache)
    observations = pycolmap.ObservationManager(reconstruction, cache.correspondence_graph)
    triangulator = pycolmap.IncrementalTriangulator(
        cache.correspondence_graph, reconstruction, observations
    )
    poses = dict(zip(keyframes.names, keyframes.world_from_cam, strict=True))
    for image in reconstruction.images.values():
        frame = reconstruction.frame(image.frame_id)
        frame.rig_from_world = rigid3d_from_pose(invert_pose(poses[image.name]))
        observations.register_frame(image.frame_id)
    tri_options = _pipeline_options(options, use_priors=True, rebuilt=True).get_triangulation()
    for image_id in sorted(reconstruction.reg_image_ids()):
        triangulator.triangulate_image(tri_options, image_id)
    return int(reconstruction.num_points3D())


def test_keyframe_order_gives_one_track_per_point(two_passes: tuple[Path, KeyframeSet]) -> None:
    database, keyframes = two_passes
    options = RefineOptions(num_threads=1)
    poses = dict(zip(keyframes.names, keyframes.world_from_cam, strict=True))
    mapper = _Mapper(database, poses, options, rebuilt=True)
    reconstruction = mapper.reconstruction
    assert reconstruction.num_reg_images() == len(keyframes)
    assert reconstruction.compute_num_observations() == mapper.triangulated
    in_order = reconstruction.num_points3D()
    # The second pass continued the first pass's tracks through the loop pairs.
    fragments = _all_registered_first(database, keyframes, options)
    assert in_order < 0.7 * fragments, (in_order, fragments)
    # Little is left to merge, and merging leaves the tracks about as they were.
    mapper.mapper.merge_tracks(mapper.tri_options)
    assert reconstruction.num_points3D() > 0.9 * in_order
    spans = [
        {e.image_id for e in reconstruction.point3D(p).track.elements}
        for p in reconstruction.point3D_ids()
    ]
    crossing = sum(1 for s in spans if min(s) <= LAP_KEYFRAMES < max(s))
    assert crossing > 0.5 * len(spans)  # most tracks hold both passes
    errors = [reconstruction.point3D(p).error for p in reconstruction.point3D_ids()]
    assert np.median(errors) < 1.0
    mapper.close()
