"""Options declared once: flags, the example project file and help from the dataclasses."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from postproc.pipeline.options import (
    Flag,
    add_flags,
    example_text,
    field_docs,
    options_from_args,
    stages_example,
    unit_of,
)

REPO = Path(__file__).resolve().parents[3]
EXAMPLE = REPO / "deploy" / "project.example.yaml"


@dataclass(kw_only=True)
class Inner:
    """Inner group.

    radius_m: how far to look.
    """

    radius_m: float = 1.5


@dataclass(kw_only=True)
class Toy:
    """A toy options class.

    mode: "fast" or "slow", the
        whole story on two lines.
    window_s / step_s: the search window and its step.
    enabled: do it at all.
    """

    mode: Literal["fast", "slow"] = "fast"
    window_s: float | None = 300.0
    step_s: float = 1.0
    enabled: bool = True
    count: int = field(default=3, metadata={"help": "how many, from the metadata"})
    inner: Inner = field(default_factory=Inner)


FLAGS = [
    Flag(field="mode"),
    Flag(field="window_s", flag="--window", zero_is_none=True),
    Flag(field="enabled", flag="--off", negate=True),
    Flag(field="count"),
    Flag(field="inner.radius_m", flag="--radius"),
]


def _parse(argv: list[str]) -> Toy:
    parser = argparse.ArgumentParser()
    add_flags(parser, Toy, FLAGS)
    return options_from_args(Toy, parser.parse_args(argv), FLAGS)  # type: ignore[no-any-return]


def test_the_example_project_file_is_current() -> None:
    """deploy/project.example.yaml's stages: section is what the dataclasses declare
    (`wreckmap-post options --write-example deploy/project.example.yaml` updates it)."""
    assert EXAMPLE.read_text(encoding="utf-8") == example_text(EXAMPLE)


def test_every_stage_key_is_in_the_example_with_its_default() -> None:
    import yaml

    from postproc.pipeline.project import build_stage_options
    from postproc.pipeline.stages import STAGES

    document = yaml.safe_load(stages_example())["stages"]
    assert list(document) == list(STAGES)
    for name, values in document.items():
        options = build_stage_options(EXAMPLE, name, values)
        assert options == STAGES[name].options_type()(), name


def test_help_comes_from_the_docstring_or_the_metadata() -> None:
    docs = field_docs(Toy)
    assert docs["mode"] == '"fast" or "slow", the whole story on two lines.'
    assert docs["window_s"] == docs["step_s"] == "the search window and its step."
    assert docs["count"] == "how many, from the metadata"
    assert docs["inner"] == ""
    assert (unit_of("window_s"), unit_of("rate_m_s"), unit_of("count")) == ("s", "m/s", None)


def test_flags_follow_the_fields() -> None:
    assert _parse([]) == Toy()
    parsed = _parse(["--mode", "slow", "--window", "0", "--off", "--count", "5", "--radius", "2"])
    assert parsed == Toy(
        mode="slow", window_s=None, enabled=False, count=5, inner=Inner(radius_m=2)
    )
    assert _parse(["--window", "12.5"]).window_s == 12.5
    with pytest.raises(SystemExit):
        _parse(["--mode", "medium"])
    parser = argparse.ArgumentParser()
    add_flags(parser, Toy, FLAGS)
    text = " ".join(parser.format_help().split())
    assert "{fast,slow}" in text and "(s; default: 300.0); 0: none" in text
    assert "turn off: do it at all" in text
    with pytest.raises(ValueError, match="negate must match"):
        add_flags(argparse.ArgumentParser(), Toy, [Flag(field="enabled")])


def test_the_depth_command_keeps_its_flags_and_defaults() -> None:
    from postproc.commands.depth import DEPTH_FLAGS, _options_type

    depth_options = _options_type()
    parser = argparse.ArgumentParser()
    add_flags(parser, depth_options, DEPTH_FLAGS)
    assert options_from_args(depth_options, parser.parse_args([]), DEPTH_FLAGS) == (depth_options())
    argv = ["--method", "paper", "--time-offset", "289.8", "--max-offset", "100", "--no-drift",
            "--estimate-scale", "--no-fuse", "--no-plot", "--depth-sigma", "0.1",
            "--clock-window", "0", "--min-evidence", "8",
            "--trajectory-format", "svin"]  # fmt: skip
    options = options_from_args(depth_options, parser.parse_args(argv), DEPTH_FLAGS)
    assert options == depth_options(
        method="paper",
        time_offset_s=289.8,
        max_offset_s=100.0,
        estimate_drift=False,
        estimate_scale=True,
        fuse=False,
        plot=False,
        depth_sigma_m=0.1,
        clock_prior_window_s=None,
        min_evidence=8.0,
        trajectory_format="svin",
    )


def test_options_command_prints_and_rewrites_the_example(tmp_path: Path) -> None:
    import subprocess
    import sys

    command = [sys.executable, "-m", "postproc.cli", "options"]
    printed = subprocess.run(command, cwd=REPO, capture_output=True, text=True, check=True)
    assert printed.stdout == stages_example()
    stale = tmp_path / "project.yaml"
    stale.write_text(
        EXAMPLE.read_text(encoding="utf-8").replace("max_offset_s: 54000.0", "max_offset_s: 1")
    )
    done = subprocess.run(
        [*command, "--write-example", str(stale)], cwd=REPO, capture_output=True, text=True
    )
    assert done.returncode == 0 and "updated" in done.stdout
    assert stale.read_text(encoding="utf-8") == EXAMPLE.read_text(encoding="utf-8")


def test_the_merge_command_keeps_its_flags_and_defaults() -> None:
    from postproc.commands.merge import MERGE_FLAGS, _options_type

    merge_options = _options_type()
    parser = argparse.ArgumentParser()
    add_flags(parser, merge_options, MERGE_FLAGS)

    def parse(*argv: str) -> object:
        return options_from_args(merge_options, parser.parse_args(list(argv)), MERGE_FLAGS)

    assert parse() == merge_options()
    options = parse("--dof", "4", "--no-natural-features", "--depth-fused", "--no-plot",
                    "--no-drift-weighting", "--tilt-sigma-deg", "0.05", "--reference", "dive2",
                    "--method", "paper", "--min-tags", "3", "--camera", "cam1")  # fmt: skip
    assert options == merge_options(
        dof=4,
        natural_features=False,
        depth_fused=True,
        plot=False,
        drift_weighting=False,
        tilt_sigma_deg=0.05,
        reference="dive2",
        method="paper",
        min_tags=3,
        camera="cam1",
    )
    assert parse("--natural-features", "--no-depth-fused") == merge_options(
        natural_features=True, depth_fused=False
    )
    with pytest.raises(SystemExit):  # one or the other, never both
        parse("--natural-features", "--no-natural-features")
    with pytest.raises(SystemExit):
        parse("--dof", "5")


def test_the_slam_command_keeps_its_flags_and_defaults() -> None:
    from postproc.commands.slam import SLAM_FLAGS, _options_type

    slam_options = _options_type()
    parser = argparse.ArgumentParser()
    add_flags(parser, slam_options, SLAM_FLAGS)

    def parse(*argv: str) -> object:
        return options_from_args(slam_options, parser.parse_args(list(argv)), SLAM_FLAGS)

    assert parse() == slam_options()
    options = parse("--width", "640", "--no-imu", "--max-frames", "50", "--max-speed", "0",
                    "--gyro-check", "off")  # fmt: skip
    assert options.frontend.width_px == 640  # type: ignore[attr-defined]
    assert options == slam_options(
        frontend=type(slam_options().frontend)(width_px=640),
        use_imu=False,
        max_frames=50,
        max_speed_m_s=None,
        gyro_check="off",
    )
    assert parse("--max-speed", "2.5").max_speed_m_s == 2.5  # type: ignore[attr-defined]
    assert parse("--estimator-process", "on").estimator_process == "on"  # type: ignore[attr-defined]
    with pytest.raises(SystemExit):
        parse("--gyro-check", "maybe")
    with pytest.raises(SystemExit):
        parse("--estimator-process", "maybe")


def test_the_dense_command_keeps_its_flags_and_defaults() -> None:
    from postproc.commands.dense import DENSE_FLAGS, _options_type, dense_options
    from postproc.dense.options import ColourOptions, FusionOptions, MeshingOptions

    options_type = _options_type()
    parser = argparse.ArgumentParser()
    add_flags(parser, options_type, DENSE_FLAGS)
    assert dense_options(parser.parse_args([])) == options_type()
    argv = ["--images", "imgs", "--max-image-size", "640", "--backend", "cpu",
            "--octree-depth", "9", "--no-mesh", "--attenuation", "0.4", "0.13", "0.11",
            "--backscatter", "0.1", "0.2", "0.3", "--threads", "2"]  # fmt: skip
    assert dense_options(parser.parse_args(argv)) == options_type(
        image_dir=Path("imgs"),
        max_image_size_px=640,
        backend="cpu",
        make_mesh=False,
        colour_correction=True,  # a known attenuation turns it on
        colour=ColourOptions(attenuation_per_m=(0.4, 0.13, 0.11), backscatter=(0.1, 0.2, 0.3)),
        fusion=FusionOptions(num_threads=2),
        meshing=MeshingOptions(octree_depth=9, num_threads=2),
    )
    assert dense_options(parser.parse_args(["--colour-correction"])).colour_correction
    with pytest.raises(SystemExit):
        parser.parse_args(["--attenuation", "0.4", "0.13"])


def test_the_calibrate_commands_keep_their_flags_and_defaults() -> None:
    from postproc.calibrate.options import (
        CameraCalibrationOptions,
        CameraImuOptions,
        FrameSelectionOptions,
        ImuCalibrationOptions,
        IntrinsicsOptions,
        RigCalibrationOptions,
        RigSyncOptions,
    )
    from postproc.commands.calibrate import CAMERA_FLAGS, IMU_FLAGS, RIG_FLAGS

    def parse(cls: type, flags: list[Flag], *argv: str) -> object:
        parser = argparse.ArgumentParser()
        add_flags(parser, cls, flags)
        return options_from_args(cls, parser.parse_args(list(argv)), flags)

    assert parse(CameraCalibrationOptions, CAMERA_FLAGS) == CameraCalibrationOptions()
    camera = parse(CameraCalibrationOptions, CAMERA_FLAGS, "--model", "pinhole-equidistant",
                   "--topic", "/cam1/video", "--max-frames", "20", "--rate", "0",
                   "--fix-principal-point", "--fix-aspect-ratio", "--no-distortion",
                   "--min-views", "5")  # fmt: skip
    assert camera == CameraCalibrationOptions(
        topic="/cam1/video",
        max_candidate_rate_hz=0.0,
        selection=FrameSelectionOptions(max_frames=20),
        intrinsics=IntrinsicsOptions(
            model="pinhole-equidistant",
            fix_principal_point=True,
            fix_aspect_ratio=True,
            zero_distortion=True,
            min_views=5,
        ),
    )
    with pytest.raises(SystemExit):
        parse(CameraCalibrationOptions, CAMERA_FLAGS, "--model", "omni")

    assert parse(ImuCalibrationOptions, IMU_FLAGS) == ImuCalibrationOptions()
    imu = parse(ImuCalibrationOptions, IMU_FLAGS, "--camera", "1", "--topic", "/cam1/video",
                "--imu-topic", "/imu1", "--max-timeshift", "0.2", "--no-features",
                "--stride", "3")  # fmt: skip
    assert imu == ImuCalibrationOptions(
        camera_index=1,
        topic="/cam1/video",
        imu_topic="/imu1",
        use_features=False,
        frame_stride=3,
        estimate=CameraImuOptions(max_timeshift_s=0.2),
    )

    assert parse(RigCalibrationOptions, RIG_FLAGS) == RigCalibrationOptions()
    rig = parse(RigCalibrationOptions, RIG_FLAGS, "--imu-topic0", "/imu0", "--imu-topic1",
                "/imu1", "--max-offset", "10", "--prior-offset", "-2.5")  # fmt: skip
    assert rig == RigCalibrationOptions(
        imu_topic1="/imu1", sync=RigSyncOptions(max_offset_s=10.0, prior_offset_s=-2.5)
    )
