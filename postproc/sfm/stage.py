"""The SfM stage: one COLMAP model of every session, seeded and held by the SLAM poses.

`run(options, input_dirs, out_dir)` reads SLAM result folders and/or a merge
folder, builds one database (one camera per physical camera, the keyframes as
images, a position prior per placed keyframe), extracts SIFT features within a
budget, matches the pairs chosen from the priors, refines (see
`postproc.sfm.refine`), and writes into `out_dir`:

- `sparse/0/`: the COLMAP binary model (cameras, images, points, rigs, frames),
  in the world frame W, metres;
- `sessions/<name>/keyframes.tum`: refined camera poses with the input's stamps,
  in the input's frame (`T_S_C` for a SLAM folder, `T_W_C` for a merged session),
  and `sessions/<name>/keyframes_world.tum` (`T_W_C`); with one session also
  `keyframes.tum` at the top;
- `transforms.json`: `T_W_S` of every session (given, or fitted for sessions tied
  in by natural features) and whether it is placed;
- `stats.json`: pairs by kind, matches, registered keyframes, reprojection error,
  refinement rounds and the time of each step;
- `database.db`, `pairs.txt` and `images/` (links to the keyframes), which a
  resumed run reuses and the dense stage reads;
- while a run with a `map_fn` works: `features_chunks/` and `matches_chunks/`, one
  `.npz` per worker task, imported into `database.db` and then removed.

The resume rule of every stage (`shared.folders.rebuild`): a finished run of the same
inputs and options is kept, another is refused unless `overwrite`; the run works under
a temporary name beside the output folder and is swapped in when complete. An
interrupted run is resumed there by the next run with the same inputs and options
(features and matches already in the database are kept).
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.sfm.database import KeyframeSet, write_database
from postproc.sfm.features import (
    extract_features,
    extract_features_mapped,
    match_pairs,
    match_pairs_mapped,
    match_statistics,
    write_pairs_file,
)
from postproc.sfm.inputs import SessionInput, read_inputs, read_place_links
from postproc.sfm.options import SfmOptions as SfmOptions
from postproc.sfm.pairs import place_pairs, select_pairs
from postproc.sfm.refine import RefineResult, refine
from shared.calibration.cameras import CameraModel
from shared.errors import InputError, StageError
from shared.folders import MergeFolder, SfmFolder, SlamFolder, rebuild, result_stamp
from shared.fsutil import atomic_path
from shared.geometry import invert_pose
from shared.progress import MapFn
from shared.trajectory import Trajectory

FloatArray = npt.NDArray[np.float64]

log = logging.getLogger(__name__)

# Scratch folders of the worker tasks (removed once imported into the database).
_FEATURES_DIR = "features_chunks"
_MATCHES_DIR = "matches_chunks"


def prior_sigmas_m(
    positions_m: FloatArray, *, floor_m: float, world_sigma_m: float, drift_per_m: float
) -> FloatArray:
    """Per-keyframe prior sigma (N,), metres, growing with the distance travelled."""
    steps = np.linalg.norm(np.diff(positions_m, axis=0), axis=1)
    travelled = np.r_[0.0, np.cumsum(steps)]
    sigmas: FloatArray = np.sqrt(floor_m**2 + world_sigma_m**2 + (drift_per_m * travelled) ** 2)
    return sigmas


def build_keyframes(
    sessions: list[SessionInput], options: SfmOptions
) -> tuple[KeyframeSet, list[CameraModel]]:
    """The keyframe table of all sessions and the distinct cameras."""
    cameras: list[CameraModel] = []
    names: list[str] = []
    sources: list[Path] = []
    session_index: list[int] = []
    camera_index: list[int] = []
    stamps: list[int] = []
    poses: list[FloatArray] = []
    placed: list[bool] = []
    sigmas: list[FloatArray] = []
    for k, session in enumerate(sessions):
        if session.camera not in cameras:
            cameras.append(session.camera)
        c = cameras.index(session.camera)
        T_W_S = session.world_from_session
        local = session.keyframes.poses
        if session.world_keyframes is not None:
            world = session.world_keyframes.poses
        else:
            world = local if T_W_S is None else T_W_S @ local
        for stamp, image in zip(session.keyframes.stamps_ns.tolist(), session.images, strict=True):
            names.append(f"{session.name}/{stamp}.png")
            sources.append(image)
            session_index.append(k)
            camera_index.append(c)
            stamps.append(stamp)
        poses.append(world)
        placed.extend([T_W_S is not None] * len(session.keyframes))
        if options.prior_sigma_m is not None:
            sigmas.append(np.full(len(session.keyframes), options.prior_sigma_m))
        else:
            drift = (
                session.drift_per_m
                if session.drift_per_m is not None
                else options.prior_drift_per_m
            )
            sigmas.append(
                prior_sigmas_m(
                    local[:, :3, 3],
                    floor_m=options.prior_sigma_floor_m,
                    world_sigma_m=session.world_sigma_m,
                    drift_per_m=drift,
                )
            )
    keyframes = KeyframeSet(
        names=names,
        sources=sources,
        session=np.asarray(session_index, dtype=np.int64),
        camera=np.asarray(camera_index, dtype=np.int64),
        stamps_ns=np.asarray(stamps, dtype=np.int64),
        world_from_cam=np.concatenate(poses, axis=0),
        placed=np.asarray(placed, dtype=bool),
        prior_sigma_m=np.concatenate(sigmas),
    )
    return keyframes, cameras


def _link_images(keyframes: KeyframeSet, image_dir: Path, *, copy: bool) -> None:
    for name, source in zip(keyframes.names, keyframes.sources, strict=True):
        target = image_dir / name
        if target.exists():
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        if copy:
            shutil.copyfile(source, target)
            continue
        try:
            target.symlink_to(source.resolve())
        except OSError:
            # Filesystems without symbolic links (some network shares): copy instead.
            shutil.copyfile(source, target)


def _fill_missing(
    keyframes: KeyframeSet, refined: dict[str, FloatArray], prior_world: FloatArray
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Refined `T_W_C` for every keyframe; ones not in the model get the correction of the
    nearest keyframe in time of the same session that is (or their prior if none is)."""
    out = prior_world.copy()
    in_model = np.array([n in refined for n in keyframes.names])
    for i, name in enumerate(keyframes.names):
        if in_model[i]:
            out[i] = refined[name]
    for s in np.unique(keyframes.session):
        members = np.flatnonzero(keyframes.session == s)
        good = members[in_model[members]]
        if good.size == 0:
            continue
        for i in members[~in_model[members]]:
            j = good[np.argmin(np.abs(keyframes.stamps_ns[good] - keyframes.stamps_ns[i]))]
            correction = out[j] @ invert_pose(prior_world[j])
            out[i] = correction @ prior_world[i]
    return out, in_model


