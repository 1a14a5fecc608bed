"""Synthetic inputs of the depth stage: a TUM trajectory and a dive folder on disk."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from shared.formats.diveprofile import write_dive
from shared.formats.tum import write_tum
from shared.trajectory import Trajectory
from sim.dive import SyntheticDive


def write_inputs(folder: Path, sim: SyntheticDive) -> tuple[Path, Path]:
    """Write `sim` as `folder/trajectory.tum` and the dive folder `folder/dives`."""
    trajectory = write_tum(folder / "trajectory.tum", sim.trajectory)
    for profile in sim.dives:
        write_dive(folder / "dives", profile)
    return trajectory, folder / "dives"


def relative_inputs(
    sim: SyntheticDive,
) -> tuple[
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
]:
    """(traj_t_s, traj_z_m, dive_t_s, dive_depth_m) relative to the trajectory's first stamp."""
    reference_ns = int(sim.trajectory.stamps_ns[0])
    traj_t = (sim.trajectory.stamps_ns - reference_ns) / 1e9
    dive = sim.dives[sim.dive_index]
    return traj_t, sim.trajectory.positions[:, 2], dive.stamps_s - reference_ns / 1e9, dive.depth_m


@dataclass
class DemoSession:
    """One session of `bench/demo.py`'s survey, written as the depth stage receives it.

    trajectory: TUM of the true body poses in a VIO-like frame (origin at the
        first pose), stamped on the GoPro's clock as `gopro import` stamps them.
    dives: one dive folder holding the logs of every dive of the survey, as
        `dc download` leaves them (the stage must find the right one).
    time_offset_s: true dive-computer minus camera clock at the first stamp.
    depth_offset_m: true depth of the first pose.
    label: the stage's label of the session's own dive.
    """

    trajectory: Path
    dives: Path
    time_offset_s: float
    depth_offset_m: float
    label: str


def demo_session(folder: Path, *, seed: int, session: int, duration_s: float = 60.0) -> DemoSession:
    """`sim`'s survey as `make demo` runs it (two dives, `duration_s` filmed each).

    A minute of video overlaps six 10 s dive-computer samples.
    """
    from sim.survey import SurveyOptions, SurveySimulator

    sim = SurveySimulator(SurveyOptions(sessions=2, duration_s=duration_s, seed=seed, video=False))
    dives = folder / "dives"
    for k in range(len(sim.sessions)):
        write_dive(dives, sim.dive_profile(k))
    truth = sim.sessions[session]
    true_ns = np.arange(truth.start_ns, truth.end_ns, 50_000_000, dtype=np.int64)
    poses = truth.trajectory.world_from_body(true_ns)
    depth_offset_m = float(-poses[0, 2, 3])
    poses[:, :3, 3] -= poses[0, :3, 3]
    camera_ns = truth.gopro_clock.apply(true_ns)
    trajectory = write_tum(folder / "trajectory.tum", Trajectory(stamps_ns=camera_ns, poses=poses))
    offset_ns = truth.dive_clock.apply(int(true_ns[0])) - int(camera_ns[0])
    profile = sim.dive_profile(session)
    return DemoSession(
        trajectory=trajectory,
        dives=dives,
        time_offset_s=offset_ns / 1e9,
        depth_offset_m=depth_offset_m,
        label=f"dives/{profile.start_iso}",
    )
