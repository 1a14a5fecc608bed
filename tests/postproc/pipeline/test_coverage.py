"""Coverage math on a synthetic seabed with known gaps: a strip the cameras never flew
over, and a hole in the mesh itself."""

from __future__ import annotations

import numpy as np
import pytest

from postproc.pipeline.coverage import (
    CoverageOptions,
    KeyframeViews,
    coverage_map,
    nearest_target,
    observe,
    score_samples,
    surface_from_mesh,
)
from shared.calibration.cameras import PinholeRadtan

SEABED_Z = -20.0
# Flown over: x 0..20, y 0..10, except this rectangle (x0, x1, y0, y1).
SKIPPED = (12.0, 16.0, 2.0, 7.0)
# Cut out of the mesh.
HOLE = (4.0, 6.0, 3.0, 5.0)


def seabed(step_m: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """A flat grid mesh over x 0..20, y 0..10 at SEABED_Z without the HOLE's faces."""
    xs = np.arange(0.0, 20.0 + 1e-9, step_m)
    ys = np.arange(0.0, 10.0 + 1e-9, step_m)
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, SEABED_Z)])
    cols = len(xs)
    faces = []
    for r in range(len(ys) - 1):
        for c in range(cols - 1):
            cx, cy = xs[c] + step_m / 2, ys[r] + step_m / 2
            if HOLE[0] < cx < HOLE[1] and HOLE[2] < cy < HOLE[3]:
                continue
            a, b, d, e = r * cols + c, r * cols + c + 1, (r + 1) * cols + c, (r + 1) * cols + c + 1
            faces += [[a, b, e], [a, e, d]]
    return vertices, np.array(faces)


def down_looking(x: float, y: float, z: float, tilt_deg: float) -> np.ndarray:
    """T_W_C of a camera at (x, y, z) looking down, tilted about x by `tilt_deg`."""
    t = np.deg2rad(tilt_deg)
    # Camera z (forward) down, x along world x, y = z cross x.
    forward = np.array([0.0, np.sin(t), -np.cos(t)])
    right = np.array([1.0, 0.0, 0.0])
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = [x, y, z]
    return pose


def survey() -> KeyframeViews:
    """Lawnmower lines 1 m apart, 2.5 m above the seabed, a keyframe every 0.5 m,
    alternately tilted +-15 deg (parallax), none over SKIPPED."""
    poses = []
    for k, y in enumerate(np.arange(0.0, 10.01, 1.0)):
        for j, x in enumerate(np.arange(0.0, 20.01, 0.5)):
            if SKIPPED[0] <= x <= SKIPPED[1] and SKIPPED[2] <= y <= SKIPPED[3]:
                continue
            poses.append(down_looking(x, y, SEABED_Z + 2.5, 15.0 if (j + k) % 2 else -15.0))
    camera = PinholeRadtan(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5)
    return KeyframeViews(name="s1", world_from_cam=np.array(poses), camera=camera)


@pytest.fixture(scope="module")
def top_map():
    vertices, faces = seabed()
    surface = surface_from_mesh(vertices, faces)
    options = CoverageOptions(cell_m=0.25)
    obs = observe(surface, [survey()], options, occluder=(vertices, faces))
    return surface, obs, coverage_map(surface, obs, "top", options)


def test_the_skipped_strip_is_the_largest_gap(top_map) -> None:
    _, obs, cmap = top_map
    assert obs.views.max() >= 3  # the flown area is seen by several keyframes
    gaps = cmap.gaps
    assert len(gaps) >= 2
    largest = gaps[0]
    # Cameras beside the strip see about 0.8 m into it (half the footprint of a 0.5 rad
    # wide view at 2.5 m, plus the tilt): the gap is the strip shrunk by that much.
    cx, cy = (SKIPPED[0] + SKIPPED[1]) / 2, (SKIPPED[2] + SKIPPED[3]) / 2
    assert largest.centre_m[:2] == pytest.approx([cx, cy], abs=0.5)
    assert largest.centre_m[2] == pytest.approx(SEABED_Z, abs=1e-6)
    inner = (SKIPPED[1] - SKIPPED[0] - 2.4) * (SKIPPED[3] - SKIPPED[2] - 2.4)
    outer = (SKIPPED[1] - SKIPPED[0] + 1.0) * (SKIPPED[3] - SKIPPED[2] + 1.0)
    assert inner < largest.area_m2 < outer
    assert largest.no_surface_m2 == 0.0  # the seabed is there, it was just not seen
    # Far inside the strip nothing saw the seabed; well inside the survey it is good.
    row = int((cy - cmap.origin_v_m) / cmap.cell_m)
    assert cmap.score[row, int((cx - cmap.origin_u_m) / cmap.cell_m)] == 0.0
    assert cmap.score[row, int((2.0 - cmap.origin_u_m) / cmap.cell_m)] > 0.9