def _write_outputs(
    out_dir: SfmFolder,
    sessions: list[SessionInput],
    keyframes: KeyframeSet,
    result: RefineResult,
) -> dict[str, Any]:
    prior_world = keyframes.world_from_cam.copy()
    world_from_session: dict[int, FloatArray] = {}
    for k, session in enumerate(sessions):
        T = (
            session.world_from_session
            if session.world_from_session is not None
            else (result.world_from_session.get(k))
        )
        if T is not None:
            world_from_session[k] = T
            members = keyframes.session == k
            if session.world_from_session is None:
                prior_world[members] = T @ keyframes.world_from_cam[members]
    refined, in_model = _fill_missing(keyframes, result.world_from_cam, prior_world)
    transforms: dict[str, Any] = {}
    session_stats: dict[str, Any] = {}
    for k, session in enumerate(sessions):
        members = np.flatnonzero(keyframes.session == k)
        T = world_from_session.get(k)
        stamps = keyframes.stamps_ns[members]
        if T is not None:
            world = Trajectory(stamps, refined[members])
            out_dir.write_session_keyframes_world(session.name, world, overwrite=True)
            # The input's frame: W for a merged session, S for a SLAM folder.
            local = world if session.source == "merge" else world.transformed(invert_pose(T))
            out_dir.write_session_keyframes(session.name, local, overwrite=True)
            if len(sessions) == 1:
                out_dir.write_keyframes(local, overwrite=True)
            moves = np.linalg.norm(refined[members, :3, 3] - prior_world[members, :3, 3], axis=1)
        else:
            moves = np.zeros(0)
        transforms[session.name] = {
            "folder": str(session.folder),
            "placed": T is not None,
            "placed_by": session.source
            if session.world_from_session is not None
            else ("natural_features" if T is not None else None),
            "T_W_S": T.tolist() if T is not None else None,
        }
        session_stats[session.name] = {
            "keyframes": int(members.size),
            "in_model": int(np.sum(in_model[members])),
            "placed": T is not None,
            "prior_to_refined_rms_m": float(np.sqrt(np.mean(moves**2))) if moves.size else None,
            "prior_to_refined_max_m": float(np.max(moves)) if moves.size else None,
        }
    out_dir.write_transforms(transforms, overwrite=True)
    return session_stats


