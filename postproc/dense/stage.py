"""The dense stage: SfM model -> undistorted workspace -> depth maps -> fused.ply -> mesh.ply.

`run(options, sfm_dir, out_dir)` reads a COLMAP binary model (`sfm_dir/sparse`,
`sfm_dir/model`, `sfm_dir/sparse/0` or `sfm_dir` itself) and the images it names
(`options.image_dir`, else `sfm_dir/images` or `sfm_dir/keyframes`), and writes into
`out_dir`:

- `workspace/`: COLMAP's dense workspace (PINHOLE `sparse/` of every image, undistorted
  `images/` of those the stereo reads, `stereo/depth_maps/<name>.geometric.bin`,
  `stereo/normal_maps/...`);
- `fused.ply` (+ `fused.ply.vis`): COLMAP stereo fusion of the depth maps, box by box
  over the reference views' model (`postproc.dense.fusion`);
- `fused_corrected.ply`: the same with underwater colour correction (when asked);
- `fused_supported.ply`: the fused points seen in `mesh_min_images` images or more;
- `mesh.ply`: screened Poisson mesh of those, octree depth from the scene, trimmed, then
  carved where the depth maps saw past it (`postproc.dense.carving`);
- `dense.json`: backend, parameters chosen, counts and timings (s, s per image).

Depth maps come from COLMAP PatchMatch when pycolmap was built with CUDA, else from our
CPU stereo (`postproc.dense.stereo_cpu`). The CPU stereo computes them for reference
views only (`ViewSelectionOptions`: dense work grows with the surveyed surface, not the
keyframe count; every keyframe may be a stereo source, and only the references and their
partners are undistorted), one job per reference through a
map function (`run(..., map_fn=...)`: a process pool or Dask tasks, see
`postproc.pipeline.parallel`), each job writing its maps atomically into the shared
workspace.

The resume rule of every stage (`shared.folders.rebuild`): a complete result of the same
inputs and options is kept, another is refused unless `overwrite`; the run works under a
temporary name beside `out_dir` and is swapped in when complete. Every step skips what
is already there (depth maps per image), so an interrupted run resumes on the next run
with the same inputs and options; `overwrite=True` redoes everything.
"""

from __future__ import annotations

import functools
import logging
import shutil
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from postproc.dense.colmap_io import (
    DenseWorkspace,
    FusionVisibility,
    PinholeView,
    read_array,
    write_array,
)
from postproc.dense.options import DenseOptions as DenseOptions
from postproc.dense.stereo_cpu import CpuStereoOptions
from shared.errors import InputError, StageError
from shared.folders import DenseFolder, SfmFolder, SlamFolder, jsonable, rebuild, result_stamp
from shared.progress import MapFn, serial_map

log = logging.getLogger(__name__)

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")
# Fewer sparse points than this in an image: its depth range falls back to the option.
_MIN_POINTS_FOR_RANGE = 10


def model_dirs(sfm_dir: Path) -> list[Path]:
    """Where an SfM folder may hold its COLMAP model, in the order tried: a COLMAP
    project's own layouts (the .bin files in sparse/ or model/: COLMAP's names, not our
    hand-off names), the SfM stage's model (`SfmFolder.model`), the folder itself."""
    return [sfm_dir / "sparse", sfm_dir / "model", SfmFolder(sfm_dir).model, sfm_dir]


def image_dirs(sfm_dir: Path) -> list[Path]:
    """Where the model's images may be, in the order tried: the SfM stage's images, a
    SLAM folder's keyframes."""
    return [SfmFolder(sfm_dir).images, SlamFolder(sfm_dir).keyframes]


# ----------------------------------------------------------------- inputs


