"""Synthetic inputs of the depth stage: a TUM trajectory and a dive folder on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from postproc.depth.simulate import SyntheticDive
from shared.formats.diveprofile import write_dive
from shared.formats.tum import write_tum


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