def run(
    options: SfmOptions,
    input_dirs: list[Path] | list[str],
    out_dir: Path | str,
    *,
    merge: Path | str | None = None,
    overwrite: bool = False,
    map_fn: MapFn | None = None,
) -> Path:
    """Run the SfM stage (see the module docstring); returns the model folder `sparse/0`.

    input_dirs: SLAM result folders (a merge folder among them is recognised too, as on
    the command line); merge: the merge folder placing them in one world frame.

    map_fn: spreads the per-image work over workers: `map_fn(function, items)` must
    return `[function(item) for item in items]` in order (a process pool's or a Dask
    client's map); `function` is a top-level function and the items hold paths and
    options only, so the workers must see `out_dir` and the keyframe images at the same
    paths. Feature extraction goes out in chunks of `options.chunk_images` keyframes and
    matching in chunks of `options.chunk_pairs` pairs; each task writes its result file
    under `out_dir` and the stage imports it into the one database. None: everything
    runs in this process.

    Raises InputError for unreadable or inconsistent inputs, StageError when no model
    can be built, OutputExistsError for another result in the way without `overwrite`.
    """
    start_all = time.perf_counter()
    folder = SfmFolder(out_dir)
    dirs = ([MergeFolder(merge).path] if merge is not None else []) + [Path(d) for d in input_dirs]
    sessions = read_inputs(dirs)
    keyframes, cameras = build_keyframes(sessions, options)
    if len(keyframes) < 3:
        raise InputError(
            f"{len(keyframes)} keyframes in all inputs (expected at least 3 to build a model)"
        )
    timings = {"read_inputs_s": time.perf_counter() - start_all}
    # A SLAM folder's depth stage (inside it or beside it) is an input too.
    depths = [f.path for d in dirs for f in SlamFolder(d).depth_folders() if f.path.is_dir()]
    stamp = result_stamp("sfm", options, inputs=dirs, depth=depths)
    # The places natural-feature merging verified across sessions are matched too, so
    # the adjustment ties the dives together where they overlap.
    links = read_place_links(dirs, sessions)
    with rebuild(folder, stamp, overwrite=overwrite, resumable=True) as work:
        if work is not None:
            _build(options, sessions, keyframes, cameras, work, map_fn, timings, start_all, links)
    return folder.model


def _build(
    options: SfmOptions,
    sessions: list[SessionInput],
    keyframes: KeyframeSet,
    cameras: list[CameraModel],
    out: SfmFolder,
    map_fn: MapFn | None,
    timings: dict[str, float],
    start_all: float,
    links: list[tuple[str, int, str, int]],
) -> None:
    """The SfM run itself in `out` (resumes what an interrupted run left there).

    links: the merge's verified cross-session places (`inputs.read_place_links`).
    """
    image_dir = out.images
    database_path = out.database
    _link_images(keyframes, image_dir, copy=options.copy_images)
    if not database_path.exists():
        with atomic_path(database_path) as tmp:
            write_database(tmp, cameras, keyframes)

    start = time.perf_counter()
    log.info("extracting SIFT features of %d keyframes", len(keyframes))
    longest = max(max(int(c.width), int(c.height)) for c in cameras)
    if map_fn is None:
        extract_features(
            database_path, image_dir, keyframes.names, options.features, longest_side_px=longest
        )
    else:
        extract_features_mapped(
            database_path,
            image_dir,
            keyframes.names,
            options.features,
            longest_side_px=longest,
            features_dir=out.path / _FEATURES_DIR,
            map_fn=map_fn,
            chunk_size=options.chunk_images,
        )
    timings["extract_s"] = time.perf_counter() - start

    start = time.perf_counter()
    pair_set = select_pairs(
        keyframes.world_from_cam,
        keyframes.session,
        keyframes.stamps_ns,
        keyframes.placed,
        options.pairs,
        places=place_pairs(
            keyframes.session, keyframes.stamps_ns, [s.name for s in sessions], links
        )
        if links
        else None,
    )
    names = keyframes.names
    name_pairs = [(names[i], names[j]) for i, j in pair_set.pairs.tolist()]
    pairs_path = write_pairs_file(out.pairs, name_pairs)
    timings["pairs_s"] = time.perf_counter() - start
    log.info("matching %d pairs %s", len(pair_set), pair_set.counts())
    start = time.perf_counter()
    if map_fn is None:
        match_pairs(database_path, pairs_path, options.features)
    else:
        match_pairs_mapped(
            database_path,
            name_pairs,
            options.features,
            matches_dir=out.path / _MATCHES_DIR,
            map_fn=map_fn,
            chunk_size=options.chunk_pairs,
        )
    timings["match_s"] = time.perf_counter() - start
    matches = match_statistics(database_path)
    if matches["verified_pairs"] == 0:
        raise StageError(
            f"{database_path}: no pair of keyframes passed geometric verification (expected "
            "overlapping, textured keyframes)"
        )

    start = time.perf_counter()
    result = refine(database_path, image_dir, out.path / "mapper", keyframes, options.refine)
    timings["refine_s"] = time.perf_counter() - start
    timings.update(result.seconds)
    reconstruction = result.reconstruction
    reconstruction.extract_colors_for_all_images(image_dir)
    with atomic_path(out.model, overwrite=True) as tmp:
        tmp.mkdir(parents=True)
        reconstruction.write_binary(tmp)
    shutil.rmtree(out.path / "mapper", ignore_errors=True)
    session_stats = _write_outputs(out, sessions, keyframes, result)
    timings["total_s"] = time.perf_counter() - start_all
    stats = {
        "keyframes": len(keyframes),
        "sessions": session_stats,
        "cameras": len(cameras),
        "pairs": {"total": len(pair_set), **pair_set.counts()},
        "matches": matches,
        "mapper": result.mapper,
        "registered_images": int(reconstruction.num_reg_images()),
        "points3D": int(reconstruction.num_points3D()),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "rounds": result.rounds,
        "seconds": timings,
        "options": asdict(options),
    }
    # stats.json last: the folder's completeness marker.
    out.write_stats(stats, overwrite=True)
