"""The dense stage: SfM model -> undistorted workspace -> depth maps -> fused.ply -> mesh.ply.

`run(options, sfm_dir, out_dir)` reads a COLMAP binary model (`sfm_dir/sparse`,
`sfm_dir/model`, `sfm_dir/sparse/0` or `sfm_dir` itself) and the images it names
(`options.image_dir`, else `sfm_dir/images` or `sfm_dir/keyframes`), and writes into
`out_dir`:

- `workspace/`: COLMAP's dense workspace (undistorted `images/`, PINHOLE `sparse/`,
  `stereo/depth_maps/<name>.geometric.bin`, `stereo/normal_maps/...`);
- `fused.ply` (+ `fused.ply.vis`): COLMAP stereo fusion of the depth maps;
- `fused_corrected.ply`: the same with underwater colour correction (when asked);
- `mesh.ply`: screened Poisson mesh, octree depth from the scene, trimmed;
- `dense.json`: backend, parameters chosen, counts and timings (s, s per image).

Depth maps come from COLMAP PatchMatch when pycolmap was built with CUDA, else from our
CPU stereo (`postproc.dense.stereo_cpu`). Every step skips what is already on disk (depth
maps per image), so an interrupted run resumes; `overwrite=True` redoes everything.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from postproc.dense.colmap_io import DenseWorkspace, PinholeView, read_array, write_array
from postproc.dense.colour import ColourOptions
from postproc.dense.fusion import FusionOptions
from postproc.dense.meshing import MeshingOptions
from postproc.dense.stereo_cpu import CpuStereoOptions
from postproc.dense.views import NeighbourOptions
from shared.errors import InputError, OutputExistsError, StageError

log = logging.getLogger(__name__)

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")
# Where the SfM stage may have put its model and images, in the order tried.
MODEL_SUBDIRS = ("sparse", "model", "sparse/0", ".")
IMAGE_SUBDIRS = ("images", "keyframes")
# Fewer sparse points than this in an image: its depth range falls back to the option.
_MIN_POINTS_FOR_RANGE = 10
# Undistorted images held in memory at once by the CPU backend.
_IMAGE_CACHE = 24


@dataclass(kw_only=True)
class DenseOptions:
    """What the dense stage does.

    max_image_size_px: longest side of the undistorted images (and so of the depth maps);
    backend: "auto" (PatchMatch when pycolmap has CUDA, else CPU), "cpu" or "patchmatch";
    image_dir: the images the model names (None: look beside the model);
    fallback_depth_range_m: (near, far) camera depths searched by an image that sees too
    few sparse points to know its own; colour_correction: also write
    `fused_corrected.ply` and mesh it; make_mesh: run Poisson meshing.
    """

    max_image_size_px: int = 960
    backend: str = "auto"
    image_dir: Path | None = None
    fallback_depth_range_m: tuple[float, float] = (0.3, 20.0)
    neighbours: NeighbourOptions = field(default_factory=NeighbourOptions)
    stereo: CpuStereoOptions = field(default_factory=CpuStereoOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    meshing: MeshingOptions = field(default_factory=MeshingOptions)
    colour_correction: bool = False
    colour: ColourOptions = field(default_factory=ColourOptions)
    make_mesh: bool = True


# ----------------------------------------------------------------- inputs


def find_model_dir(sfm_dir: Path) -> Path:
    """The folder of the COLMAP binary model inside an SfM output folder."""
    sfm_dir = Path(sfm_dir)
    if not sfm_dir.is_dir():
        raise InputError(f"{sfm_dir}: no such SfM folder")
    for sub in MODEL_SUBDIRS:
        candidate = sfm_dir / sub
        if all((candidate / name).is_file() for name in MODEL_FILES):
            return candidate.resolve() if sub == "." else candidate
    raise InputError(
        f"{sfm_dir}: no COLMAP model (expected {', '.join(MODEL_FILES)} in one of "
        f"{', '.join(s + '/' for s in MODEL_SUBDIRS if s != '.')} or the folder itself)"
    )


def registered_image_names(model_dir: Path) -> list[str]:
    """Names of the images with a pose in the model (raises InputError when none)."""
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as error:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise InputError(f"{model_dir}: cannot read the COLMAP model ({error})") from error
    names = [rec.images[i].name for i in rec.reg_image_ids()]
    if not names:
        raise InputError(f"{model_dir}: the model has no registered images")
    return names


def find_image_dir(sfm_dir: Path, names: list[str], image_dir: Path | None) -> Path:
    """The folder holding every image the model names."""
    candidates = [Path(image_dir)] if image_dir is not None else [
        Path(sfm_dir) / sub for sub in IMAGE_SUBDIRS
    ]  # fmt: skip
    for folder in candidates:
        if folder.is_dir() and (folder / names[0]).is_file():
            missing = [n for n in names if not (folder / n).is_file()]
            if missing:
                raise InputError(
                    f"{folder}: {len(missing)} of {len(names)} images the model names are "
                    f"missing (first: {missing[0]})"
                )
            return folder
    raise InputError(
        f"{sfm_dir}: no images for the model (expected {names[0]} in "
        f"{' or '.join(str(c) for c in candidates)}; pass the image folder)"
    )


# ----------------------------------------------------------------- depth backends


class DepthBackend(Protocol):
    """Writes geometric depth and normal maps for every image of a workspace."""

    def run(
        self, options: DenseOptions, workspace: DenseWorkspace, views: list[PinholeView]
    ) -> dict[str, Any]:
        """Compute the missing maps; returns figures for dense.json."""
        ...


def depth_range_m(view: PinholeView, fallback: tuple[float, float]) -> tuple[float, float]:
    """Depths searched for a view: its sparse points' 1-99 % depths stretched by 25 %
    (COLMAP's rule), or `fallback` when it sees too few points."""
    z = view.point_depths_m()
    if len(z) < _MIN_POINTS_FOR_RANGE:
        return fallback
    lo, hi = np.percentile(z, [1.0, 99.0])
    return float(lo * 0.75), float(hi * 1.25)


def maps_done(workspace: DenseWorkspace, name: str) -> bool:
    return workspace.depth_map_path(name).is_file() and workspace.normal_map_path(name).is_file()


class CpuBackend:
    """Our SGBM stereo on neighbour pairs (`postproc.dense.stereo_cpu`)."""

    def run(
        self, options: DenseOptions, workspace: DenseWorkspace, views: list[PinholeView]
    ) -> dict[str, Any]:
        import cv2

        from postproc.dense.stereo_cpu import StereoView, depth_map
        from postproc.dense.views import select_neighbours
        from shared.progress import progress

        ranges = [depth_range_m(v, options.fallback_depth_range_m) for v in views]
        typical = [
            float(np.median(v.point_depths_m()))
            if len(v.point_depths_m())
            else np.sqrt(r[0] * r[1])
            for v, r in zip(views, ranges, strict=True)
        ]
        # Far partners are chosen for the 90th percentile depth: the far end of an oblique
        # wall needs a longer baseline than the median depth asks for.
        far = [
            float(np.percentile(v.point_depths_m(), 90.0)) if len(v.point_depths_m()) else r[1]
            for v, r in zip(views, ranges, strict=True)
        ]
        neighbours = select_neighbours(
            [v.K for v in views],
            [(v.width, v.height) for v in views],
            [v.cam_from_world for v in views],
            typical,
            options.neighbours,
            far_depths_m=far,
        )
        cache: OrderedDict[int, npt.NDArray[np.uint8]] = OrderedDict()

        def image(k: int) -> npt.NDArray[np.uint8]:
            if k in cache:
                cache.move_to_end(k)
                return cache[k]
            path = workspace.images_dir / views[k].name
            pixels = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if pixels is None:
                raise InputError(f"{path}: cannot read the undistorted image")
            cache[k] = pixels
            if len(cache) > _IMAGE_CACHE:
                cache.popitem(last=False)
            return pixels

        def stereo_view(k: int) -> StereoView:
            return StereoView(image=image(k), K=views[k].K, cam_from_world=views[k].cam_from_world)

        computed, skipped, seconds = 0, 0, 0.0
        no_partner = []
        for k in progress(range(len(views)), total=len(views), desc="depth maps", unit="image"):
            name = views[k].name
            if maps_done(workspace, name):
                skipped += 1
                continue
            start = time.perf_counter()
            if not neighbours[k]:
                no_partner.append(name)
            pose = views[k].cam_from_world
            points_cam = views[k].points_m @ pose[:3, :3].T + pose[:3, 3]
            depth, normals = depth_map(
                stereo_view(k),
                [stereo_view(j) for j in neighbours[k]],
                ranges[k],
                options.stereo,
                points_ref_cam=points_cam,
            )
            # Normals first: a depth map on disk means its normal map is there too.
            write_array(workspace.normal_map_path(name), normals, overwrite=True)
            write_array(workspace.depth_map_path(name), depth, overwrite=True)
            seconds += time.perf_counter() - start
            computed += 1
        if no_partner:
            log.warning(
                "%d images had no stereo partner (no depth): %s",
                len(no_partner),
                ", ".join(no_partner[:5]),
            )
        return {
            "computed": computed,
            "skipped": skipped,
            "seconds": seconds,
            "seconds_per_image": seconds / computed if computed else None,
            "images_without_partner": len(no_partner),
            "mean_neighbours": float(np.mean([len(n) for n in neighbours])),
        }


class PatchMatchBackend:
    """COLMAP's PatchMatch stereo with geometric consistency (needs pycolmap with CUDA)."""

    def run(
        self, options: DenseOptions, workspace: DenseWorkspace, views: list[PinholeView]
    ) -> dict[str, Any]:
        import pycolmap

        if all(maps_done(workspace, v.name) for v in views):
            return {"computed": 0, "skipped": len(views), "seconds": 0.0}
        start = time.perf_counter()
        pycolmap.patch_match_stereo(
            workspace_path=str(workspace.root),
            workspace_format="COLMAP",
            options=pycolmap.PatchMatchOptions(
                max_image_size=options.max_image_size_px, geom_consistency=True
            ),
        )
        seconds = time.perf_counter() - start
        return {
            "computed": len(views),
            "skipped": 0,
            "seconds": seconds,
            "seconds_per_image": seconds / len(views),
        }


BACKENDS: dict[str, type[DepthBackend]] = {"cpu": CpuBackend, "patchmatch": PatchMatchBackend}


def choose_backend(requested: str, *, has_cuda: bool) -> str:
    """The backend to use: "auto" picks PatchMatch when pycolmap has CUDA."""
    if requested == "auto":
        return "patchmatch" if has_cuda else "cpu"
    if requested not in BACKENDS:
        raise ValueError(f"backend must be auto, {' or '.join(BACKENDS)}; got {requested!r}")
    if requested == "patchmatch" and not has_cuda:
        raise StageError(
            "backend 'patchmatch' needs pycolmap built with CUDA (pycolmap.has_cuda is "
            "False here); use 'cpu' or 'auto'"
        )
    return requested


# ----------------------------------------------------------------- the stage


def undistort(options: DenseOptions, model_dir: Path, image_dir: Path, workspace_dir: Path) -> None:
    """COLMAP's undistorter into `workspace_dir` (written aside, renamed when complete)."""
    import pycolmap

    from shared.fsutil import atomic_path

    with atomic_path(workspace_dir) as tmp:
        pycolmap.undistort_images(
            output_path=str(tmp),
            input_path=str(model_dir),
            image_path=str(image_dir),
            output_type="COLMAP",
            undistort_options=pycolmap.UndistortCameraOptions(
                max_image_size=options.max_image_size_px
            ),
        )


def run(options: DenseOptions, sfm_dir: Path, out_dir: Path, *, overwrite: bool = False) -> Path:
    """Dense reconstruction of an SfM folder into `out_dir`; returns `mesh.ply` (or
    `fused.ply` when `make_mesh` is off). See the module docstring for the outputs."""
    import pycolmap

    from postproc.dense.colmap_io import read_pinhole_views
    from postproc.dense.fusion import fuse
    from postproc.dense.meshing import mesh
    from shared.fsutil import write_text_atomic

    sfm_dir, out_dir = Path(sfm_dir), Path(out_dir)
    model_dir = find_model_dir(sfm_dir)
    names = registered_image_names(model_dir)
    image_dir = find_image_dir(sfm_dir, names, options.image_dir)
    backend_name = choose_backend(options.backend, has_cuda=bool(pycolmap.has_cuda))
    out_dir.mkdir(parents=True, exist_ok=True)
    workspace = DenseWorkspace(out_dir / "workspace")
    fused_ply = out_dir / "fused.ply"
    corrected_ply = out_dir / "fused_corrected.ply"
    mesh_ply = out_dir / "mesh.ply"
    report_path = out_dir / "dense.json"
    if overwrite:
        for path in (fused_ply, corrected_ply, mesh_ply, report_path):
            path.unlink(missing_ok=True)
        fused_ply.with_name(fused_ply.name + ".vis").unlink(missing_ok=True)
        shutil.rmtree(workspace.root, ignore_errors=True)
    elif report_path.exists() and (mesh_ply.exists() or not options.make_mesh):
        log.info("%s: already complete (pass overwrite to redo)", out_dir)
        return mesh_ply if options.make_mesh else fused_ply
    timings: dict[str, float] = {}
    report: dict[str, Any] = {
        "sfm_dir": str(sfm_dir),
        "model_dir": str(model_dir),
        "image_dir": str(image_dir),
        "backend": backend_name,
        "options": _jsonable(asdict(options)),
    }

    start = time.perf_counter()
    if not workspace.is_undistorted():
        if workspace.root.exists():
            raise OutputExistsError(
                f"{workspace.root}: exists but is not a complete workspace (pass overwrite)"
            )
        undistort(options, model_dir, image_dir, workspace.root)
    _check_workspace_size(workspace, options.max_image_size_px)
    timings["undistort_s"] = time.perf_counter() - start
    views = read_pinhole_views(workspace.sparse_dir)
    report["images"] = len(views)

    start = time.perf_counter()
    report["depth_maps"] = BACKENDS[backend_name]().run(options, workspace, views)
    timings["depth_maps_s"] = time.perf_counter() - start

    start = time.perf_counter()
    if not fused_ply.exists():
        fuse(options.fusion, workspace.root, fused_ply)
    timings["fusion_s"] = time.perf_counter() - start
    from postproc.dense.ply import read_ply

    report["fused_points"] = len(read_ply(fused_ply).vertices)

    mesh_input = fused_ply
    if options.colour_correction:
        from postproc.dense.colour import correct_fused

        start = time.perf_counter()
        if not corrected_ply.exists():
            water = correct_fused(options.colour, fused_ply, views, corrected_ply)
            report["colour"] = _jsonable(asdict(water))
        timings["colour_s"] = time.perf_counter() - start
        mesh_input = corrected_ply

    result = fused_ply
    if options.make_mesh:
        start = time.perf_counter()
        if not mesh_ply.exists():
            report["mesh"] = asdict(mesh(options.meshing, mesh_input, mesh_ply))
        timings["meshing_s"] = time.perf_counter() - start
        result = mesh_ply
    report["timings"] = timings
    write_text_atomic(report_path, json.dumps(report, indent=2) + "\n", overwrite=True)
    return result


def _check_workspace_size(workspace: DenseWorkspace, max_image_size_px: int) -> None:
    """Refuse to resume a workspace undistorted at another image size."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(workspace.sparse_dir))
    longest = max(max(c.width, c.height) for c in rec.cameras.values())
    if max_image_size_px > 0 and longest > max_image_size_px:
        raise OutputExistsError(
            f"{workspace.root}: undistorted at {longest} px, larger than the "
            f"{max_image_size_px} px asked (pass overwrite to redo)"
        )


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def read_depth_map(workspace_dir: Path, image_name: str) -> npt.NDArray[np.float32]:
    """The geometric depth map of one image of a workspace (metres, 0 = none)."""
    return read_array(DenseWorkspace(Path(workspace_dir)).depth_map_path(image_name))
