"""Find the outputs of a `wreckmap-post run` folder (or of the sfm and dense stages)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from shared.errors import InputError

# Where the SfM stage puts its model, relative to its folder, in the order tried.
_MODEL_SUBDIRS = ("sparse/0", "sparse", "model", ".")
_IMAGE_SUBDIRS = ("images", "keyframes")


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
            raise InputError(f"{self.root}: no COLMAP model (expected sfm/sparse/0/images.bin)")
        return self.model_dir

    def need_images(self) -> Path:
        if self.image_dir is None:
            raise InputError(f"{self.root}: no keyframe images (expected sfm/images/)")
        return self.image_dir

    def need_fused(self) -> Path:
        if self.fused_ply is None:
            raise InputError(f"{self.root}: no fused point cloud (expected dense/fused.ply)")
        return self.fused_ply

    def need_mesh(self) -> Path:
        if self.mesh_ply is None:
            raise InputError(f"{self.root}: no mesh (expected dense/mesh.ply)")
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
    sfm_dirs = [root / "sfm", root]
    model_dir = _first([s / sub for s in sfm_dirs for sub in _MODEL_SUBDIRS], "model")
    image_dir = _first([s / sub for s in sfm_dirs for sub in _IMAGE_SUBDIRS], "dir")
    dense_dirs = [root / "dense", root]
    found = RunFolder(
        root=root,
        model_dir=model_dir.resolve() if model_dir else None,
        image_dir=image_dir,
        fused_ply=_first([d / "fused.ply" for d in dense_dirs], "file"),
        mesh_ply=_first([d / "mesh.ply" for d in dense_dirs], "file"),
        targets_json=_first([root / "merge" / "targets.json", root / "targets.json"], "file"),
    )
    if all(p is None for p in (found.model_dir, found.fused_ply, found.mesh_ply)):
        raise InputError(
            f"{root}: not a run folder (expected sfm/sparse/0, dense/fused.ply or "
            "dense/mesh.ply inside)"
        )
    return found
