"""The stage graph: the plan from the registry, hash-based skipping, reruns after an option
change, failures, atomic outputs and the local process pool."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from postproc.pipeline.dask_backend import ProcessBackend, make_backend
from postproc.pipeline.project import load_project
from postproc.pipeline.runner import STAMP_NAME, plan, run_project
from shared.errors import InputError
from shared.folders import DenseFolder, HandoffFolder

from .conftest import REPO, write_project

ALL = ["slam:s1", "depth:s1", "slam:s2", "depth:s2", "merge", "sfm", "dense"]


def calls(markers: Path) -> list[str]:
    """Stage keys run since the markers folder was last emptied (sorted)."""
    return sorted(p.name.split(".")[0].replace("_", ":", 1) for p in markers.glob("*.started"))


def clear(markers: Path) -> None:
    for p in markers.glob("*.started"):
        p.unlink()


def statuses(result) -> dict[str, str]:
    return {o.key: o.status for o in result.outcomes}


def outputs(root: Path) -> dict[str, bytes]:
    """Every output file except the runner's stamps, logs and caches."""
    skip = {STAMP_NAME}
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
        and p.name not in skip
        and p.relative_to(root).parts[0] not in ("logs", ".wreckmap")
    }


def test_plan_lays_out_sessions_and_project_stages(project_file: Path) -> None:
    project = load_project(project_file)
    tasks, notes = plan(project)
    assert [t.key for t in tasks] == ALL
    by_key = {t.key: t for t in tasks}
    assert by_key["depth:s1"].out == project.output / "sessions" / "s1" / "depth"
    assert by_key["merge"].deps == ("slam:s1", "slam:s2")
    assert by_key["merge"].soft_deps == by_key["sfm"].soft_deps == ("depth:s1", "depth:s2")
    assert by_key["sfm"].deps == ("slam:s1", "slam:s2", "merge")
    assert notes == []


def test_second_run_does_nothing_and_option_change_reruns_downstream(
    project_file: Path, fake_stages: dict[str, Any], tmp_path: Path
) -> None:
    markers = tmp_path / "markers"
    project = load_project(project_file)
    first = run_project(project, stages=fake_stages)
    assert first.exit_code() == 0
    assert statuses(first) == dict.fromkeys(ALL, "done")
    assert calls(markers) == sorted(ALL)
    stamp = json.loads((project.output / "sessions" / "s1" / STAMP_NAME).read_text())
    assert stamp["stage"] == "slam" and len(stamp["digest"]) == 64
    # The task's peak resident memory (a Python process with NumPy: tens of MiB at least).
    assert stamp["peak_rss_mib"] > 10
    assert all(o.peak_rss_mib > 10 for o in first.outcomes)
    assert (project.output / "logs" / "slam_s1.log").read_text().count("done in") == 1
    before = outputs(project.output)

    clear(markers)
    second = run_project(load_project(project_file), stages=fake_stages)
    assert statuses(second) == dict.fromkeys(ALL, "skipped")
    assert calls(markers) == []
    assert outputs(project.output) == before

    # A depth option changes: both depth runs and everything downstream, not SLAM.
    text = project_file.read_text() + "stages:\n  depth:\n    fuse: false\n"
    project_file.write_text(text)
    clear(markers)
    third = run_project(load_project(project_file), stages=fake_stages)
    assert calls(markers) == sorted(["depth:s1", "depth:s2", "merge", "sfm", "dense"])
    assert statuses(third)["slam:s1"] == "skipped"

    # An input's content changes: that session's chain and the project stages rerun.
    (project_file.parent / "data" / "dive2.csv").write_text(
        "timestamp_s,depth_m,temperature_c\n9,2,\n"
    )
    clear(markers)
    run_project(load_project(project_file), stages=fake_stages)
    assert calls(markers) == sorted(["depth:s2", "merge", "sfm", "dense"])


