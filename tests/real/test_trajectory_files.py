"""The real pose files of ../shared/data through the trajectory reader the depth stage uses.

EuRoC V2_03's ground truth comes in three spellings: the EuRoC CSV
(`#timestamp, p_RS_R_x [m], ..., q_RS_w [], q_RS_x [], ...`: integer
nanoseconds, w first, 17 columns), its TUM conversion (seconds with 9
decimals, w last) and the raw Vicon CSV. Each must read without a skipped
line, and the two spellings of one trajectory must agree exactly on the
stamps and to the printed digits on the poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.formats.svin import read_trajectory
from shared.formats.tum import read_tum


def _data_rows(path: Path) -> list[list[str]]:
    lines = path.read_text().splitlines()
    return [line.split(",") for line in lines if line and not line.startswith("#")]


def test_euroc_ground_truth_csv_and_its_tum_twin_agree(shared_data: Path) -> None:
    folder = shared_data / "realvi" / "euroc_v203_imu"
    csv = folder / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    read = read_trajectory(csv)
    assert (read.stamps, read.layout, read.pose_frame, read.warnings) == (
        "ns",
        "named",
        "body",
        (),
    )
    rows = _data_rows(csv)
    assert read.trajectory.stamps_ns.tolist() == [int(r[0]) for r in rows]
    table = np.array([[float(v) for v in r[1:8]] for r in rows])
    np.testing.assert_allclose(read.trajectory.positions, table[:, 0:3], atol=0)

    twin = read_trajectory(folder / "groundtruth_body_tum.txt")
    assert (twin.stamps, twin.layout, twin.warnings) == ("tum", "tum", ())
    np.testing.assert_array_equal(twin.trajectory.stamps_ns, read.trajectory.stamps_ns)
    np.testing.assert_array_equal(
        twin.trajectory.stamps_ns, read_tum(folder / "groundtruth_body_tum.txt").stamps_ns
    )
    # Same poses: quaternion order (w first vs last) handled; 6 printed decimals each.
    np.testing.assert_allclose(twin.trajectory.poses, read.trajectory.poses, atol=1e-5)


def test_euroc_vicon_csv(shared_data: Path) -> None:
    """The Vicon marker is rigid on the body: read in the header's (w, x, y, z) order, its
    rotation relative to the ground-truth body's stays nearly constant (median 6.6 deg over
    this fast run, stamps within 2 ms; read as x, y, z, w it wanders by 80 deg)."""
    folder = shared_data / "realvi" / "euroc_v203_imu" / "mav0"
    csv = folder / "vicon0" / "data.csv"
    read = read_trajectory(csv)
    rows = _data_rows(csv)
    assert read.warnings == () and read.stamps == "ns"
    assert read.trajectory.stamps_ns.tolist() == [int(r[0]) for r in rows]
    vicon = read.trajectory
    body = read_trajectory(folder / "state_groundtruth_estimate0" / "data.csv").trajectory
    after = np.clip(np.searchsorted(body.stamps_ns, vicon.stamps_ns), 1, len(body) - 1)
    nearer = np.abs(body.stamps_ns[after - 1] - vicon.stamps_ns) < np.abs(
        body.stamps_ns[after] - vicon.stamps_ns
    )
    match = np.where(nearer, after - 1, after)
    close = np.abs(body.stamps_ns[match] - vicon.stamps_ns) < 2_000_000
    assert close.sum() > 0.9 * len(vicon)
    relative = np.einsum(
        "nji,njk->nik", body.rotations[match][close], vicon.rotations[close]
    )  # R_body^T R_marker
    u, _, vt = np.linalg.svd(relative.mean(axis=0))
    mean = u @ vt
    cos = (np.einsum("ij,nij->n", mean, relative) - 1.0) / 2.0
    deviation_deg = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    assert np.median(deviation_deg) < 15.0
