"""A project whose outputs have known errors against a synthetic truth (the report and
viewer tests build it; imported by path, not a test module)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from shared.formats.ply import PlyData, write_ply
from shared.formats.tum import write_tum
from shared.geometry import invert_pose, make_pose, so3_exp
from shared.trajectory import Trajectory

SHIFT_S = 0.0125
T0_NS = 1_718_443_800_000_000_000
CAM_FROM_IMU = make_pose(so3_exp([0.1, -1.5, 0.2]), [0.02, -0.01, -0.03])


def cube() -> PlyData:
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) - 0.5
    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    return PlyData(vertices=corners * 2.0 + [0, 0, -10], faces=faces)


def png() -> bytes:
    ok, data = cv2.imencode(".png", np.full((8, 8, 3), 90, np.uint8))
    assert ok
    return data.tobytes()


def truth_body() -> Trajectory:
    t = np.arange(200)
    stamps = T0_NS + t * 100_000_000
    poses = np.stack(
        [
            make_pose(
                so3_exp([0, 0, 0.02 * k]), [np.cos(0.05 * k), np.sin(0.05 * k), -10 - 0.01 * k]
            )
            for k in t
        ]
    )
    return Trajectory(stamps.astype(np.int64), poses)


def build(root: Path, *, rng: np.random.Generator) -> tuple[Path, dict[str, float]]:
    """A project whose outputs have known errors against a synthetic truth."""
    body = truth_body()
    write_tum(root / "truth" / "s.tum", body)
    write_ply(root / "truth" / "mesh.ply", cube())
    truth = {
        "format": "wreckmap-sim-truth",
        "camera": {"timeshift_cam_imu_s": SHIFT_S, "cam_from_imu": CAM_FROM_IMU.tolist()},
        "world": {"mesh": "mesh.ply"},
        "sessions": [
            {
                "name": "session_00",
                "files": {"trajectory": "s.tum"},
                "clocks": {
                    "dive_computer": {
                        "offset_ns": -87_000_000_000,
                        "drift_ppm": 10.0,
                        "reference_ns": T0_NS,
                    }
                },
            }
        ],
    }
    (root / "truth" / "truth.json").write_text(json.dumps(truth))
    (root / "rec").mkdir()
    (root / "p.yaml").write_text(
        "name: synthetic\noutput: out\ntruth: truth/truth.json\n"
        "sessions:\n  - {name: s1, euroc: rec}\n"
    )
    out = root / "out"
    cam_stamps = body.stamps_ns - round(SHIFT_S * 1e9)
    # SLAM: the truth in another rigid frame plus 1 cm noise per axis.
    G = make_pose(so3_exp([0.0, 0.0, 1.0]), [3.0, -2.0, 10.0])
    noise = rng.normal(0.0, 0.01, (len(body), 3))
    slam_poses = G @ body.poses
    slam_poses[:, :3, 3] += noise
    slam = out / "sessions" / "s1"
    write_tum(slam / "trajectory.tum", Trajectory(cam_stamps, slam_poses))
    (slam / "stats.json").write_text(
        json.dumps({"frames": 200, "keyframes": 20, "run_time_s": 4.0})
    )
    # Depth: clock offset 0.3 s off, z 0.2 m too deep.
    ref_s = cam_stamps[0] * 1e-9
    true_offset = -87.0 + SHIFT_S + 10e-6 * (ref_s + SHIFT_S - T0_NS * 1e-9)
    world = body.poses.copy()
    world[:, 2, 3] -= 0.2
    (slam / "depth").mkdir()
    write_tum(slam / "depth" / "trajectory_world.tum", Trajectory(cam_stamps, world))
    (slam / "depth" / "sync.json").write_text(
        json.dumps(
            {"reference_time_s": ref_s, "time_offset_s": true_offset + 0.3, "drift_ppm": 9.0}
        )
    )
    (slam / "depth" / "depth_sync.png").write_bytes(png())
    # Merge: exact keyframe camera poses in a rigid frame H.
    H = make_pose(so3_exp([0.0, 0.0, -0.4]), [1.0, 1.0, 0.0])
    keyframes = Trajectory(cam_stamps[::10], H @ body.poses[::10] @ invert_pose(CAM_FROM_IMU))
    write_tum(out / "merge" / "s1" / "keyframes_merged.tum", keyframes)
    (out / "merge" / "transforms.json").write_text(
        json.dumps({"reference": "s1", "dof": 4, "sessions": {"s1": {"placed": True, "via": []}}})
    )
    (out / "merge" / "merge_top.png").write_bytes(png())
    (out / "sfm").mkdir()
    (out / "sfm" / "stats.json").write_text(json.dumps({"keyframes": 20, "points3D": 1000}))
    # Dense: the truth mesh moved into the merged frame (H).
    mesh = cube()
    mesh.vertices = mesh.vertices @ H[:3, :3].T + H[:3, 3]
    write_ply(out / "dense" / "mesh.ply", mesh)
    (out / "dense" / "dense.json").write_text(json.dumps({"backend": "cpu", "images": 20}))
    return root / "p.yaml", {"noise_rms": float(np.sqrt(np.mean(np.sum(noise**2, axis=1))))}