def test_failed_slam_blocks_its_session_and_the_project_stages(
    project_file: Path, fake_stages: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    project = load_project(project_file)
    assert run_project(project, stages=fake_stages).exit_code() == 0
    # An option change makes slam:s1 fail now: its stale output is removed, not left to be read.
    monkeypatch.setenv("FAKE_STAGE_FAIL", "slam:s1")
    project_file.write_text(project_file.read_text() + "stages:\n  slam: {max_frames: 5}\n")
    result = run_project(load_project(project_file), stages=fake_stages)
    s = statuses(result)
    assert s["slam:s1"] == "failed" and s["slam:s2"] == "done"
    assert s["depth:s1"] == s["merge"] == s["sfm"] == s["dense"] == "blocked"
    assert s["depth:s2"] == "done"
    assert not (project.output / "sessions" / "s1").exists()


class ViewsFolder(HandoffFolder):
    """A made-up kind for a made-up stage (the registry test)."""

    kind = "views"
    marker = "views.json"


def run_views(options: Any, inputs: dict[str, Any], out: Path, *, context: Any) -> Path:
    out.mkdir()
    (out / "views.json").write_text(json.dumps({"dense": str(inputs["dense"])}))
    return out


def test_a_new_stage_is_one_registry_entry(project_file: Path, fake_stages: dict[str, Any]) -> None:
    """A stage added to the registry is planned after what it reads, digested, checked
    for its marker and run, with no other table to edit."""
    from postproc.pipeline.stages import Read, Sources, Stage

    views = Stage(
        name="views",
        options_type=lambda: type(fake_stages["dense"].options_type()()),
        run=run_views,
        writes=ViewsFolder,
        reads=(Read(kind=DenseFolder, name="dense"),),
        place=lambda output, session: output / "views",
        sources=lambda project, session: Sources(),
    )
    registry = {**fake_stages, "views": views}
    project = load_project(project_file)
    tasks, _ = plan(project, registry)
    assert [t.key for t in tasks] == [*ALL, "views"]
    assert tasks[-1].deps == ("dense",) and tasks[-1].inputs == {"dense": project.output / "dense"}
    result = run_project(project, stages=registry)
    assert statuses(result)["views"] == "done" and result.exit_code() == 0
    assert json.loads((project.output / "views" / "views.json").read_text()) == {
        "dense": str(project.output / "dense")
    }
    # Up to date the second time; a run function that forgets the marker fails the stage.
    assert statuses(run_project(load_project(project_file), stages=registry))["views"] == "skipped"

    def no_marker(options: Any, inputs: dict[str, Any], out: Path, *, context: Any) -> Path:
        out.mkdir()
        return out

    broken = {**registry, "views": dataclasses.replace(views, run=no_marker)}
    again = run_project(load_project(project_file), stages=broken, force=True)
    outcome = {o.key: o for o in again.outcomes}["views"]
    assert outcome.status == "failed" and again.exit_code() == 1
    assert "views: finished without writing views.json" in outcome.message


def test_a_stage_reading_a_kind_nobody_writes_is_refused(
    project_file: Path, fake_stages: dict[str, Any]
) -> None:
    from postproc.pipeline.stages import Read

    registry = dict(fake_stages)
    registry["dense"] = dataclasses.replace(
        registry["dense"], reads=(Read(kind=ViewsFolder, name="views"),)
    )
    with pytest.raises(InputError, match=r"stage dense reads a views folder that no planned"):
        plan(load_project(project_file), registry)


def test_failed_stage_leaves_nothing_half_written_and_reruns_once_fixed(
    project_file: Path, fake_stages: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("FAKE_STAGE_FAIL", "depth:s2")
    project = load_project(project_file)
    result = run_project(project, stages=fake_stages)
    s = statuses(result)
    assert s["depth:s2"] == "failed" and s["depth:s1"] == "done"
    # Depth is a soft input: merge and SfM go on with the SLAM frames.
    assert s["merge"] == s["sfm"] == s["dense"] == "done"
    assert result.exit_code() == 1
    assert "failing on purpose" in result.failed[0].message
    s2 = project.output / "sessions" / "s2"
    assert not (s2 / "depth").exists()
    assert not list(s2.glob(".*partial*")), "the failed attempt's partial folder was left"
    assert "failing on purpose" in (project.output / "logs" / "depth_s2.log").read_text()
    # Fixed: only the failed stage and what it blocked run now.
    monkeypatch.delenv("FAKE_STAGE_FAIL")
    again = run_project(load_project(project_file), stages=fake_stages)
    assert [k for k, v in statuses(again).items() if v == "done"] == [
        "depth:s2",
        "merge",
        "sfm",
        "dense",
    ]


def test_session_without_dive_and_project_without_targets(
    project_file: Path, fake_stages: dict[str, Any]
) -> None:
    text = project_file.read_text().replace("targets: [targets/grid.yaml]\n", "")
    text = text.replace("    dive: data/dive2.csv\n", "")
    project_file.write_text(text)
    project = load_project(project_file)
    tasks, notes = plan(project)
    assert [t.key for t in tasks] == ["slam:s1", "depth:s1", "slam:s2", "sfm", "dense"]
    assert notes == [
        "depth: no dive log for s2 (not planned)",
        "merge: no targets in the project (not planned)",
    ]
    assert "merge" not in tasks[3].inputs
    assert run_project(project, stages=fake_stages).exit_code() == 0


def test_process_pool_gives_the_same_outputs(
    project_file: Path, fake_stages: dict[str, Any], tmp_path: Path
) -> None:
    inline = load_project(project_file)
    run_project(inline, stages=fake_stages)
    expected = outputs(inline.output)
    other = load_project(project_file)
    other.output = tmp_path / "pool-out"
    backend = make_backend("local", workers=2)
    assert isinstance(backend, ProcessBackend)
    try:
        result = run_project(other, stages=fake_stages, backend=backend)
    finally:
        backend.close()
    assert result.exit_code() == 0
    assert outputs(other.output) == expected


def test_backend_errors_name_the_option() -> None:
    with pytest.raises(InputError, match="--scheduler 'mpi'"):
        make_backend("mpi")
    with pytest.raises(InputError, match="--workers 0"):
        make_backend("local", workers=0)
    with pytest.raises(InputError, match="no Dask scheduler answers"):
        make_backend("tcp://127.0.0.1:9", connect_timeout_s=1.0)


def test_slurm_job_script_follows_the_cluster_settings() -> None:
    from postproc.pipeline.dask_backend import slurm_cluster
    from postproc.pipeline.project import ClusterSpec

    spec = ClusterSpec(queue="lab", account="wreck", cores=6, memory="8GB", walltime="01:30:00",
                       job_extra_directives=["--gres=gpu:1"])  # fmt: skip
    cluster = slurm_cluster(spec, host="127.0.0.1")
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    for line in ("#SBATCH -p lab", "#SBATCH -A wreck", "#SBATCH --cpus-per-task=6",
                 "#SBATCH -t 01:30:00", "#SBATCH --gres=gpu:1", "--nthreads 1"):  # fmt: skip
        assert line in script, script


def test_importing_dask_jobqueue_leaves_ctrl_c_alone() -> None:
    # A fresh interpreter: the import's side effect happens once per process.
    code = (
        "import signal\n"
        "from postproc.pipeline.dask_backend import slurm_cluster_class\n"
        "before = signal.getsignal(signal.SIGINT)\n"
        "slurm_cluster_class()\n"
        "import sys\n"
        "assert 'dask_jobqueue' in sys.modules\n"
        "assert signal.getsignal(signal.SIGINT) is before, signal.getsignal(signal.SIGINT)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr


def test_calibration_recording_runs_first_and_feeds_import_and_slam(
    project_file: Path, fake_stages: dict[str, Any], tmp_path: Path
) -> None:
    markers = tmp_path / "markers"
    root = project_file.parent
    (root / "calib_rec").mkdir()
    (root / "calib_rec" / "frames.txt").write_text("grid views\n")
    project_file.write_text(
        project_file.read_text()
        + "calibration: {recording: calib_rec, target: targets/grid.yaml}\n"
    )
    project = load_project(project_file)
    tasks, _ = plan(project)
    assert tasks[0].key == "calibrate"
    assert all("calibrate" in t.deps for t in tasks if t.stage == "slam")
    assert run_project(project, stages=fake_stages).exit_code() == 0
    assert (project.output / "calibration" / "camchain.yaml").is_file()
    # A calibration option changes: everything downstream of it reruns.
    project_file.write_text(
        project_file.read_text() + "stages:\n  calibrate: {estimate_imu: false}\n"
    )
    clear(markers)
    run_project(load_project(project_file), stages=fake_stages)
    assert calls(markers) == sorted(["calibrate", *ALL])


def test_a_session_dive_clock_offset_reaches_only_its_depth_stage(
    tmp_path: Path, fake_stages: dict[str, Any]
) -> None:
    root = tmp_path / "proj"
    path = write_project(root)
    text = path.read_text().replace(
        "    dive: data/dive1.csv\n", "    dive: data/dive1.csv\n    dive_time_offset_s: 289.8\n"
    )
    path.write_text(text)
    project = load_project(path)
    assert [s.dive_time_offset_s for s in project.sessions] == [289.8, None]
    assert run_project(project, stages=fake_stages).exit_code() == 0
    written = {
        name: json.loads(
            json.loads((project.output / "sessions" / name / "depth" / "sync.json").read_text())[
                "options"
            ]
        )
        for name in ("s1", "s2")
    }
    assert written["s1"]["time_offset_s"] == 289.8
    assert written["s2"]["time_offset_s"] is None
    # Changing the offset reruns that session's depth stage (and what reads it) only.
    path.write_text(text.replace("289.8", "290.0"))
    again = run_project(load_project(path), stages=fake_stages)
    assert statuses(again)["depth:s1"] == "done" and statuses(again)["depth:s2"] == "skipped"
    path.write_text(text.replace("289.8", "'soon'"))
    with pytest.raises(InputError, match=r"dive_time_offset_s: expected a number of seconds"):
        load_project(path)