def test_the_hole_in_the_mesh_is_a_gap_with_no_surface(top_map) -> None:
    _, _, cmap = top_map
    hole = [g for g in cmap.gaps if g.no_surface_m2 > 0]
    assert len(hole) == 1
    area = (HOLE[1] - HOLE[0]) * (HOLE[3] - HOLE[2])
    assert hole[0].no_surface_m2 == pytest.approx(area, rel=0.15)
    assert hole[0].centre_m[:2] == pytest.approx([5.0, 4.0], abs=0.2)
    # Gaps are listed largest first.
    areas = [g.area_m2 for g in cmap.gaps]
    assert areas == sorted(areas, reverse=True)


def test_occlusion_hides_what_is_under_a_plate() -> None:
    """A plate 1 m above part of the seabed: with the z-buffer the seabed under it is
    unseen from above; without, it would count as seen."""
    vertices, faces = seabed(step_m=0.5)
    plate_v = np.array([[8.0, 3.0, -19.0], [12.0, 3.0, -19.0], [12.0, 7.0, -19.0],
                        [8.0, 7.0, -19.0]])  # fmt: skip
    all_v = np.vstack([vertices, plate_v])
    n = len(vertices)
    all_f = np.vstack([faces, [[n, n + 1, n + 2], [n, n + 2, n + 3]]])
    surface = surface_from_mesh(vertices, faces)
    under = (
        (surface.points_m[:, 0] > 9.5)
        & (surface.points_m[:, 0] < 10.5)
        & (surface.points_m[:, 1] > 4.5)
        & (surface.points_m[:, 1] < 5.5)
    )
    options = CoverageOptions()
    hidden = observe(surface, [survey()], options, occluder=(all_v, all_f))
    open_view = observe(surface, [survey()], options, occluder=None)
    assert under.any()
    assert np.all(hidden.views[under] == 0)
    assert np.all(open_view.views[under] >= 3)


def test_score_factors() -> None:
    options = CoverageOptions(min_views=3, min_spread_deg=15.0, good_range_m=3.0, max_range_m=6.0)
    score = score_samples(
        np.array([0, 1, 3, 6, 3]),
        np.array([0.0, 0.0, 30.0, 7.5, 30.0]),
        np.array([np.inf, 2.0, 2.0, 2.0, 4.5]),
        options,
    )
    assert score == pytest.approx([0.0, 0.0, 1.0, 0.5, 0.5])


def test_nearest_target() -> None:
    a, b = np.eye(4), np.eye(4)
    b[:3, 3] = [10.0, 0.0, -20.0]
    found = nearest_target(np.array([9.0, 1.0, -20.0]), {"a": a, "b": b})
    assert found is not None and found.target == "b"
    assert found.offset_m == pytest.approx([-1.0, 1.0, 0.0])
    assert nearest_target(np.zeros(3), {}) is None


def test_sessions_aggregate_to_the_merged_coverage() -> None:
    """Two halves of the survey as two sessions: together they see what the whole does."""
    from postproc.pipeline.coverage import aggregate, sightings

    vertices, faces = seabed(step_m=0.5)
    surface = surface_from_mesh(vertices, faces)
    options = CoverageOptions()
    whole = survey()
    half = len(whole.world_from_cam) // 2
    first = KeyframeViews(name="a", world_from_cam=whole.world_from_cam[:half],
                          camera=whole.camera)  # fmt: skip
    second = KeyframeViews(name="b", world_from_cam=whole.world_from_cam[half:],
                           camera=whole.camera)  # fmt: skip
    seen = [sightings(surface, s, options) for s in (first, second)]
    merged = aggregate(len(surface.points_m), seen, options)
    alone = [aggregate(len(surface.points_m), [s], options) for s in seen]
    reference = observe(surface, [whole], options)
    assert np.array_equal(merged.views, reference.views)
    assert np.array_equal(merged.views, alone[0].views + alone[1].views)
    assert np.allclose(merged.score, reference.score)


def test_gaps_say_what_they_fell_short_of(top_map) -> None:
    _, _, cmap = top_map
    strip, hole = cmap.gaps[0], next(g for g in cmap.gaps if g.no_surface_m2 > 0)
    assert hole.limited_by == "no surface"
    # The strip's middle was never seen; its median sample had too few views.
    assert strip.limited_by == "views" and strip.median_views < 3
