"""Triangulate with the prior poses, then bundle-adjust with pose priors (pycolmap, CPU).

The reconstruction is seeded with every placed keyframe at its prior pose
`T_W_C`, registered and triangulated from the verified matches one keyframe at a time
in keyframe order (`_seeded`), and rounds of COLMAP's iterative global refinement follow
(complete and merge tracks, retriangulate, global bundle adjustment with a
position prior on every keyframe, filter observations) until 95 % of the
cameras move less than `converged_change_m` in a round, the similarity common to all
moves taken out. The position priors keep the metric scale and the world frame;
without them the gauge would float.

Two passes build the tracks. The first pass triangulates at the prior poses with
thresholds wider than COLMAP's defaults (2 degrees): with drifting priors, the
rays of one point seen from two ends of a loop miss each other by the drift
over the viewing distance (0.2 m at 2 m is about 6 degrees), and default
thresholds break such tracks instead of closing the loop. Its rounds run only
until the cameras move less than the error the default thresholds tolerate
(`RefineOptions.first_pass_converged_change_m`). Wide thresholds also let
wrong observations into the tracks (merged at 8 px, continued at 8 degrees)
which the 4 px filters keep, and they bias the adjustment: on the simulated
surveys (bench/bench_sfm.py) the shape stayed up to 50 % worse than COLMAP's
incremental mapper on the same matches, and loosening the priors tenfold made
it worse still (the priors' weight is not the cause). So the rebuild pass
throws those tracks away and rebuilds them at the refined poses with COLMAP's
default reprojection thresholds (and 1 degree to continue a track), then adjusts again,
with the same priors, until converged. The first pass's last round therefore skips the
track upkeep after its adjustment.

Each adjustment sees at most `RefineOptions.ba_max_track_length` observations of a
point (`cap_tracks`, evenly spread over the track's keyframes); the track completion
right after it adds the rest back. On a dive that keeps revisiting the wreck the tracks
lengthen with the dive and an adjustment's cost per keyframe grows with them; the
cap bounds that growth.

The adjustments take dogleg steps (`RefineOptions.ba_trust_region`). Every adjustment
with priors first re-aligns the whole model to the priors (COLMAP fits a similarity to
the prior positions), and where the priors are loose, as at the end of a long dive, only
they hold the model's placement; Levenberg-Marquardt's damping all but froze that
placement, so its adjustments ran out of iterations while the cameras still moved
together by decimetres to metres, and the rounds went on (on bench_sfm.py's 10-minute
dive the third round moved the cameras by 82 cm, 3 cm of it a change of shape).
`shape_moves_m` tells the two apart in the round records.

Each adjustment also stops once an iteration no longer lowers the chi-square of its
observations by `RefineOptions.ba_chi2_tolerance` (a relative cost change scaled by the
number of residuals): COLMAP's absolute gradient rule is rarely met by a large problem,
and on a long dive every adjustment ran to its iteration limit for gains far below the
reprojection noise.

Sessions without a world pose (no shared target in the merge) are tied in
where natural features allow: their keyframes are registered one by one by
absolute pose estimation against the model (COLMAP's incremental
registration), the session's `T_W_S` is fitted to the registered keyframes,
and a second refinement runs with every session placed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from postproc.sfm.database import (
    KeyframeSet,
    pose_from_rigid3d,
    pose_prior,
    rigid3d_from_pose,
)
from postproc.sfm.options import RefineOptions as RefineOptions
from shared.errors import StageError
from shared.geometry import invert_pose, make_pose, umeyama

if TYPE_CHECKING:
    import pycolmap

FloatArray = npt.NDArray[np.float64]

log = logging.getLogger(__name__)


@dataclass
class RefineResult:
    """The refined model and what happened.

    world_from_cam: refined `T_W_C` (4, 4) of every keyframe in the model, by image name.
    world_from_session: `T_W_S` fitted for sessions that were not placed and could be
        tied in, by session index. rounds: one record per refinement round (seconds,
        largest camera move in metres, points, mean reprojection error in pixels,
        `rebuilt_tracks` 1.0 in the rebuild pass).
    mapper: which mapper produced the model ("prior" or "incremental").
    """

    reconstruction: Any
    world_from_cam: dict[str, FloatArray]
    world_from_session: dict[int, FloatArray] = field(default_factory=dict)
    rounds: list[dict[str, float]] = field(default_factory=list)
    mapper: str = "prior"
    seconds: dict[str, float] = field(default_factory=dict)


def _pipeline_options(
    options: RefineOptions, *, use_priors: bool, rebuilt: bool = False
) -> pycolmap.IncrementalPipelineOptions:
    """COLMAP's options from ours; `rebuilt`: the rebuild pass's (default) thresholds."""
    import pycolmap

    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.use_prior_position = use_priors
    pipeline.use_robust_loss_on_prior_position = options.robust_prior_loss
    pipeline.ba_refine_focal_length = options.refine_intrinsics
    pipeline.ba_refine_extra_params = options.refine_intrinsics
    pipeline.ba_refine_principal_point = False
    pipeline.min_num_matches = options.min_num_matches
    pipeline.num_threads = options.num_threads
    pipeline.random_seed = options.random_seed
    pipeline.extract_colors = False
    pipeline.mapper.filter_max_reproj_error = options.filter_max_reproj_error_px
    pipeline.mapper.filter_min_tri_angle = options.filter_min_tri_angle_deg
    # Solve first without the points that add little coverage, then those alone.
    pipeline.mapper.ba_global_ignore_redundant_points3D = options.skip_redundant_points
    pipeline.mapper.ba_global_prune_points_min_coverage_gain = options.redundant_min_coverage_gain
    tri = pipeline.triangulation
    angle_deg = options.rebuilt_max_angle_deg if rebuilt else options.triangulation_max_angle_deg
    merge_px = (
        options.rebuilt_merge_max_reproj_error_px if rebuilt else options.merge_max_reproj_error_px
    )
    tri.create_max_angle_error = angle_deg
    tri.continue_max_angle_error = angle_deg
    tri.re_max_angle_error = max(angle_deg, tri.re_max_angle_error)
    tri.merge_max_reproj_error = merge_px
    tri.complete_max_reproj_error = merge_px
    tri.ignore_two_view_tracks = options.ignore_two_view_tracks
    return pipeline


def _load_cache(database_path: Path, options: RefineOptions) -> pycolmap.DatabaseCache:
    import pycolmap

    cache_options = pycolmap.DatabaseCacheOptions()
    cache_options.min_num_matches = options.min_num_matches
    cache_options.load_all_images = True
    with pycolmap.Database.open(database_path) as db:
        return pycolmap.DatabaseCache.create(db, cache_options)


def camera_poses(reconstruction: pycolmap.Reconstruction) -> dict[str, FloatArray]:
    """`T_W_C` of every image with a pose, by image name."""
    poses: dict[str, FloatArray] = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            poses[image.name] = invert_pose(pose_from_rigid3d(image.cam_from_world()))
    return poses


def _seeded(
    cache: pycolmap.DatabaseCache,
    world_from_cam: dict[str, FloatArray],
    tri_options: pycolmap.IncrementalTriangulatorOptions,
) -> tuple[pycolmap.Reconstruction, int]:
    """All cached images, the given ones registered at their poses (trivial rigs) one at a
    time in image order (the order the keyframes were written, in time per session), each
    triangulated as it is registered; the model and the observations triangulated.

    COLMAP's triangulation only looks at registered images. With every keyframe
    registered first, each image created tracks from its correspondences in images not
    yet triangulated while continuing one existing track, so one physical point came out
    in many short tracks (226 000 points of 3.9 observations on bench_pipeline's
    10-minute dive) that track merging then joined one merge at a time, each merge
    re-checking the whole grown track: 14 s there against 1.5 s at 3 minutes. Registered
    in order, an image continues the tracks of the keyframes before it (55 000 points,
    and merging took 1.6 s).
    """
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    reconstruction.load(cache)
    observations = pycolmap.ObservationManager(reconstruction, cache.correspondence_graph)
    triangulator = pycolmap.IncrementalTriangulator(
        cache.correspondence_graph, reconstruction, observations
    )
    triangulated = 0
    for image_id in sorted(reconstruction.images):
        image = reconstruction.image(image_id)
        pose = world_from_cam.get(image.name)
        if pose is None:
            continue
        frame = reconstruction.frame(image.frame_id)
        if not frame.has_pose():
            frame.rig_from_world = rigid3d_from_pose(invert_pose(pose))
            observations.register_frame(image.frame_id)
        triangulated += triangulator.triangulate_image(tri_options, image_id)
    return reconstruction, triangulated


def _camera_moves_m(before: dict[str, FloatArray], after: dict[str, FloatArray]) -> FloatArray:
    """Distances (m) the centres of the cameras present in both moved."""
    common = sorted(before.keys() & after.keys())
    return np.array([float(np.linalg.norm(after[n][:3, 3] - before[n][:3, 3])) for n in common])


def shape_moves_m(before: dict[str, FloatArray], after: dict[str, FloatArray]) -> FloatArray:
    """Distances (m) the centres of the cameras present in both moved once the similarity
    that best maps the old centres onto the new ones is taken out: how much the shape of
    the path changed, not where the path as a whole went (every adjustment with priors
    first re-aligns the whole model to the priors, a common similarity)."""
    common = sorted(before.keys() & after.keys())
    if len(common) < 3:
        return _camera_moves_m(before, after)
    old = np.array([before[n][:3, 3] for n in common])
    new = np.array([after[n][:3, 3] for n in common])
    try:
        R, t, scale = umeyama(old, new, with_scale=True)
    except ValueError:
        return _camera_moves_m(before, after)
    return np.asarray(np.linalg.norm(scale * old @ R.T + t - new, axis=1), dtype=np.float64)


def evenly_spaced(count: int, keep: int) -> list[int]:
    """`keep` indices of `range(count)` spread evenly, the first and the last included
    (all of them when `keep >= count`)."""
    if keep >= count:
        return list(range(count))
    if keep == 1:
        return [0]
    return sorted({round(k * (count - 1) / (keep - 1)) for k in range(keep)})


def cap_tracks(
    reconstruction: pycolmap.Reconstruction,
    observation_manager: pycolmap.ObservationManager,
    max_length: int,
) -> int:
    """Drop observations of tracks longer than `max_length`; the number dropped.

    Each long track keeps `max_length` observations spread evenly over its keyframes in
    image order (the order the keyframes were written, in time per session), so a point
    seen on several passes still ties them together. No point is deleted (`max_length`
    >= 2). The dropped observations are only out of the model until the next track
    completion, which adds back those that reproject well.
    """
    dropped = 0
    for point3D_id in reconstruction.point3D_ids():
        track = reconstruction.point3D(point3D_id).track
        if track.length() <= max_length:
            continue
        elements = sorted((e.image_id, e.point2D_idx) for e in track.elements)
        kept = set(evenly_spaced(len(elements), max_length))
        for index, (image_id, point2D_idx) in enumerate(elements):
            if index not in kept:
                observation_manager.delete_observation(image_id, point2D_idx)
                dropped += 1
    return dropped


def function_tolerance(floor: float, chi2_tolerance: float | None, observations: int) -> float:
    """Ceres's relative cost tolerance that stops an adjustment once an iteration lowers the
    chi-square of `observations` observations (2 residuals each) by less than
    `chi2_tolerance`, and never below `floor`.

    With N residuals of noise sigma, chi2 = 2 cost / sigma^2 and sigma^2 is about
    2 cost / N, so a change of chi2 by c is a relative change of the cost by c / N.
    """
    if chi2_tolerance is None or observations <= 0:
        return floor
    return max(floor, chi2_tolerance / (2.0 * observations))


class _Mapper:
    """One pycolmap mapper over one database cache (both must live together)."""

    def __init__(
        self,
        database_path: Path,
        world_from_cam: dict[str, FloatArray],
        options: RefineOptions,
        *,
        rebuilt: bool = False,
    ) -> None:
        import pycolmap

        self.options = options
        self.rebuilt = rebuilt
        self.cache = _load_cache(database_path, options)
        self.pipeline = _pipeline_options(options, use_priors=True, rebuilt=rebuilt)
        self.mapper_options = self.pipeline.get_mapper()
        self.tri_options = self.pipeline.get_triangulation()
        self.reconstruction, self.triangulated = _seeded(
            self.cache, world_from_cam, self.tri_options
        )
        if self.reconstruction.num_reg_frames() < 2:
            raise StageError(
                f"{database_path}: fewer than 2 keyframes with matches and a prior pose "
                "(expected overlapping keyframes; check the images and the pair choice)"
            )
        self.ba_options = self.pipeline.get_global_bundle_adjustment()
        self.ba_options.print_summary = False
        # COLMAP's global-BA stopping rules by default: solving to 1e-8 took twice as long
        # and moved no camera by more than a millimetre on the simulated surveys.
        solver = self.ba_options.ceres.solver_options
        solver.gradient_tolerance = options.ba_gradient_tolerance
        solver.function_tolerance = options.ba_function_tolerance
        solver.max_num_iterations = options.ba_max_iterations
        self.ba_options.ceres.max_num_images_direct_sparse_cpu_solver = (
            options.ba_max_direct_sparse_images
        )
        if (
            options.ba_trust_region == "dogleg"
            and self.reconstruction.num_images() <= options.ba_max_direct_sparse_images
        ):
            # Dogleg needs the direct solver Ceres picks up to that many images (see
            # `RefineOptions.ba_trust_region`).
            solver.trust_region_strategy_type = type(solver.trust_region_strategy_type).DOGLEG
        self.mapper = pycolmap.IncrementalMapper(self.cache)
        self.mapper.begin_reconstruction(self.reconstruction)

    def _set_function_tolerance(self, observations: int) -> None:
        """The adjustment's relative cost tolerance for `observations` observations (see
        `RefineOptions.ba_chi2_tolerance`)."""
        solver = self.ba_options.ceres.solver_options
        chi2 = self.options.ba_chi2_tolerance
        if not self.rebuilt and self.options.rebuild_tracks:
            chi2 = self.options.first_pass_ba_chi2_tolerance
        solver.function_tolerance = function_tolerance(
            self.options.ba_function_tolerance, chi2, observations
        )

    def refine_rounds(
        self,
        rounds: list[dict[str, float]],
        *,
        converged_change_m: float,
        keep_tracks: bool = True,
    ) -> None:
        """Rounds of (merge/complete tracks, retriangulate, BA with priors, filter) until
        95 % of the camera centres move less than `converged_change_m` once the common
        similarity is taken out (or are predicted to in the next round, see
        `RefineOptions.predict_convergence`).

        keep_tracks: False when only the poses of the last round are used (its tracks are
        thrown away next): the last adjustment is then not followed by track completion,
        merging and filtering, which change no pose.
        """
        previous = float("inf")
        pass_name = "rebuilt" if self.rebuilt else "first"
        for _ in range(self.options.max_rounds):
            start = time.perf_counter()
            before = camera_poses(self.reconstruction)
            # COLMAP's iterative global refinement, one adjustment per round, spelled out so
            # the convergence test is on the poses (COLMAP's counts changed observations).
            t0 = time.perf_counter()
            self.mapper.complete_and_merge_tracks(self.tri_options)
            t_merged = time.perf_counter()
            self.mapper.retriangulate(self.tri_options)
            t_retriangulated = time.perf_counter()
            points = max(self.reconstruction.num_points3D(), 1)
            observations = self.reconstruction.compute_num_observations()
            dropped = 0
            if self.options.ba_max_track_length:
                dropped = cap_tracks(
                    self.reconstruction,
                    self.mapper.observation_manager,
                    self.options.ba_max_track_length,
                )
            self._set_function_tolerance(observations - dropped)
            t1 = time.perf_counter()
            self.mapper.adjust_global_bundle(self.mapper_options, self.ba_options)
            t2 = time.perf_counter()
            after = camera_poses(self.reconstruction)
            moves = _camera_moves_m(before, after)
            move = float(np.max(moves)) if moves.size else float("inf")
            # The 95th percentile: one weakly seen keyframe at a session's end can swing for
            # a round or two while the rest has long settled. Of the shape's moves: every
            # adjustment first re-aligns the model to the priors (a similarity COLMAP fits
            # by RANSAC), which can shift the settled model by centimetres from one round
            # to the next where the priors are loose; more rounds do not settle that.
            raw = float(np.percentile(moves, 95)) if moves.size else float("inf")
            shape = shape_moves_m(before, after)
            typical = float(np.percentile(shape, 95)) if shape.size else float("inf")
            # A prediction needs two rounds, the second moving less than the first.
            contracting = np.isfinite(previous) and typical < previous
            predicted = typical * typical / previous if contracting else float("inf")
            converged = typical < converged_change_m or (
                self.options.predict_convergence and predicted < converged_change_m
            )
            if keep_tracks or not converged:
                self.mapper.complete_and_merge_tracks(self.tri_options)
                self.mapper.filter_points(self.mapper_options)
            t3 = time.perf_counter()
            rounds.append(
                {
                    "seconds": time.perf_counter() - start,
                    "tracks_s": t1 - t0,
                    "merge_tracks_s": t_merged - t0,
                    "retriangulate_s": t_retriangulated - t_merged,
                    "cap_tracks_s": t1 - t_retriangulated,
                    "bundle_adjust_s": t2 - t1,
                    "filter_s": t3 - t2,
                    "max_camera_move_m": move,
                    "p95_camera_move_m": raw,
                    "p95_shape_move_m": typical,
                    "points": float(self.reconstruction.num_points3D()),
                    "observations_per_point": observations / points,
                    "adjusted_observations_per_point": (observations - dropped) / points,
                    "registered": float(self.reconstruction.num_reg_images()),
                    "mean_reprojection_error_px": float(
                        self.reconstruction.compute_mean_reprojection_error()
                    ),
                    "rebuilt_tracks": float(self.rebuilt),
                }
            )
            log.info(
                "refinement round %d (%s pass): largest camera move %.4f m, %d points, "
                "%.3f px, %.1f s",
                len(rounds),
                pass_name,
                move,
                self.reconstruction.num_points3D(),
                rounds[-1]["mean_reprojection_error_px"],
                rounds[-1]["seconds"],
            )
            if converged:
                if typical >= converged_change_m:
                    log.info("next round predicted to move cameras by %.4f m: stopping", predicted)
                break
            previous = typical
        self.mapper.clear_modified_points3D()

    def register_remaining(self) -> int:
        """Register unregistered keyframes by absolute pose against the model."""
        registered = 0
        failed: set[int] = set()
        while True:
            candidates = [
                i
                for i in self.mapper.find_next_images(self.mapper_options, structure_less=False)
                if i not in failed
            ]
            if not candidates:
                break
            progress = False
            for image_id in candidates:
                if self.mapper.register_next_image(self.mapper_options, image_id):
                    self.mapper.triangulate_image(self.tri_options, image_id)
                    registered += 1
                    progress = True
                    break
                failed.add(image_id)
            if not progress:
                break
        return registered

    def close(self) -> None:
        self.mapper.end_reconstruction(False)
        self.reconstruction.update_point_3d_errors()


def fit_world_from_session(
    session_from_cam: FloatArray, world_from_cam: FloatArray
) -> tuple[FloatArray, float]:
    """Rigid `T_W_S` mapping the session's camera centres onto the model's; RMS residual (m).

    Both inputs (N, 4, 4), N >= 3 with non-collinear centres for a unique rotation;
    the SLAM frame is metric and gravity-aligned, so no scale is fitted.
    """
    R, t, _ = umeyama(session_from_cam[:, :3, 3], world_from_cam[:, :3, 3], with_scale=False)
    T = make_pose(R, t)
    residual = (session_from_cam[:, :3, 3] @ R.T + t) - world_from_cam[:, :3, 3]
    return T, float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def fit_unplaced_sessions(
    keyframes: KeyframeSet, world_from_cam: dict[str, FloatArray], options: RefineOptions
) -> dict[int, FloatArray]:
    """`T_W_S` of each unplaced session with enough keyframes in the model, by session index."""
    fitted: dict[int, FloatArray] = {}
    for s in np.unique(keyframes.session[~keyframes.placed]).tolist():
        members = [
            i
            for i in np.flatnonzero(keyframes.session == s)
            if keyframes.names[i] in world_from_cam
        ]
        if len(members) < max(options.min_registered_for_placement, 3):
            log.warning(
                "session %d: only %d keyframes registered by natural features; left unplaced",
                s,
                len(members),
            )
            continue
        T, rms = fit_world_from_session(
            keyframes.world_from_cam[members],
            np.stack([world_from_cam[keyframes.names[i]] for i in members]),
        )
        log.info("session %d tied in from %d keyframes (fit RMS %.3f m)", s, len(members), rms)
        fitted[s] = T
    return fitted


def _write_priors(
    database_path: Path, keyframes: KeyframeSet, indices: list[int], world_from_cam: FloatArray
) -> None:
    """Write (or replace, on a resumed run) the position priors of the given keyframes."""
    import pycolmap

    with pycolmap.Database.open(database_path) as db:
        existing = {int(p.corr_data_id.id): p for p in db.read_all_pose_priors()}
        for i in indices:
            image = db.read_image_with_name(keyframes.names[i])
            if image is None:
                continue
            prior = pose_prior(world_from_cam[i], keyframes.prior_sigma_m[i], image)
            old = existing.get(int(image.image_id))
            if old is None:
                db.write_pose_prior(prior)
            else:
                # COLMAP refuses two priors for one image.
                prior.pose_prior_id = old.pose_prior_id
                db.update_pose_prior(prior)


def refine_with_priors(
    database_path: Path, keyframes: KeyframeSet, options: RefineOptions
) -> RefineResult:
    """Triangulate at the prior poses, BA with priors in rounds; tie in unplaced sessions;
    rebuild the tracks at the refined poses and adjust again (see the module docstring)."""
    seconds: dict[str, float] = {}
    rounds: list[dict[str, float]] = []
    first_converged_m = (
        options.first_pass_converged_change_m
        if options.rebuild_tracks
        else options.converged_change_m
    )
    placed = {
        keyframes.names[i]: keyframes.world_from_cam[i] for i in np.flatnonzero(keyframes.placed)
    }
    start = time.perf_counter()
    mapper = _Mapper(database_path, placed, options)
    triangulated = mapper.triangulated
    seconds["triangulate_s"] = time.perf_counter() - start
    log.info("triangulated %d observations at the prior poses", triangulated)
    start = time.perf_counter()
    unplaced_sessions = np.unique(keyframes.session[~keyframes.placed])
    # The rebuild pass throws the first pass's tracks away; registering the unplaced
    # sessions needs them.
    mapper.refine_rounds(
        rounds,
        converged_change_m=first_converged_m,
        keep_tracks=not options.rebuild_tracks or bool(unplaced_sessions.size),
    )
    seconds["bundle_adjust_s"] = time.perf_counter() - start
    world_from_session: dict[int, FloatArray] = {}
    if unplaced_sessions.size:
        start = time.perf_counter()
        registered = mapper.register_remaining()
        log.info("registered %d keyframes of unplaced sessions", registered)
        world_from_session = fit_unplaced_sessions(
            keyframes, camera_poses(mapper.reconstruction), options
        )
        seconds["register_unplaced_s"] = time.perf_counter() - start
    mapper.close()
    result_poses = camera_poses(mapper.reconstruction)
    if world_from_session:
        # Second pass (wide thresholds again): every session placed, priors for the newly
        # placed ones.
        start = time.perf_counter()
        seeds = dict(result_poses)
        newly: list[int] = []
        world_from_cam = keyframes.world_from_cam.copy()
        for s, T in world_from_session.items():
            for i in np.flatnonzero(keyframes.session == s).tolist():
                world_from_cam[i] = T @ keyframes.world_from_cam[i]
                newly.append(i)
                seeds.setdefault(keyframes.names[i], world_from_cam[i])
        _write_priors(database_path, keyframes, newly, world_from_cam)
        mapper = _Mapper(database_path, seeds, options)
        mapper.refine_rounds(
            rounds, converged_change_m=first_converged_m, keep_tracks=not options.rebuild_tracks
        )
        mapper.close()
        result_poses = camera_poses(mapper.reconstruction)
        seconds["second_pass_s"] = time.perf_counter() - start
    if options.rebuild_tracks:
        start = time.perf_counter()
        mapper = _Mapper(database_path, result_poses, options, rebuilt=True)
        triangulated = mapper.triangulated
        seconds["rebuild_triangulate_s"] = time.perf_counter() - start
        log.info("rebuilt tracks at the refined poses: %d observations", triangulated)
        mapper.refine_rounds(rounds, converged_change_m=options.converged_change_m)
        mapper.close()
        result_poses = camera_poses(mapper.reconstruction)
        seconds["rebuild_tracks_s"] = time.perf_counter() - start
    if world_from_session:
        # Refit on the final poses (more keyframes, adjusted together).
        world_from_session.update(fit_unplaced_sessions(keyframes, result_poses, options))
    return RefineResult(
        reconstruction=mapper.reconstruction,
        world_from_cam=result_poses,
        world_from_session=world_from_session,
        rounds=rounds,
        mapper="prior",
        seconds=seconds,
    )


def incremental_with_priors(
    database_path: Path,
    image_dir: Path,
    work_dir: Path,
    keyframes: KeyframeSet,
    options: RefineOptions,
) -> RefineResult:
    """COLMAP's incremental mapper with position priors, from scratch (the fallback).

    The pose priors keep the result in the world frame at metric scale; the largest
    model is kept.
    """
    import pycolmap

    start = time.perf_counter()
    pipeline = _pipeline_options(options, use_priors=True)
    pipeline.multiple_models = False
    work_dir.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(database_path, image_dir, work_dir, options=pipeline)
    if not models:
        raise StageError(
            f"{database_path}: the incremental mapper built no model (expected overlapping "
            "keyframes with enough verified matches)"
        )
    best = max(models.values(), key=lambda r: r.num_reg_images())
    poses = camera_poses(best)
    return RefineResult(
        reconstruction=best,
        world_from_cam=poses,
        world_from_session=fit_unplaced_sessions(keyframes, poses, options),
        mapper="incremental",
        seconds={"incremental_mapping_s": time.perf_counter() - start},
    )


def refine(
    database_path: Path,
    image_dir: Path,
    work_dir: Path,
    keyframes: KeyframeSet,
    options: RefineOptions,
) -> RefineResult:
    """Refine the keyframe poses as `options.mapper` says (see `RefineOptions`)."""
    if not np.any(keyframes.placed):
        raise StageError("no session has a world pose (expected at least one placed session)")
    if options.mapper == "incremental":
        return incremental_with_priors(database_path, image_dir, work_dir, keyframes, options)
    result = refine_with_priors(database_path, keyframes, options)
    n_placed = int(np.sum(keyframes.placed))
    placed_in_model = sum(
        1 for i in np.flatnonzero(keyframes.placed) if keyframes.names[i] in result.world_from_cam
    )
    if options.mapper == "auto" and placed_in_model < options.min_registered_fraction * n_placed:
        log.warning(
            "only %d of %d placed keyframes in the model: trying the incremental mapper",
            placed_in_model,
            n_placed,
        )
        fallback = incremental_with_priors(database_path, image_dir, work_dir, keyframes, options)
        if len(fallback.world_from_cam) > len(result.world_from_cam):
            fallback.rounds = result.rounds
            return fallback
    return result
