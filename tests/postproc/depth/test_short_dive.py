"""A minute of video, six dive-computer samples: `make demo`'s shape, where the sync went wrong.

Each case first replays the selection rule the stage used before it measured
ambiguity (every coarse candidate of every dive fitted, the least robust scale
wins, then the flatness and sigma checks) and shows that it returns a wrong
offset with nothing to flag it; then runs the stage, which must either find the
true offset or refuse with a StageError that names the dive and `--time-offset`.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from postproc.depth.stage import DepthOptions, run
from postproc.depth.sync import (
    SyncError,
    coarse_offset_search,
    depth_variation_m,
    fit_depth_sync,
)
from shared.errors import StageError
from shared.formats.diveprofile import read_dive_folder, stamp_s_to_iso, write_dive
from shared.formats.tum import read_tum, write_tum
from shared.trajectory import Trajectory

from .inputs import DemoSession, demo_session

# What bench/demo.py writes into project.yaml for a dive of a minute.
DEMO_MIN_DEPTH_RANGE_M = 0.5


def _options(**changes: object) -> DepthOptions:
    options = DepthOptions(min_depth_range_m=DEMO_MIN_DEPTH_RANGE_M, fuse=False, plot=False)
    for name, value in changes.items():
        setattr(options, name, value)
    return options


def _best_offsets(
    offsets_s: np.ndarray, rms_m: np.ndarray, *, separation_s: float, count: int = 5
) -> list[float]:
    """The old candidate rule: the best-scoring grid offsets at least `separation_s` apart."""
    picked: list[float] = []
    for index in np.argsort(rms_m, kind="stable"):
        if len(picked) >= count:
            break
        if all(abs(offsets_s[index] - p) >= separation_s for p in picked):
            picked.append(float(offsets_s[index]))
    return picked


def _old_rule(case: DemoSession) -> tuple[float, float] | None:
    """(offset_s, depth_offset_m) the stage returned before; None when it refused."""
    trajectory = read_tum(case.trajectory)
    reference_ns = int(trajectory.stamps_ns[0])
    traj_t = (trajectory.stamps_ns - reference_ns) / 1e9
    traj_z = trajectory.positions[:, 2]
    best = None
    for profile in read_dive_folder(case.dives):
        dive_t = profile.stamps_s - reference_ns / 1e9
        try:
            # The search of then: raw z and depths, the five best grid offsets 10 s apart.
            coarse = coarse_offset_search(
                traj_t,
                traj_z,
                dive_t,
                profile.depth_m,
                max_offset_s=15 * 3600.0,
                smooth_s=0.0,
                despike_depth=False,
            )
        except SyncError:
            continue
        for offset_s in _best_offsets(coarse.offsets_s, coarse.rms_m, separation_s=10.0):
            sync = fit_depth_sync(
                traj_t, traj_z, dive_t, profile.depth_m, initial_offset_s=offset_s, smooth_s=2.0
            )
            if best is None or sync.robust_scale_m < best[0].robust_scale_m:
                best = (sync, dive_t, profile.depth_m)
    assert best is not None
    sync, dive_t, depth = best
    depth_range, z_range = depth_variation_m(traj_t, traj_z, dive_t, depth, sync)
    if min(depth_range, z_range) < DEMO_MIN_DEPTH_RANGE_M or not sync.time_offset_sigma_s <= 5.0:
        return None
    return sync.time_offset_s, sync.depth_offset_m


def _assert_old_rule_silently_wrong(case: DemoSession) -> None:
    old = _old_rule(case)
    assert old is not None, "the old rule refused: this case no longer shows the failure"
    assert abs(old[0] - case.time_offset_s) > 60.0
    assert abs(old[1] - case.depth_offset_m) > 1.0


def test_demo_dive_that_went_wrong_is_now_right(tmp_path):
    # bench/demo.py's first dive (seed 1): the old rule matched the safety stop, +344 s.
    case = demo_session(tmp_path, seed=1, session=0)
    _assert_old_rule_silently_wrong(case)
    doc = json.loads(run(_options(), case.trajectory, case.dives, tmp_path / "out").read_text())
    assert abs(doc["time_offset_s"] - case.time_offset_s) < 2.0
    assert abs(doc["depth_offset_m"] - case.depth_offset_m) < 0.1
    assert doc["dive"]["label"] == case.label
    ambiguity = doc["offset_ambiguity"]
    assert ambiguity["ambiguous"] is False and ambiguity["reasons"] == []
    assert ambiguity["samples"] == 6
    assert ambiguity["evidence"] >= DepthOptions().min_evidence
    # The runner-up the old rule took is reported, with its wrong depth.
    assert abs(ambiguity["runner_up_offset_s"] - case.time_offset_s) > 60.0
    assert abs(ambiguity["runner_up_depth_offset_m"] - case.depth_offset_m) > 1.0
    assert ambiguity["runner_up_cost"] > ambiguity["best_cost"]
    assert ambiguity["excursion_steps"] == pytest.approx(ambiguity["depth_range_m"] / 0.1)
    assert doc["clock_prior"]["available"] is True
    assert doc["clock_prior"]["used"] is False  # the data alone decided
    assert doc["clock_prior"]["inside"] is True
    assert "search_ambiguity" not in doc


def test_clock_prior_settles_an_ambiguous_short_dive(tmp_path):
    # Seed 15, first dive: the other dive of the day, 4 h away, fits about as well.
    case = demo_session(tmp_path, seed=15, session=0)
    _assert_old_rule_silently_wrong(case)
    doc = json.loads(run(_options(), case.trajectory, case.dives, tmp_path / "out").read_text())
    assert abs(doc["time_offset_s"] - case.time_offset_s) < 2.0
    assert abs(doc["depth_offset_m"] - case.depth_offset_m) < 0.1
    assert doc["clock_prior"]["used"] is True
    assert doc["clock_prior"]["distance_s"] <= doc["clock_prior"]["window_s"]
    assert doc["search_ambiguity"]["ambiguous"] is True
    assert doc["search_ambiguity"]["evidence"] < DepthOptions().min_evidence
    assert doc["offset_ambiguity"]["ambiguous"] is False
    assert doc["offset_ambiguity"]["evidence"] >= DepthOptions().min_evidence

    # Without the prior the same data are refused, not answered wrongly.
    with pytest.raises(StageError, match=r"ambiguous.*clock_prior_window_s is off.*--time-offset"):
        run(_options(clock_prior_window_s=None), case.trajectory, case.dives, tmp_path / "none")
    assert not (tmp_path / "none" / "sync.json").exists()


def test_no_prior_when_the_stamps_are_not_dates(tmp_path):
    case = demo_session(tmp_path, seed=15, session=0)
    # The same data on clocks counting from zero (both shifted alike: same offset).
    trajectory = read_tum(case.trajectory)
    shift_s = float(trajectory.stamps_ns[0] // 1_000_000_000)
    shifted = tmp_path / "shifted"
    write_tum(
        shifted / "trajectory.tum",
        Trajectory(
            stamps_ns=trajectory.stamps_ns - int(shift_s) * 1_000_000_000,
            poses=trajectory.poses,
        ),
    )
    for profile in read_dive_folder(case.dives):
        profile.start_iso = stamp_s_to_iso(profile.start_s - shift_s)
        profile.stamps_s = profile.stamps_s - shift_s
        write_dive(shifted / "dives", profile)
    with pytest.raises(StageError, match=r"stamps are not wall-clock dates"):
        run(_options(), shifted / "trajectory.tum", shifted / "dives", tmp_path / "out")


def test_ambiguous_short_dive_is_refused_with_the_way_out(tmp_path):
    # Seed 13, first dive: even inside the prior's window two offsets fit alike.
    case = demo_session(tmp_path, seed=13, session=0)
    _assert_old_rule_silently_wrong(case)
    with pytest.raises(StageError) as raised:
        run(_options(), case.trajectory, case.dives, tmp_path / "out")
    message = str(raised.value)
    assert message.startswith(case.label + ": the clock offset is ambiguous")
    assert "another offset fits almost as well" in message
    assert "did not settle it" in message and "--time-offset SECONDS" in message
    assert not (tmp_path / "out" / "sync.json").exists()
    # The way out the message gives: the offset by hand.
    doc = json.loads(
        run(
            _options(time_offset_s=case.time_offset_s),
            case.trajectory,
            case.dives,
            tmp_path / "out",
        ).read_text()
    )
    assert doc["time_offset_given"] is True
    assert abs(doc["depth_offset_m"] - case.depth_offset_m) < 0.1
    assert doc["offset_ambiguity"] is None
    assert doc["clock_prior"]["used"] is False


def test_longer_video_of_the_same_survey_needs_no_prior(tmp_path):
    # Five minutes of the same survey: 30 samples, the offset is plain.
    case = demo_session(tmp_path, seed=13, session=0, duration_s=300.0)
    doc = json.loads(run(_options(), case.trajectory, case.dives, tmp_path / "out").read_text())
    assert abs(doc["time_offset_s"] - case.time_offset_s) < 1.0
    assert doc["offset_ambiguity"]["samples"] >= 25
    assert doc["offset_ambiguity"]["evidence"] > 10 * DepthOptions().min_evidence
    assert doc["clock_prior"]["used"] is False
    assert np.isfinite(doc["offset_ambiguity"]["time_offset_sigma_s"])
