"""The dive computer's profile (its clock, its resolution) and the truth mesh."""

from __future__ import annotations

import numpy as np
import pytest

from shared.clock import ClockModel
from shared.errors import OutputExistsError
from sim.dive import DiveComputerOptions, log_depth, simulate_dive_profile, true_depth_m
from sim.mesh import ply_bytes, scene_mesh, write_ply
from sim.motion import builtin_route, diver_trajectory
from sim.scene import WreckScene
from sim.survey import default_cam_from_imu

START_NS = 1_718_443_800_000_000_000


@pytest.fixture(scope="module")
def trajectory():
    return diver_trajectory(
        builtin_route(0), start_ns=START_NS, duration_s=60.0,
        cam_from_imu=default_cam_from_imu(), rng=np.random.default_rng(2),
    )  # fmt: skip


def test_profile_is_a_dive_on_the_computer_clock(trajectory) -> None:
    clock = ClockModel(offset_ns=-7_200_000_000_000 + 41_500_000_000, drift_ppm=37.0,
                       reference_ns=START_NS)  # fmt: skip
    options = DiveComputerOptions()
    profile = simulate_dive_profile(
        trajectory, film_start_ns=START_NS, film_end_ns=START_NS + 60 * 10**9, clock=clock,
        options=options, rng=np.random.default_rng(0),
    )  # fmt: skip
    assert profile.sample_interval_s == 10.0
    np.testing.assert_allclose(np.diff(profile.stamps_s), 10.0)
    assert profile.depth_m[0] < 1.0 and profile.depth_m[-1] < 1.0
    assert 13.0 < profile.max_depth_m < 16.0
    np.testing.assert_allclose(profile.depth_m * 10, np.round(profile.depth_m * 10), atol=1e-9)
    # Mapping the computer's stamps back to true time recovers the diver's depth.
    true_ns = clock.inverse(np.rint(profile.stamps_s * 1e9).astype(np.int64))
    expected = true_depth_m(trajectory, START_NS, START_NS + 60 * 10**9, true_ns, options)
    residual = profile.depth_m - expected
    assert np.abs(residual).max() < 0.25
    filmed = (true_ns >= START_NS) & (true_ns <= START_NS + 60 * 10**9)
    assert filmed.sum() == 6
    np.testing.assert_allclose(
        expected[filmed], -trajectory.position_m(true_ns[filmed])[:, 2], atol=1e-12
    )
    # The computer's clock is about two hours behind, as its stamps show.
    assert abs(profile.start_s - (START_NS * 1e-9 - 7200 - 270)) < 120


def test_the_computer_logs_noisy_depths_in_tenths_and_spikes_when_asked() -> None:
    depth = np.linspace(0.0, 20.0, 2001)
    quiet = log_depth(depth, np.random.default_rng(2), noise_m=0.05)
    np.testing.assert_allclose(quiet * 10.0, np.round(quiet * 10.0), atol=1e-9)
    assert quiet.min() >= 0.0
    assert 0.03 < np.std(quiet - depth) < 0.07
    # Spikes: every sample 1-5 m too deep; the noise is drawn first, as without spikes.
    spiky = log_depth(depth, np.random.default_rng(2), noise_m=0.05, outlier_fraction=1.0)
    excess = spiky - quiet
    assert excess.min() > 0.9 and excess.max() < 5.1
    none = log_depth(depth, np.random.default_rng(2), noise_m=0.05, outlier_fraction=0.0)
    np.testing.assert_array_equal(none, quiet)


def test_mesh_covers_the_scene_with_outward_normals(coarse_scene: WreckScene) -> None:
    mesh = scene_mesh(coarse_scene, cell_m=0.5)
    vertices, colors, triangles = mesh.vertices, mesh.colors, mesh.triangles
    assert colors.shape == vertices.shape and colors.dtype == np.uint8
    assert triangles.min() == 0 and triangles.max() == len(vertices) - 1
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    normals = np.cross(b - a, c - a)
    centroids = (a + b + c) / 3
    # Every box triangle lies on its face and its normal points out of its box.
    lo, hi = coarse_scene.box_arrays()
    on_box = mesh.triangle_face < coarse_scene.seafloor_face
    box = mesh.triangle_face[on_box] // 6
    axis = (mesh.triangle_face[on_box] % 6) // 2
    side = mesh.triangle_face[on_box] % 2
    rows = np.arange(len(box))
    plane = np.where(side == 1, hi[box, axis], lo[box, axis])
    np.testing.assert_allclose(centroids[on_box][rows, axis], plane, atol=1e-9)
    centre = (lo[box] + hi[box]) / 2
    assert np.all(np.einsum("ij,ij->i", normals[on_box], centroids[on_box] - centre) > 0)
    assert on_box.sum() > len(triangles) // 2
    floor = mesh.triangle_face == coarse_scene.seafloor_face
    assert floor.any() and np.all(normals[floor, 2] > 0)
    for k, placement in enumerate(coarse_scene.targets):
        board = mesh.triangle_face == coarse_scene.seafloor_face + 1 + k
        facing = normals[board] @ placement.world_from_target[:3, 2]
        assert board.any() and np.all(facing > 0)
    # Nothing below the seafloor.
    assert vertices[:, 2].min() >= coarse_scene.seafloor_z_m - 1e-9


def test_ply_is_binary_with_colours(tmp_path, coarse_scene: WreckScene) -> None:
    mesh = scene_mesh(coarse_scene, cell_m=1.0)
    vertices, triangles = mesh.vertices, mesh.triangles
    path = write_ply(tmp_path / "mesh.ply", mesh)
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert b"format binary_little_endian 1.0" in header
    assert f"element vertex {len(vertices)}".encode() in header
    assert len(body) == len(vertices) * 15 + len(triangles) * 13
    first = np.frombuffer(body[:12], dtype="<f4")
    np.testing.assert_allclose(first, vertices[0], atol=1e-5)
    assert data == ply_bytes(mesh)
    with pytest.raises(OutputExistsError):
        write_ply(path, mesh)
