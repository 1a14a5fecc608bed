"""The stage calls of the pipeline, one small adapter per stage (the only place they are made).

Every adapter has the signature `(options, inputs, out, *, context) -> Path` where
`inputs` maps input names to paths (or lists of paths), `out` is a folder that does not
exist yet (the runner renames it into place when the adapter returns) and `context`
carries project-wide paths (calibration) and how per-image work spreads over the
workers (`parallel`: SfM and dense get a map function, `postproc.pipeline.parallel`).
They run on whichever worker the scheduler picks, so they take only paths and options:
data moves through the shared filesystem.

`import` runs `wreckmap-field gopro import` as a subprocess: the post-processing side
never imports the field package.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from shared.errors import StageError

if TYPE_CHECKING:
    from postproc.pipeline.parallel import MapFn

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class ImportOptions:
    """Options of the GoPro import (`wreckmap-field gopro import`).

    medium: "water" (flat-port housing) or "air", for the intrinsics guess when the
        project gives no calibration.
    require_imu: fail when a chapter has no GPMF IMU data.
    compression: MCAP chunk compression ("none", "zstd", "lz4").
    """

    medium: Literal["water", "air"] = "water"
    require_imu: bool = True
    compression: Literal["none", "zstd", "lz4"] = "none"


def run_calibrate(
    options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]
) -> Path:
    """A calibration recording and its AprilGrid -> `out/camchain.yaml` (Kalibr).

    options: `postproc.pipeline.calibrate_options.CalibrateOptions`."""
    from postproc.calibrate.stage import run_camera, run_imu

    camchain = run_camera(options.camera, inputs["recording"], inputs["target"], out / "camera")
    if options.estimate_imu:
        camchain = run_imu(
            options.imu, inputs["recording"], camchain, inputs["target"], out / "imu"
        )
    shutil.copyfile(camchain, out / "camchain.yaml")
    return out


def run_import(
    options: ImportOptions, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]
) -> Path:
    """GoPro chapters (`inputs["videos"]`) -> a field session folder `out`."""
    command = [
        sys.executable,
        "-m",
        "field.cli",
        "gopro",
        "import",
        *[str(p) for p in inputs["videos"]],
        "--out",
        str(out),
        "--medium",
        options.medium,
        "--compression",
        options.compression,
    ]
    if options.require_imu:
        command.append("--require-imu")
    if context.get("camchain") is not None:
        command += ["--camchain", str(context["camchain"])]
    if context.get("imu_yaml") is not None:
        command += ["--imu-yaml", str(context["imu_yaml"])]
    log.info("running %s", " ".join(command))
    completed = subprocess.run(command, capture_output=True, text=True, check=False)
    for line in (completed.stdout + completed.stderr).splitlines():
        log.info("gopro import: %s", line)
    if completed.returncode != 0:
        tail = (completed.stderr or completed.stdout).strip().splitlines()[-1:] or ["no output"]
        raise StageError(
            f"gopro import of {', '.join(Path(p).name for p in inputs['videos'])} failed "
            f"(exit {completed.returncode}): {tail[0]}"
        )
    if not out.is_dir():
        raise StageError(f"gopro import wrote no session folder at {out}")
    return out


def run_slam(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """A recording (EuRoC or session folder) -> a SLAM result folder `out`."""
    from postproc.slam.stage import run

    return run(
        options,
        inputs["recording"],
        out,
        camchain=context.get("camchain"),
        imu_yaml=context.get("imu_yaml"),
        overwrite=True,
    )


def run_depth(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """A SLAM trajectory and a dive log -> the depth stage folder `out` (sync.json...)."""
    from postproc.depth.stage import run

    run(options, Path(inputs["slam"]) / "trajectory.tum", inputs["dive"], out, overwrite=True)
    return out


def run_merge(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """SLAM folders (each with its depth/ beside) and targets -> the merge folder `out`."""
    from postproc.merge.stage import run

    run(options, list(inputs["slam"]), list(context["targets"]), out, overwrite=True)
    return out


def run_sfm(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """The merge folder (when there is one) and SLAM folders -> the SfM folder `out`."""
    from postproc.sfm.stage import run

    folders = ([Path(inputs["merge"])] if inputs.get("merge") else []) + [
        Path(p) for p in inputs["slam"]
    ]
    run(options, folders, out, overwrite=True, map_fn=stage_map(context))
    return out


def run_dense(options: Any, inputs: dict[str, Any], out: Path, *, context: dict[str, Any]) -> Path:
    """The SfM folder -> the dense folder `out` (fused.ply, mesh.ply, dense.json)."""
    from postproc.dense.stage import run

    run(options, Path(inputs["sfm"]), out, overwrite=True, map_fn=stage_map(context))
    return out


def stage_map(context: dict[str, Any]) -> MapFn:
    """The map function for a stage's per-image work on the backend it runs on."""
    from postproc.pipeline.parallel import make_map

    return make_map(context.get("parallel"))


ADAPTERS = {
    "calibrate": run_calibrate,
    "import": run_import,
    "slam": run_slam,
    "depth": run_depth,
    "merge": run_merge,
    "sfm": run_sfm,
    "dense": run_dense,
}


def check_output(stage: str, out: Path) -> None:
    """Refuse an output folder missing the file that marks the stage as done."""
    marker = {
        "calibrate": "camchain.yaml",
        "slam": "stats.json",
        "depth": "sync.json",
        "merge": "transforms.json",
        "sfm": "stats.json",
        "dense": "dense.json",
        "import": "session.yaml",
    }.get(stage)
    if marker is not None and not (out / marker).is_file():
        raise StageError(f"{stage}: finished without writing {marker} in {out}")
