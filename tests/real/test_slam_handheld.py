"""SLAM on a real hand-held camera + IMU: ../shared/data/realvi/handheld_a.

A RealSense colour camera (grey, 640x360, about 19 fps with 33/60 ms gaps) and
its IMU (gyro and accelerometer merged into one ~220 Hz stream with stamps
1 us to 20 ms apart), indoors, dim and low in texture, 62 s. The IMU starts
1 s before the first image, at rest; the hand starts moving about 0.5 s
before the first image. Its Kalibr file says the gyro bias walks by 2.6e-6
rad/s^2/sqrt(Hz), far below what consumer parts do.

No truth. What must hold, and was measured (one run per test session):

- it finishes (it used to stop 6 s in: "Indeterminate linear system ...
  Symbol: b0", the bias walk 1e7 times stiffer than the bias prior); the start is
  at rest, carried by the IMU to the first image (init "at rest (still IMU),
  propagated to the first keyframe"), one map segment;
- the trajectory has a pose at every image (1191 of 1191);
- a hand-held camera: keyframe speed at most 0.18 m/s (limit 3 m/s), path 6.2 m
  over the 62 s, within a 1.6 m box;
- gravity consistent: the accelerometer's mean specific force rotated into S by
  the estimated attitude points up within 1.1-1.7 degrees in every 10 s window
  (limit 3). (Its norm is not checked: the accelerometer's bias, 0.44 m/s^2 as
  estimated, projects differently in each attitude: 9.93 m/s^2 at rest, 10.05-10.18
  in the windows.)
- its keyframes, cut into two halves at 31 s and the second moved by a known
  transform, merge through the room's own structure (no target): 0.377 deg and
  5.0 cm from the known transform, the SLAM's own drift between the halves
  included (limits 1 deg, 10 cm).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from postproc.merge.stage import MergeOptions
from postproc.merge.stage import run as merge
from postproc.slam.inputs import open_input
from postproc.slam.stage import SlamOptions, keyframe_speeds_m_s, run
from shared.folders import SlamFolder
from shared.formats.tum import read_tum
from shared.geometry import invert_pose, make_pose, pose_difference, so3_exp
from shared.trajectory import Trajectory


@dataclass
class HandheldRun:
    images_ns: np.ndarray
    trajectory: Trajectory
    keyframes: Trajectory
    stats: dict[str, Any]
    folder: Path
    slam: Path


@pytest.fixture(scope="module")
def handheld(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> HandheldRun:
    folder = shared_data / "realvi" / "handheld_a"
    out = run(SlamOptions(), folder, tmp_path_factory.mktemp("handheld") / "slam")
    source = open_input(folder)
    images = _image_stamps_ns(folder)
    assert len(images) == source.frame_count
    return HandheldRun(
        images_ns=images,
        trajectory=read_tum(out / "trajectory.tum"),
        keyframes=read_tum(out / "keyframes.tum"),
        stats=json.loads((out / "stats.json").read_text()),
        folder=folder,
        slam=out,
    )


def _image_stamps_ns(folder: Path) -> np.ndarray:
    """Image stamps from cam0/data.csv (without decoding 1191 images)."""
    lines = (folder / "mav0" / "cam0" / "data.csv").read_text().splitlines()
    return np.array([int(x.split(",")[0]) for x in lines if x and x[0] != "#"], dtype=np.int64)


@pytest.mark.slow
def test_it_finishes_from_a_still_start_and_covers_every_image(handheld: HandheldRun) -> None:
    stats = handheld.stats
    assert stats["init"].startswith("at rest (still IMU)")
    assert stats["map_segments"] == 1 and not stats["segment_failures"]
    assert stats["frames_before_imu"] == stats["frames_after_imu"] == 0
    images, trajectory = handheld.images_ns, handheld.trajectory
    assert len(trajectory) >= 0.95 * len(images)
    span = (trajectory.stamps_ns[-1] - trajectory.stamps_ns[0]) / (images[-1] - images[0])
    assert span >= 0.95
    assert np.all(np.isin(trajectory.stamps_ns, images))
    assert np.all(np.isfinite(trajectory.poses))
    assert stats["keyframes"] >= 100 and stats["landmarks"] >= 500


@pytest.mark.slow
def test_a_hand_held_speed(handheld: HandheldRun) -> None:
    keyframes = handheld.keyframes
    speeds = keyframe_speeds_m_s(keyframes.stamps_ns, keyframes.poses)
    assert float(np.max(speeds)) <= 3.0
    position = handheld.trajectory.poses[:, :3, 3]
    steps = np.linalg.norm(np.diff(position, axis=0), axis=1)
    dt_s = np.diff(handheld.trajectory.stamps_ns) * 1e-9
    assert float(np.max(steps / dt_s)) <= 3.0
    # Walked about a room, not flown off: a path of metres inside a few metres.
    assert 1.0 < float(steps.sum()) < 40.0
    assert float(np.max(np.ptp(position, axis=0))) < 10.0


@pytest.mark.slow
def test_gravity_stays_consistent(handheld: HandheldRun) -> None:
    imu = open_input(handheld.folder).imu
    trajectory = handheld.trajectory
    inside = (imu.stamps_ns >= trajectory.stamps_ns[0]) & (
        imu.stamps_ns <= trajectory.stamps_ns[-1]
    )
    nearest = np.clip(
        np.searchsorted(trajectory.stamps_ns, imu.stamps_ns[inside]), 0, len(trajectory) - 1
    )
    force_s = np.einsum("nij,nj->ni", trajectory.poses[nearest, :3, :3], imu.accel_m_s2[inside])
    t_s = (imu.stamps_ns[inside] - imu.stamps_ns[inside][0]) * 1e-9
    for start in np.arange(0.0, t_s[-1] - 5.0, 10.0):
        window = (t_s >= start) & (t_s < start + 10.0)
        mean = force_s[window].mean(axis=0)
        tilt_deg = float(np.degrees(np.arccos(mean[2] / np.linalg.norm(mean))))
        assert tilt_deg < 3.0, f"window at {start:.0f} s tilts {tilt_deg:.1f} deg"


def _half(slam: Path, out: Path, *, first: bool, split_s: float, moved: np.ndarray) -> int:
    """The keyframes (and trajectory) before or after `split_s` as a SLAM folder of its
    own, its poses in a frame moved by `moved` (`T_S_S'`); returns its keyframe count."""
    source = SlamFolder(slam)
    keyframes, trajectory = source.read_keyframes(), source.read_trajectory()
    split_ns = int(trajectory.stamps_ns[0]) + int(split_s * 1e9)
    half = SlamFolder(out)
    half.keyframes.mkdir(parents=True)
    shutil.copytree(source.calib, half.calib)
    moved_from = invert_pose(moved)
    for what, write in ((keyframes, half.write_keyframes), (trajectory, half.write_trajectory)):
        keep = (what.stamps_ns < split_ns) if first else (what.stamps_ns >= split_ns)
        write(Trajectory(what.stamps_ns[keep], moved_from @ what.poses[keep]))
    for stamp in half.read_keyframes().stamps_ns.tolist():
        shutil.copy(source.keyframe_image(stamp), half.keyframe_image(stamp))
    half.write_stats({"split_from": slam.name})
    return len(half.read_keyframes())


@pytest.mark.slow
def test_its_two_halves_merge_through_the_room_without_targets(
    handheld: HandheldRun, tmp_path: Path
) -> None:
    # The recording's first and last 31 s as two dives, the second in a frame turned by
    # 40 deg and moved 1.7 m: the natural-feature merge (no target in the room) must
    # find the transform back. The SLAM's own drift between the halves is part of the
    # error and is not known (no truth here). Measured (one run): 0.377 deg, 5.0 cm;
    # with places not refined by their adjustment (the PnP alone) 0.135 deg, 1.6 cm;
    # other splits (20 s, 42 s): 0.34 / 0.68 deg against 1.10 / 0.45 deg.
    moved = make_pose(so3_exp([0.0, 0.0, np.deg2rad(40.0)]), [1.5, -0.7, 0.2])
    counts = [
        _half(handheld.slam, tmp_path / name, first=name == "a", split_s=31.0, moved=pose)
        for name, pose in (("a", np.eye(4)), ("b", moved))
    ]
    assert min(counts) >= 50
    merged = merge(MergeOptions(plot=False), [tmp_path / "a", tmp_path / "b"], [], tmp_path / "m")
    document = json.loads(merged.read_text())
    b = document["sessions"]["b"]
    [pair] = document["pairs"]
    assert b["placed"] and pair["mergeable"] and pair["consistent"] >= 10, pair["reason"]
    rotation, translation = pose_difference(np.array(b["T_W_S"]), moved)
    assert np.rad2deg(rotation) < 1.0 and translation < 0.10
