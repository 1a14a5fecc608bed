"""The project file: a valid one loads into the stages' option dataclasses; every error
names the file and the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from postproc.pipeline.project import (
    ClusterSpec,
    build_stage_options,
    load_project,
)
from shared.errors import InputError


def test_valid_project_loads_paths_and_nested_options(project_file: Path) -> None:
    extra = """\
stages:
  slam:
    max_frames: 50
    frontend: {}
  depth: {fuse: false, max_offset_s: 3600}
  dense: {fallback_depth_range_m: [0.5, 10]}
cluster: {queue: lab, jobs: 3}
"""
    project_file.write_text(project_file.read_text() + extra)
    project = load_project(project_file)
    root = project_file.parent
    assert project.name == "fake-survey"
    assert project.output == root / "out"
    assert [s.name for s in project.sessions] == ["s1", "s2"]
    assert project.sessions[0].paths == [root / "data" / "s1"]
    assert project.sessions[1].dive == root / "data" / "dive2.csv"
    assert project.targets == [root / "targets" / "grid.yaml"]
    assert project.options_for("slam").max_frames == 50
    assert project.options_for("depth").fuse is False
    assert project.options_for("depth").max_offset_s == 3600.0
    assert project.options_for("dense").fallback_depth_range_m == (0.5, 10.0)
    assert project.options_for("merge").method == "ours"  # defaults when not given
    assert project.cluster == ClusterSpec(queue="lab", jobs=3)


def test_gopro_session_and_calibration(tmp_path: Path) -> None:
    (tmp_path / "GX010001.MP4").write_bytes(b"x")
    (tmp_path / "camchain.yaml").write_text("cam0: {}\n")
    (tmp_path / "p.yaml").write_text(
        "sessions:\n  - {name: d1, gopro: GX010001.MP4}\ncalibration: {camchain: camchain.yaml}\n"
    )
    project = load_project(tmp_path / "p.yaml")
    assert project.sessions[0].source == "gopro"
    assert project.sessions[0].paths == [tmp_path / "GX010001.MP4"]
    assert project.camchain == tmp_path / "camchain.yaml"
    assert project.name == "p" and project.output == tmp_path / "output"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t + "colour: blue\n", r"project.yaml: colour: unknown key"),
        (
            lambda t: t.replace("euroc: data/s1", "euroc: data/nope"),
            r"sessions\[0\].euroc: .*nope does not exist",
        ),
        (
            lambda t: t.replace(
                "    dive: data/dive1.csv\n", "    dive: data/dive1.csv\n    speed: 3\n"
            ),
            r"sessions\[0\].speed: unknown key",
        ),
        (
            lambda t: t.replace("euroc: data/s2", "euroc: data/s2\n    session: data/s1"),
            r"sessions\[1\]: give exactly one of euroc, session, gopro \(found: euroc, session\)",
        ),
        (
            lambda t: t.replace("name: s2", "name: s1"),
            r"sessions\[1\].name: session name 's1' is used twice",
        ),
        (lambda t: t.replace("name: s2", "name: 'a b'"), r"sessions\[1\].name: expected a name"),
        (
            lambda t: t + "stages:\n  depth: {fuse: 'yes'}\n",
            r"stages.depth.fuse: expected true or false, got 'yes'",
        ),
        (
            lambda t: t + "stages:\n  depth: {method: best}\n",
            r"stages.depth.method: expected one of 'ours', 'paper'",
        ),
        (
            lambda t: t + "stages:\n  slam: {frontend: {bogus: 1}}\n",
            r"stages.slam.frontend.bogus: unknown key",
        ),
        (
            lambda t: t + "stages:\n  slam: {max_frames: 1.5}\n",
            r"stages.slam.max_frames: expected int or null",
        ),
        (lambda t: t + "stages:\n  warp: {}\n", r"stages.warp: unknown key"),
        (
            lambda t: t + "stages:\n  dense: {fallback_depth_range_m: [1]}\n",
            r"stages.dense.fallback_depth_range_m: expected a list of 2 values",
        ),
        (
            lambda t: t.replace("targets: [targets/grid.yaml]", "targets: targets/grid.yaml"),
            r"targets: expected a list",
        ),
        (
            lambda t: t.replace("targets: [targets/grid.yaml]", "targets: [targets/none.yaml]"),
            r"targets\[0\]: .*none.yaml does not exist",
        ),
        (lambda t: t + "truth: 3\n", r"truth: expected a path"),
        (lambda t: t + "cluster: {cores: many}\n", r"cluster.cores: expected an integer"),
        (
            lambda t: t.split("sessions:")[0] + "sessions: []\n",
            r"sessions: expected a non-empty list",
        ),
        (
            lambda t: t + "calibration: {recording: data/s1}\n",
            r"calibration.target: missing",
        ),
        (
            lambda t: (
                t
                + "calibration: {recording: data/s1, target: targets/grid.yaml, "
                + "camchain: targets/grid.yaml}\n"
            ),
            r"calibration: give camchain \(known calibration\) or recording",
        ),
        (
            lambda t: t + "calibration: {camchain: nope.yaml}\n",
            r"calibration.camchain: .*nope.yaml does not exist",
        ),
    ],
)
def test_errors_name_the_file_and_the_key(project_file: Path, edit, message: str) -> None:
    project_file.write_text(edit(project_file.read_text()))
    with pytest.raises(
        InputError, match=r"project\.yaml: " + message.removeprefix("project.yaml: ")
    ):
        load_project(project_file)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"missing.yaml: cannot read the project file"):
        load_project(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("sessions: [\n")
    with pytest.raises(InputError, match=r"bad.yaml: not valid YAML"):
        load_project(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("- a\n")
    with pytest.raises(InputError, match=r"list.yaml: expected a mapping"):
        load_project(tmp_path / "list.yaml")


def test_example_project_keys_are_the_real_ones() -> None:
    """deploy/project.example.yaml documents keys the loader accepts (stages, cluster)."""
    import yaml

    from postproc.pipeline.project import dataclass_from_mapping

    path = Path(__file__).resolve().parents[3] / "deploy" / "project.example.yaml"
    document = yaml.safe_load(path.read_text())
    assert set(document) == {
        "name", "output", "calibration", "targets", "truth", "sessions", "stages", "cluster"
    }  # fmt: skip
    for stage, options in document["stages"].items():
        build_stage_options(path, stage, options)
    dataclass_from_mapping(ClusterSpec, document["cluster"], path=path, key="cluster")
    assert {"name", "gopro", "dive"} <= set(document["sessions"][0])