def find_model_dir(sfm_dir: Path) -> Path:
    """The folder of the COLMAP binary model inside an SfM output folder."""
    sfm_dir = Path(sfm_dir)
    if not sfm_dir.is_dir():
        raise InputError(f"{sfm_dir}: no such SfM folder")
    candidates = model_dirs(sfm_dir)
    for candidate in candidates:
        if all((candidate / name).is_file() for name in MODEL_FILES):
            return candidate.resolve() if candidate == sfm_dir else candidate
    subdirs = [c.relative_to(sfm_dir).as_posix() + "/" for c in candidates if c != sfm_dir]
    raise InputError(
        f"{sfm_dir}: no COLMAP model (expected {', '.join(MODEL_FILES)} in one of "
        f"{', '.join(subdirs)} or the folder itself)"
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
    candidates = [Path(image_dir)] if image_dir is not None else image_dirs(Path(sfm_dir))
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
    """Writes geometric depth and normal maps for the reference images of a workspace."""

    def images_needed(
        self, options: DenseOptions, views: list[PinholeView], references: list[int]
    ) -> list[int]:
        """Indices (ascending) of the views whose undistorted images `run` reads."""
        ...

    def run(
        self,
        options: DenseOptions,
        workspace: DenseWorkspace,
        views: list[PinholeView],
        *,
        references: list[int],
        map_fn: MapFn,
    ) -> dict[str, Any]:
        """Compute the missing maps of `views[k]` for k in `references` (indices into
        `views`), per-image work through `map_fn`; returns figures for dense.json."""
        ...


def depth_range_m(view: PinholeView, fallback: tuple[float, float]) -> tuple[float, float]:
    """Depths searched for a view: its sparse points' 1-99 % depths stretched by 25 %
    (COLMAP's rule), or `fallback` when it sees too few points."""
    z = view.point_depths_m()
    if len(z) < _MIN_POINTS_FOR_RANGE:
        return fallback
    lo, hi = np.percentile(z, [1.0, 99.0])
    return float(lo * 0.75), float(hi * 1.25)


def scene_depth_m(view: PinholeView, fallback: tuple[float, float]) -> float:
    """A typical depth of what a view sees: its sparse points' median depth (m), else the
    geometric mean of its depth range."""
    z = view.point_depths_m()
    if len(z):
        return float(np.median(z))
    near, far = depth_range_m(view, fallback)
    return float(np.sqrt(near * far))


def maps_done(workspace: DenseWorkspace, name: str) -> bool:
    return workspace.depth_map_path(name).is_file() and workspace.normal_map_path(name).is_file()


@dataclass(kw_only=True)
class ViewJob:
    """One reference image's depth-map work, as a worker receives it: the workspace path,
    the image names, small matrices and options (the images are read from the shared
    workspace by the worker, never sent).

    Ks: 3x3 intrinsics (px) and cams_from_world: 4x4 `T_C_W` (m) of the reference first,
    then of each source; depth_range_m: (near, far) reference depths searched;
    points_cam_m: (P, 3) sparse points seen by the reference, in its camera frame.
    """

    workspace_dir: Path
    name: str
    source_names: list[str]
    Ks: list[npt.NDArray[np.float64]]
    cams_from_world: list[npt.NDArray[np.float64]]
    depth_range_m: tuple[float, float]
    points_cam_m: npt.NDArray[np.float64]
    stereo: CpuStereoOptions


def compute_view_maps(job: ViewJob) -> dict[str, Any]:
    """Write one reference image's geometric depth and normal maps into the workspace
    (atomically, normals and the pair support first: a depth map on disk means the
    others are there too);
    skips an image whose maps exist (a rerun after a worker died, or a resumed stage).

    Returns {"name", "computed", "seconds", "worker" (host:pid), "sources"}.
    """
    import os
    import socket

    import cv2

    from postproc.dense.stereo_cpu import StereoView, depth_support_map

    workspace = DenseWorkspace(Path(job.workspace_dir))
    worker = f"{socket.gethostname()}:{os.getpid()}"
    result: dict[str, Any] = {
        "name": job.name,
        "computed": False,
        "seconds": 0.0,
        "worker": worker,
        "sources": len(job.source_names),
    }
    if maps_done(workspace, job.name):
        return result
    start = time.perf_counter()
    stereo_views = []
    for name, K, pose in zip(
        [job.name, *job.source_names], job.Ks, job.cams_from_world, strict=True
    ):
        path = workspace.images_dir / name
        pixels = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if pixels is None:
            raise InputError(f"{path}: cannot read the undistorted image")
        image = np.asarray(pixels, dtype=np.uint8)  # IMREAD_GRAYSCALE: 8 bits already
        stereo_views.append(StereoView(image=image, K=K, cam_from_world=pose))
    depth, normals, support = depth_support_map(
        stereo_views[0],
        stereo_views[1:],
        job.depth_range_m,
        job.stereo,
        points_ref_cam=job.points_cam_m,
    )
    write_array(workspace.normal_map_path(job.name), normals, overwrite=True)
    write_array(workspace.support_map_path(job.name), support, overwrite=True)
    write_array(workspace.depth_map_path(job.name), depth, overwrite=True)
    result["computed"] = True
    result["seconds"] = time.perf_counter() - start
    return result


def stereo_partners(
    options: DenseOptions, views: list[PinholeView], references: list[int]
) -> list[list[int]]:
    """Each reference's stereo partners among all views (`select_neighbours`: best for
    its median sparse depth, then for its 90th percentile depth), in `references` order."""
    from postproc.dense.views import select_neighbours

    ranges = [depth_range_m(v, options.fallback_depth_range_m) for v in views]
    typical = [scene_depth_m(v, options.fallback_depth_range_m) for v in views]
    # Far partners are chosen for the 90th percentile depth: the far end of an oblique
    # wall needs a longer baseline than the median depth asks for.
    far = [
        float(np.percentile(v.point_depths_m(), 90.0)) if len(v.point_depths_m()) else r[1]
        for v, r in zip(views, ranges, strict=True)
    ]
    return select_neighbours(
        [v.K for v in views],
        [(v.width, v.height) for v in views],
        [v.cam_from_world for v in views],
        typical,
        options.neighbours,
        far_depths_m=far,
        references=references,
    )


class CpuBackend:
    """Our SGBM stereo on neighbour pairs (`postproc.dense.stereo_cpu`), one job per
    reference image through the map function."""

    def __init__(self) -> None:
        # The views, references and partners last computed: `run` matches the partners
        # `images_needed` had undistorted (seconds of geometry on a long dive, done once).
        self._last: tuple[list[PinholeView], list[int], list[list[int]]] | None = None

    def partners(
        self, options: DenseOptions, views: list[PinholeView], references: list[int]
    ) -> list[list[int]]:
        """`stereo_partners`, computed once for the same views and references."""
        last = self._last
        if last is None or last[0] is not views or last[1] != list(references):
            last = (views, list(references), stereo_partners(options, views, references))
            self._last = last
        return last[2]

    def images_needed(
        self, options: DenseOptions, views: list[PinholeView], references: list[int]
    ) -> list[int]:
        """The references and their stereo partners."""
        needed = set(references)
        for partners in self.partners(options, views, references):
            needed.update(partners)
        return sorted(needed)

    def run(
        self,
        options: DenseOptions,
        workspace: DenseWorkspace,
        views: list[PinholeView],
        *,
        references: list[int],
        map_fn: MapFn,
    ) -> dict[str, Any]:
        ranges = [depth_range_m(v, options.fallback_depth_range_m) for v in views]
        neighbours = self.partners(options, views, references)
        jobs = []
        skipped = 0
        for k, partners in zip(references, neighbours, strict=True):
            view = views[k]
            if maps_done(workspace, view.name):
                skipped += 1
                continue
            pose = view.cam_from_world
            jobs.append(
                ViewJob(
                    workspace_dir=workspace.root,
                    name=view.name,
                    source_names=[views[j].name for j in partners],
                    Ks=[view.K, *[views[j].K for j in partners]],
                    cams_from_world=[pose, *[views[j].cam_from_world for j in partners]],
                    depth_range_m=ranges[k],
                    points_cam_m=view.points_m @ pose[:3, :3].T + pose[:3, 3],
                    stereo=options.stereo,
                )
            )
        start = time.perf_counter()
        results = map_fn(compute_view_maps, jobs) if jobs else []
        wall_s = time.perf_counter() - start
        computed = [r for r in results if r["computed"]]
        seconds = float(sum(r["seconds"] for r in computed))
        workers: dict[str, int] = {}
        for r in computed:
            workers[r["worker"]] = workers.get(r["worker"], 0) + 1
        no_partner = [r["name"] for r in results if r["sources"] == 0]
        if no_partner:
            log.warning(
                "%d images had no stereo partner (no depth): %s",
                len(no_partner),
                ", ".join(no_partner[:5]),
            )
        return {
            "computed": len(computed),
            "skipped": skipped + len(results) - len(computed),
            "seconds": seconds,
            "seconds_per_image": seconds / len(computed) if computed else None,
            "wall_s": wall_s,
            "workers": workers,
            "images_without_partner": len(no_partner),
            "mean_neighbours": float(np.mean([len(n) for n in neighbours])) if neighbours else 0.0,
        }


class PatchMatchBackend:
    """COLMAP's PatchMatch stereo with geometric consistency (needs pycolmap with CUDA)."""

    def images_needed(
        self, options: DenseOptions, views: list[PinholeView], references: list[int]
    ) -> list[int]:
        """Every view: one PatchMatch call reads them all."""
        return list(range(len(views)))

    def run(
        self,
        options: DenseOptions,
        workspace: DenseWorkspace,
        views: list[PinholeView],
        *,
        references: list[int],
        map_fn: MapFn,
    ) -> dict[str, Any]:
        """Every image of the workspace in one PatchMatch call on this machine's GPU (the
        reference selection and the map function do not apply)."""
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


def undistort(
    options: DenseOptions,
    model_dir: Path,
    image_dir: Path,
    workspace_dir: Path,
    *,
    image_names: list[str] | None = None,
) -> None:
    """COLMAP's undistorter into `workspace_dir` (written aside, renamed when complete):
    the PINHOLE model of every registered image, and the images named in `image_names`
    (None: every image)."""
    import pycolmap

    from shared.fsutil import atomic_path

    if image_names is not None and not image_names:
        raise ValueError("name at least one image (COLMAP reads an empty list as all)")
    with atomic_path(workspace_dir) as tmp:
        pycolmap.undistort_images(
            output_path=str(tmp),
            input_path=str(model_dir),
            image_path=str(image_dir),
            image_names=list(image_names or []),
            output_type="COLMAP",
            undistort_options=pycolmap.UndistortCameraOptions(
                max_image_size=options.max_image_size_px
            ),
        )


def undistort_missing(
    model_dir: Path,
    image_dir: Path,
    workspace: DenseWorkspace,
    views: list[PinholeView],
) -> int:
    """Undistort those of `views` whose image is not yet in the workspace, into the
    PINHOLE camera COLMAP chose for it (`postproc.dense.undistort`: one pixel map per
    camera, each image written atomically); returns how many were missing."""
    from postproc.dense.undistort import PinholeTarget, undistort_images
    from shared.progress import progress_bar

    missing = [v for v in views if not (workspace.images_dir / v.name).is_file()]
    if not missing:
        return 0
    targets = {v.name: PinholeTarget.of(v.K, v.width, v.height) for v in missing}
    with progress_bar(total=len(targets), desc="undistort", unit="image") as bar:
        undistort_images(
            model_dir, image_dir, workspace.images_dir, targets, on_done=lambda: bar.update(1)
        )
    return len(missing)


def run(
    options: DenseOptions,
    sfm_dir: Path,
    out_dir: Path,
    *,
    overwrite: bool = False,
    map_fn: MapFn | None = None,
) -> Path:
    """Dense reconstruction of an SfM folder into `out_dir`; returns `mesh.ply` (or
    `fused.ply` when `make_mesh` is off). See the module docstring for the outputs.

    map_fn: how the per-image depth maps are spread, `map_fn(fn, items) -> list` (see
    `postproc.pipeline.parallel`; None: one after another here). The workspace must be
    on a filesystem every worker sees at the same path.
    """
    import pycolmap

    sfm_dir = Path(sfm_dir)
    folder = DenseFolder(out_dir)
    model_dir = find_model_dir(sfm_dir)
    names = registered_image_names(model_dir)
    image_dir = find_image_dir(sfm_dir, names, options.image_dir)
    backend_name = choose_backend(options.backend, has_cuda=bool(pycolmap.has_cuda))
    stamp = result_stamp("dense", options, sfm=sfm_dir, images=image_dir)
    stamp["backend"] = backend_name  # "auto" resolves by the machine's pycolmap
    with rebuild(folder, stamp, overwrite=overwrite, resumable=True) as work:
        if work is not None:
            _build(options, sfm_dir, model_dir, image_dir, names, backend_name, work, map_fn)
    return folder.mesh if options.make_mesh else folder.fused


def _build(
    options: DenseOptions,
    sfm_dir: Path,
    model_dir: Path,
    image_dir: Path,
    names: list[str],
    backend_name: str,
    out: DenseFolder,
    map_fn: MapFn | None,
) -> None:
    """The dense run itself in `out` (resumes what an interrupted run left there)."""
    from postproc.dense.colmap_io import read_pinhole_views
    from postproc.dense.fusion import fuse
    from postproc.dense.meshing import mesh

    workspace = DenseWorkspace(out.workspace)
    fused_ply = out.fused
    corrected_ply = out.fused_corrected
    mesh_ply = out.mesh
    timings: dict[str, float] = {}
    report: dict[str, Any] = {
        "sfm_dir": str(sfm_dir),
        "model_dir": str(model_dir),
        "image_dir": str(image_dir),
        "backend": backend_name,
        "options": jsonable(options),
    }

    start = time.perf_counter()
    backend = BACKENDS[backend_name]()
    if not workspace.is_undistorted():
        # Interrupted while undistorting the model: start the workspace again. The CPU
        # backend undistorts the model and one image here, the images its stereo reads
        # below (PatchMatch reads every image of COLMAP's patch-match.cfg).
        shutil.rmtree(workspace.root, ignore_errors=True)
        first = names[:1] if backend_name == "cpu" else None
        undistort(options, model_dir, image_dir, workspace.root, image_names=first)
    views = read_pinhole_views(workspace.sparse_dir)
    report["images"] = len(views)
    references = reference_views(options, views, backend_name)
    report["reference_images"] = len(references)
    needed = backend.images_needed(options, views, references)
    undistort_missing(model_dir, image_dir, workspace, [views[k] for k in needed])
    report["undistorted_images"] = len(needed)
    timings["undistort_s"] = time.perf_counter() - start

    if map_fn is None:
        map_fn = functools.partial(serial_map, desc="depth maps", unit="image")
    start = time.perf_counter()
    report["depth_maps"] = backend.run(
        options, workspace, views, references=references, map_fn=map_fn
    )
    timings["depth_maps_s"] = time.perf_counter() - start

    start = time.perf_counter()
    if not fused_ply.exists():
        # The references only: the others have no depth map.
        report["fusion"] = fuse(options.fusion, workspace, views, references, fused_ply)
    timings["fusion_s"] = time.perf_counter() - start
    from shared.formats.ply import vertex_ply_header

    report["fused_points"] = vertex_ply_header(fused_ply)[1]

    mesh_input = fused_ply
    if options.colour_correction:
        from postproc.dense.colour import correct_fused

        start = time.perf_counter()
        if not corrected_ply.exists():
            water = correct_fused(options.colour, fused_ply, views, corrected_ply)
            report["colour"] = jsonable(water)
        timings["colour_s"] = time.perf_counter() - start
        mesh_input = corrected_ply

    if options.make_mesh:
        start = time.perf_counter()
        if not mesh_ply.exists() and options.mesh_min_images > 1:
            mesh_input = supported_points(
                mesh_input, out.fused_visibility, out.fused_supported,
                min_images=options.mesh_min_images,
                min_neighbours=options.mesh_single_image_neighbours,
                radius_m=options.mesh_single_image_radius_m,
                min_pairs=options.mesh_single_image_min_pairs,
                near_min_pairs=options.mesh_single_image_near_min_pairs,
                near_range_m=options.mesh_single_image_near_range_m,
                stray_neighbours=options.mesh_stray_neighbours,
                stray_radius_m=options.mesh_stray_radius_m,
                stray_radius_spacings=options.mesh_stray_radius_spacings,
                workspace=workspace, views=views,
            )  # fmt: skip
        if not mesh_ply.exists():
            # With carving, Poisson's mesh goes aside and is carved into place (a rerun
            # after an interruption meshes again).
            carve = options.mesh_carve_min_views > 0
            poisson_ply = mesh_ply.with_name(".poisson." + mesh_ply.name) if carve else mesh_ply
            report["mesh"] = asdict(mesh(options.meshing, mesh_input, poisson_ply, overwrite=carve))
            timings["meshing_s"] = time.perf_counter() - start
            if carve:
                start = time.perf_counter()
                report["mesh"].update(
                    carve_mesh(options, poisson_ply, mesh_ply, workspace, views, references)
                )
                poisson_ply.unlink()
                timings["carving_s"] = time.perf_counter() - start
        else:
            timings["meshing_s"] = time.perf_counter() - start
    report["timings"] = timings
    # dense.json last: the folder's completeness marker.
    out.write_report(report, overwrite=True)


def carve_mesh(
    options: DenseOptions,
    mesh_ply: Path,
    out_ply: Path,
    workspace: DenseWorkspace,
    views: list[PinholeView],
    references: list[int],
) -> dict[str, Any]:
    """Free-space carving (`postproc.dense.carving`) of `mesh_ply` against the depth maps
    of `views[k]`, k in `references`, into `out_ply` (atomic); returns the mesh's new
    "vertices" and "faces" and the "carved_vertices" for dense.json. Raises StageError
    when nothing is left."""
    from postproc.dense.carving import DepthView, carved_vertices
    from postproc.dense.meshing import keep_vertices, write_mesh
    from shared.formats.ply import read_ply

    surface = read_ply(mesh_ply)

    def depth_views() -> Iterator[DepthView]:
        for k in references:
            path = workspace.depth_map_path(views[k].name)
            if path.is_file():
                yield DepthView(read_array(path), views[k].K, views[k].cam_from_world)

    carved = carved_vertices(
        surface.vertices,
        depth_views(),
        tolerance_rel=options.mesh_carve_tolerance_rel,
        min_views=options.mesh_carve_min_views,
    )
    kept = keep_vertices(surface, ~carved)
    faces = write_mesh(
        out_ply,
        kept,
        empty=f"{mesh_ply}: free-space carving removed the whole mesh ({int(carved.sum())} "
        f"of {len(carved)} vertices lie where the depth maps saw past them)",
        overwrite=True,
    )
    return {"vertices": len(kept.vertices), "faces": faces, "carved_vertices": int(carved.sum())}


def reference_views(
    options: DenseOptions, views: list[PinholeView], backend_name: str
) -> list[int]:
    """Indices of the views that get a depth map: `options.view_selection` in name order
    (keyframe names are timestamps, so time order) for the CPU backend; every view for
    PatchMatch (one call computes them all)."""
    from postproc.dense.views import select_reference_views

    if backend_name != "cpu":
        return list(range(len(views)))
    return select_reference_views(
        [v.cam_from_world for v in views],
        [scene_depth_m(v, options.fallback_depth_range_m) for v in views],
        options.view_selection,
        order=sorted(range(len(views)), key=lambda k: views[k].name),
    )


def supported_points(
    fused_ply: Path,
    visibility: Path,
    out_ply: Path,
    *,
    min_images: int,
    min_neighbours: int = 0,
    radius_m: float = 0.05,
    min_pairs: int = 0,
    near_min_pairs: int = 0,
    near_range_m: float = 0.0,
    stray_neighbours: int = 0,
    stray_radius_m: float = 0.05,
    stray_radius_spacings: float = 0.0,
    workspace: DenseWorkspace | None = None,
    views: list[PinholeView] | None = None,
) -> Path:
    """Write the points of `fused_ply` fused from at least `min_images` images (COLMAP's
    `.vis` beside the fused cloud, same point order) to `out_ply` (atomic, overwritten).

    A point seen in fewer images is kept too when either rule keeps it:
    - `min_neighbours` > 0: at least `min_neighbours` other fused points lie within
      `radius_m` (m) of it (a patch of one depth map is surface, a stray depth is alone);
    - `min_pairs` > 0: in each depth map it came from, at least `min_pairs` stereo pairs
      agreed on the depth at its pixel (the CPU stereo's support maps in `workspace`;
      `views` in the workspace's image order, as `.vis` indexes them), so `min_pairs` + 1
      images matched it. A map without support (PatchMatch) keeps nothing by this rule;
    - `near_min_pairs` > 0: the same with `near_min_pairs` pairs for a point no farther
      than `near_range_m` (m) from the cameras of those maps (through water, far surfaces
      lose contrast and a few pairs agree on a wrong depth by chance).

    Then, `stray_neighbours` > 0: of the points kept so far, those with fewer than
    `stray_neighbours` others (also kept) within `stray_radius_m` (m), or within
    `stray_radius_spacings` median point spacings where that is larger (`lone_points`),
    are left out, seen by many images or not: a surface is a patch of points, and
    Poisson grows a blob of surface around each lone point."""
    from postproc.dense.colmap_io import read_fusion_visibility
    from postproc.dense.meshing import lone_points
    from shared.formats.ply import PlyData, read_ply, write_ply

    cloud = read_ply(fused_ply)
    visible = read_fusion_visibility(visibility)
    keep = visible.counts >= min_images
    if len(keep) != len(cloud.vertices):
        raise InputError(
            f"{visibility}: {len(keep)} points, but {fused_ply} has {len(cloud.vertices)}"
        )
    weak = np.flatnonzero(~keep)
    extra = np.zeros(len(keep), bool)
    if min_neighbours > 0 and len(weak):
        from scipy.spatial import cKDTree

        # return_length counts the point itself.
        counts = cKDTree(cloud.vertices).query_ball_point(
            cloud.vertices[weak], radius_m, return_length=True
        )
        extra[weak[np.asarray(counts) - 1 >= min_neighbours]] = True
    if (min_pairs > 0 or near_min_pairs > 0) and len(weak):
        if workspace is None or views is None:
            raise ValueError("the pair-support rule needs the workspace and its views")
        support = pair_support(cloud.vertices[weak], visible.subset(weak), workspace, views)
        if min_pairs > 0:
            extra[weak] |= support.pairs >= min_pairs
        if near_min_pairs > 0:
            extra[weak] |= (support.pairs >= near_min_pairs) & (support.depth_m <= near_range_m)
    keep |= extra
    if not keep.any():
        raise StageError(f"{fused_ply}: no point was fused from {min_images} or more images")
    if stray_neighbours > 0:
        lone = lone_points(
            cloud.vertices[keep], stray_neighbours, stray_radius_m,
            radius_spacings=stray_radius_spacings,
        )  # fmt: skip
        keep[np.flatnonzero(keep)[lone]] = False
        if not keep.any():
            raise StageError(
                f"{fused_ply}: every point has fewer than {stray_neighbours} others within "
                f"{stray_radius_m:g} m or {stray_radius_spacings:g} point spacings"
            )
    kept = PlyData(
        vertices=cloud.vertices[keep],
        normals=None if cloud.normals is None else cloud.normals[keep],
        colors=None if cloud.colors is None else cloud.colors[keep],
    )
    return write_ply(out_ply, kept, overwrite=True)


class PairSupport(NamedTuple):
    """`pair_support`'s answer, one value per point."""

    pairs: npt.NDArray[np.int64]  # fewest stereo pairs agreeing in any of its images
    depth_m: npt.NDArray[np.float64]  # largest depth in those cameras (m; inf: none)


def pair_support(
    points_m: npt.NDArray[np.float64],
    visible: FusionVisibility,
    workspace: DenseWorkspace,
    views: list[PinholeView],
) -> PairSupport:
    """For each point (world, m) and the images it was fused from (`visible[i]` for
    point i): the fewest stereo pairs that agreed on its depth in any of those images'
    support maps, read at the point's projection (the most of the 3x3 pixels around it:
    a fused point averages pixels); 0 when an image has no support map or the point falls
    outside it. Also the point's largest depth in those cameras (inf: none)."""
    import cv2

    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    result = np.full(len(points), np.iinfo(np.int64).max, np.int64)
    result[visible.counts == 0] = 0
    depth = np.full(len(points), -np.inf)
    depth[visible.counts == 0] = np.inf
    owners = visible.point_of_each_image()
    order = np.argsort(visible.images, kind="stable")
    images, starts = np.unique(visible.images[order], return_index=True)
    for k, group in zip(images.tolist(), np.split(order, starts[1:]), strict=True):
        index = owners[group]
        view = views[k]
        cam = points[index] @ view.cam_from_world[:3, :3].T + view.cam_from_world[:3, 3]
        front = cam[:, 2] > 0
        np.maximum.at(depth, index, np.where(front, cam[:, 2], np.inf))
        path = workspace.support_map_path(view.name)
        if not path.is_file():
            result[index] = 0
            continue
        grown = cv2.dilate(read_array(path), np.ones((3, 3), np.uint8))
        z = np.where(front, cam[:, 2], np.nan)
        with np.errstate(invalid="ignore"):
            u = np.floor(view.K[0, 0] * cam[:, 0] / z + view.K[0, 2])
            v = np.floor(view.K[1, 1] * cam[:, 1] / z + view.K[1, 2])
        height, width = grown.shape
        inside = np.isfinite(u) & np.isfinite(v)
        inside &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
        pairs = np.zeros(len(index), np.int64)
        pairs[inside] = grown[v[inside].astype(np.int64), u[inside].astype(np.int64)]
        np.minimum.at(result, index, pairs)
    return PairSupport(pairs=result, depth_m=depth)


def read_depth_map(workspace_dir: Path, image_name: str) -> npt.NDArray[np.float32]:
    """The geometric depth map of one image of a workspace (metres, 0 = none)."""
    return read_array(DenseWorkspace(Path(workspace_dir)).depth_map_path(image_name))
