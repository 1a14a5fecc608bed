"""Find the outputs of a `wreckmap-post run` folder (or of the sfm and dense stages)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from shared.errors import InputError
from shared.folders import DenseFolder, MergeFolder, SfmFolder, SlamFolder

# A run folder holds each project stage's folder under the stage's name (the pipeline's
# layout, `postproc.pipeline.runner`); a stage folder itself is taken as well.
_SFM, _DENSE, _MERGE = "sfm", "dense", "merge"
# After the SfM stage's model (`SfmFolder.model`), other COLMAP model layouts, relative to
# the folder, in the order tried: a COLMAP project's own (the .bin files in sparse/ or
# model/) or the model itself. These are COLMAP's layouts, not our hand-off names.
_COLMAP_MODEL_SUBDIRS = ("sparse", "model", ".")


def _model_dirs(folder: Path) -> list[Path]:
    return [SfmFolder(folder).model, *(folder / sub for sub in _COLMAP_MODEL_SUBDIRS)]


def _image_dirs(folder: Path) -> list[Path]:
    return [SfmFolder(folder).images, SlamFolder(folder).keyframes]


def _expected(root: Path, path: Path) -> str:
    return path.relative_to(root).as_posix()


@dataclass(frozen=True)
class RunFolder:
    """The files an export may read; None where the run has not produced them.

    model_dir: the COLMAP binary model (world frame W, metres); image_dir: the images it
    names (distorted, as recorded); fused_ply, mesh_ply: the dense stage's outputs;
    targets_json: the merge stage's target poses.
    """

    root: Path
    model_dir: Path | None
    image_dir: Path | None
    fused_ply: Path | None
    mesh_ply: Path | None
    targets_json: Path | None

    def need_model(self) -> Path:
        if self.model_dir is None:
            model = _expected(self.root, SfmFolder(self.root / _SFM).model / "images.bin")
            raise InputError(f"{self.root}: no COLMAP model (expected {model})")
        return self.model_dir

    def need_images(self) -> Path:
        if self.image_dir is None:
            images = _expected(self.root, SfmFolder(self.root / _SFM).images)
            raise InputError(f"{self.root}: no keyframe images (expected {images}/)")
        return self.image_dir

    def need_fused(self) -> Path:
        if self.fused_ply is None:
            fused = _expected(self.root, DenseFolder(self.root / _DENSE).fused)
            raise InputError(f"{self.root}: no fused point cloud (expected {fused})")
        return self.fused_ply

    def need_mesh(self) -> Path:
        if self.mesh_ply is None:
            mesh = _expected(self.root, DenseFolder(self.root / _DENSE).mesh)
            raise InputError(f"{self.root}: no mesh (expected {mesh})")
        return self.mesh_ply


def _first(paths: list[Path], test: str) -> Path | None:
    for path in paths:
        if (
            (test == "model" and (path / "images.bin").is_file())
            or (test == "file" and path.is_file())
            or (test == "dir" and path.is_dir() and any(path.iterdir()))
        ):
            return path
    return None


def find_run(root: Path | str) -> RunFolder:
    """Locate the model, images, fused points, mesh and targets under `root`: a run
    folder (`sfm/`, `dense/`, `merge/` inside) or an SfM or dense stage folder itself.

    Raises InputError when `root` is not a folder or holds none of them.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: no such run folder")
    sfm_dirs = [root / _SFM, root]
    model_dir = _first([m for s in sfm_dirs for m in _model_dirs(s)], "model")
    image_dir = _first([i for s in sfm_dirs for i in _image_dirs(s)], "dir")
    dense = [DenseFolder(root / _DENSE), DenseFolder(root)]
    merge = [MergeFolder(root / _MERGE), MergeFolder(root)]
    found = RunFolder(
        root=root,
        model_dir=model_dir.resolve() if model_dir else None,
        image_dir=image_dir,
        fused_ply=_first([d.fused for d in dense], "file"),
        mesh_ply=_first([d.mesh for d in dense], "file"),
        targets_json=_first([m.targets for m in merge], "file"),
    )
    if all(p is None for p in (found.model_dir, found.fused_ply, found.mesh_ply)):
        model = _expected(root, SfmFolder(root / _SFM).model)
        fused, mesh = (_expected(root, path) for path in (dense[0].fused, dense[0].mesh))
        raise InputError(f"{root}: not a run folder (expected {model}, {fused} or {mesh} inside)")
    return found
