"""The SfM stage's options: feature extraction, pair choice, refinement and `SfmOptions`
that holds them.

Light on purpose (no NumPy or pycolmap here): the command line builds its flags from
these classes (postproc.pipeline.options) without importing the stage. Each class is
re-exported by the module that uses it (`postproc.sfm.features.FeatureOptions`...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(kw_only=True)
class FeatureOptions:
    """Budgets of the feature stage.

    max_num_features: SIFT keypoints kept per image (largest scales first).
    max_image_size_px: longer image side for extraction (images are scaled down, the
        keypoints scaled back to full resolution).
    max_ratio: Lowe's ratio test threshold. max_error_px: RANSAC threshold of the
        two-view verification (pixels). min_num_inliers: verified pairs need this many.
    first_octave: first octave of the SIFT pyramid. COLMAP's -1 doubles the image first,
        which costs about 3/4 of the extraction time and adds the finest features, the
        first to go when `max_num_features` caps the count (largest scales are kept);
        None: -1 for small images (longer side below `small_image_px`), else 0.
    num_threads: worker threads (-1: all cores).
    """

    # 512 features on images of at most 640 px: with the priors holding the geometry,
    # bench_sfm.py found the refined poses within 2-3 mm of 1024 features, in about half
    # the matching and adjustment time; at 480 px one session lost 3-4 mm.
    max_num_features: int = 512
    max_image_size_px: int = 640
    max_ratio: float = 0.8
    max_error_px: float = 4.0
    min_num_inliers: int = 15
    first_octave: int | None = None
    small_image_px: int = 480
    num_threads: int = -1

    def __post_init__(self) -> None:
        if self.max_num_features < 64:
            raise ValueError(f"max_num_features must be at least 64, got {self.max_num_features}")
        if self.max_image_size_px < 64:
            raise ValueError(f"max_image_size_px must be at least 64, got {self.max_image_size_px}")
        if not 0 < self.max_ratio <= 1:
            raise ValueError(f"max_ratio must be in (0, 1], got {self.max_ratio}")


@dataclass(kw_only=True)
class PairOptions:
    """How many and which pairs to match.

    sequential_neighbours: successors in time within a session (offsets 1..n, no gaps).
    spatial_neighbours: at most this many spatial/loop partners per keyframe.
    view_distance_m: distance along the optical axis of the point a camera looks at
        (about the working distance to the wreck), metres.
    spatial_radius_m: two keyframes are spatial candidates when their viewed points
        are this close (3D distance, z included), metres.
    max_view_angle_deg: and their optical axes differ by at most this angle.
    loop_min_separation_s: keyframes of one session are loop candidates only this far
        apart in time (closer ones are the sequential matcher's business), seconds.
    max_bridging_pairs: budget of pairs tying one unplaced session to the placed ones.
    """

    # 3 + 4 partners (about 4.6 pairs per keyframe) instead of 5 + 6 (7.4): 37 % fewer
    # pairs to match, 98 % of them verified, the refined poses within a few millimetres.
    sequential_neighbours: int = 3
    spatial_neighbours: int = 4
    view_distance_m: float = 2.0
    spatial_radius_m: float = 1.5
    max_view_angle_deg: float = 60.0
    loop_min_separation_s: float = 10.0
    max_bridging_pairs: int = 400

    def __post_init__(self) -> None:
        if self.sequential_neighbours < 0 or self.spatial_neighbours < 0:
            raise ValueError("sequential_neighbours and spatial_neighbours must be >= 0")
        if self.spatial_radius_m <= 0 or self.view_distance_m < 0:
            raise ValueError("spatial_radius_m must be > 0 and view_distance_m >= 0")
        if not 0 < self.max_view_angle_deg <= 180:
            raise ValueError("max_view_angle_deg must be in (0, 180]")
        if self.max_bridging_pairs < 0 or self.loop_min_separation_s < 0:
            raise ValueError("max_bridging_pairs and loop_min_separation_s must be >= 0")


@dataclass(kw_only=True)
class RefineOptions:
    """How the prior poses are refined.

    triangulation_max_angle_deg: largest ray angle error to create or continue a track
        in the first pass, at the prior poses (COLMAP default 2; widened for drifting
        priors).
    merge_max_reproj_error_px: reprojection error to merge or complete tracks in the
        first pass, pixels.
    rebuild_tracks: run the rebuild pass (tracks rebuilt at the refined poses, see the
        module docstring).
    rebuilt_max_angle_deg, rebuilt_merge_max_reproj_error_px: the rebuild pass's
        thresholds (COLMAP's defaults: 2 degrees, 4 px). The rebuild pass triangulates
        the keyframes in order, each continuing the tracks of those before it when its
        ray is within the angle (`postproc.sfm.refine`), and 2 degrees is 17 px at a
        focal length of 500 px: 1 degree kept the tracks about as clean as merging at
        4 px (bench_pipeline.py's 10-minute dive, refinement rerun on its database by a
        one-off script: 1.20 cm against the truth, 1.39 cm at 2 degrees).
    first_pass_converged_change_m: with `rebuild_tracks`, the first pass stops once 95 %
        of the shape's cameras move less than this in a round (or are predicted to),
        metres:
        the rebuilt tracks only need poses good to about the rebuild pass's angle at the
        viewing distance (2 degrees at 2 m is 7 cm), and the rebuild pass converges the
        rest.
    filter_max_reproj_error_px: observations above this error after an adjustment are
        dropped, pixels. filter_min_tri_angle_deg: points seen under a smaller angle too.
    max_rounds: refinement rounds at most. converged_change_m: stop when 95 % of the
        camera centres moved less than this in a round once the similarity common to
        all is taken out, metres (each adjustment re-aligns the model to the priors, which
        can shift a settled model by centimetres every round where they are loose).
    predict_convergence: also stop when the next round is predicted to move them less
        than that: the moves shrink geometrically from round to round (0.5 m, 5 cm,
        3 mm on the simulated surveys), so the next is about this one's times the ratio
        of this one to the last; saves the round that only confirms convergence.
    skip_redundant_points: adjust first without the 3D points that add little image
        coverage, then those points alone (COLMAP's option for large adjustments).
    redundant_min_coverage_gain: the image coverage a point must add to stay in the joint
        adjustment (COLMAP's default 0.05; larger drops more points).
    ignore_two_view_tracks: do not create points seen by two keyframes only (weak and
        numerous; COLMAP's default).
    ba_gradient_tolerance, ba_function_tolerance, ba_max_iterations: Ceres stopping rules
        of each adjustment (COLMAP's global-BA defaults).
    ba_chi2_tolerance: stop an adjustment once an iteration lowers the sum of squared
        reprojection errors, counted in units of the reprojection noise (chi-square), by
        less than this (None: only the rules above). With N residuals and the noise
        estimated from the cost itself (its mean per residual), that is a relative cost
        decrease below `ba_chi2_tolerance / N` (Ceres's function tolerance, set per
        adjustment from the observations going into it). The gradient rule above is
        absolute and a larger problem rarely meets it: on bench_sfm.py's 10-minute
        revisiting dive every adjustment ran to its 50-iteration limit, the last ten or
        more each lowering the cost by a few parts in a million. With 10, the adjustments
        of the refinement took 56 against 81 s CPU there (7.8 against 9.8 s on its first
        3 minutes); the whole refinement 103-110 against 118-131 s CPU (16.0-17.5 against
        18.1-18.8 s at 3 minutes; three runs against two, load 3-9), sim3 ATE 0.80 / 0.76
        against 0.85 / 0.75 cm, without alignment 42.7 / 29.9 against 41.5 / 29.9 cm.
        The iterations that remain alternate accepted and rejected dogleg steps.
    first_pass_ba_chi2_tolerance: the same rule for the first pass's adjustments when
        the rebuild pass follows (`rebuild_tracks`): their poses only seed the rebuilt
        tracks and need to be good to centimetres. With 100 against 10, the first pass's
        one adjustment on bench_pipeline.py's 10-minute dive (rerun on its database by a
        one-off script) stopped after 9.7 against 18.7 s (keyframes 1.12 against 1.15 cm
        from the truth after the rebuild pass; bench_sfm.py --refine-only's surveys
        0.89-1.16 against 0.87-1.16 cm, sim3).
    ba_max_track_length: observations of one point that go into each adjustment, at most
        (None: all). Longer tracks keep this many, spread evenly over their keyframes
        (first and last included, so a point seen on several passes still ties them),
        for the adjustment only: the track completion after it adds the others back
        where they reproject well, so the model keeps every point with its full track.
        On a dive that keeps revisiting the wreck tracks grow with its length (16
        observations per point at 3 minutes, 29 at 10: bench_pipeline.py) and so does
        the cost of each adjustment per keyframe, about with the square of the track
        length (the Schur complement pairs every two keyframes of a track). On the
        first 3 minutes of bench_sfm.py's revisiting dive a cap of 8 halved the
        refinement's CPU time (56 against 121 s) at a better sim3 ATE (0.75 against
        1.03 cm); on the whole 10 minutes it took 387 against 1145 s (0.86 against
        1.03 cm).
    ba_trust_region: Ceres's trust-region strategy of each adjustment: "dogleg" (Powell's
        dogleg) or "levenberg_marquardt" (COLMAP's default). With the position priors
        loose (metres at the end of a long dive) the model's placement and long-range bends
        are weakly constrained, and Levenberg-Marquardt's damping, scaled by the
        reprojection terms that dominate every camera's diagonal, all but stops steps along
        them: its adjustments ran out of iterations (50) in every round while the cameras
        still moved by decimetres to metres, so the rounds went on, more of them on longer
        dives. Dogleg takes the Gauss-Newton step whenever it fits the trust region: on the
        first 3 minutes of bench_sfm.py's revisiting dive the first adjustment converged in
        23 iterations to 0.28 px where Levenberg-Marquardt stopped after 118 at 2.05 px.
        The whole refinement (CPU, loaded machine) took 18 against 44 s there (3 rounds
        against 4) and 122 against 288 s on the whole 10 minutes (3 against 6), sim3 ATE
        0.75 / 0.88 against 0.75 / 0.84 cm, without alignment 29.9 / 41.5 against
        29.9 / 57.2 cm. Dogleg needs a direct solver, so adjustments above
        `ba_max_direct_sparse_images` keyframes use Levenberg-Marquardt.
    ba_max_direct_sparse_images: up to this many keyframes the adjustment factorises the
        reduced camera system directly (Ceres sparse Schur); beyond, it iterates (Schur +
        conjugate gradients). COLMAP switches at 1000 images, a limit set for unordered
        photo collections; keyframes of a video survey see few others each, so the direct
        solver stays sparse: on a simulated 10-minute dive (1227 keyframes, 1.6 M
        residuals) it adjusted 1.3-1.6x faster than the iterative one.
    robust_prior_loss: Cauchy loss on the position priors (a few wrong priors then
        cannot pull the model). refine_intrinsics: also adjust focal length and
        distortion (off: the cameras are calibrated).
    min_num_matches: pairs with fewer inlier matches are ignored.
    min_registered_for_placement: keyframes of an unplaced session that must register
        before its `T_W_S` is fitted.
    mapper: "prior" (triangulate + BA from the priors), "incremental" (COLMAP's
        incremental mapper with pose priors, from scratch), or "auto" (prior, and the
        incremental mapper when fewer than `min_registered_fraction` of the placed
        keyframes end up in the model).
    num_threads: solver threads (-1: all cores). random_seed: for RANSAC (-1: random).
    """

    triangulation_max_angle_deg: float = 8.0
    merge_max_reproj_error_px: float = 8.0
    rebuild_tracks: bool = True
    rebuilt_max_angle_deg: float = 1.0
    rebuilt_merge_max_reproj_error_px: float = 4.0
    first_pass_converged_change_m: float = 0.05
    filter_max_reproj_error_px: float = 4.0
    filter_min_tri_angle_deg: float = 1.5
    max_rounds: int = 6
    converged_change_m: float = 0.01
    predict_convergence: bool = True
    skip_redundant_points: bool = True
    redundant_min_coverage_gain: float = 0.05
    ignore_two_view_tracks: bool = True
    ba_gradient_tolerance: float = 1.0
    ba_function_tolerance: float = 0.0
    ba_chi2_tolerance: float | None = 10.0
    first_pass_ba_chi2_tolerance: float | None = 100.0
    ba_max_iterations: int = 50
    ba_max_track_length: int | None = 8
    ba_trust_region: Literal["dogleg", "levenberg_marquardt"] = "dogleg"
    ba_max_direct_sparse_images: int = 8000
    robust_prior_loss: bool = True
    refine_intrinsics: bool = False
    min_num_matches: int = 15
    min_registered_for_placement: int = 5
    mapper: Literal["prior", "incremental", "auto"] = "auto"
    min_registered_fraction: float = 0.5
    num_threads: int = -1
    random_seed: int = 0

    def __post_init__(self) -> None:
        if self.mapper not in ("prior", "incremental", "auto"):
            raise ValueError(
                f"mapper must be 'prior', 'incremental' or 'auto', got {self.mapper!r}"
            )
        if self.ba_trust_region not in ("dogleg", "levenberg_marquardt"):
            raise ValueError(
                "ba_trust_region must be 'dogleg' or 'levenberg_marquardt', got "
                f"{self.ba_trust_region!r}"
            )
        if self.max_rounds < 1:
            raise ValueError(f"max_rounds must be at least 1, got {self.max_rounds}")
        if self.ba_max_track_length is not None and self.ba_max_track_length < 3:
            raise ValueError(
                f"ba_max_track_length must be at least 3 (or None), got {self.ba_max_track_length}"
            )
        for name in ("ba_chi2_tolerance", "first_pass_ba_chi2_tolerance"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be positive (or None), got {value}")
        if self.ba_max_direct_sparse_images < 0:
            raise ValueError(
                "ba_max_direct_sparse_images must be 0 or more, got "
                f"{self.ba_max_direct_sparse_images}"
            )
        thresholds = (
            self.triangulation_max_angle_deg,
            self.merge_max_reproj_error_px,
            self.rebuilt_max_angle_deg,
            self.rebuilt_merge_max_reproj_error_px,
            self.filter_max_reproj_error_px,
            self.converged_change_m,
            self.first_pass_converged_change_m,
        )
        if not all(value > 0 for value in thresholds):
            raise ValueError("triangulation, filter and convergence thresholds must be positive")


@dataclass(kw_only=True)
class SfmOptions:
    """Options of the SfM stage.

    features, pairs, refine: see `FeatureOptions`, `PairOptions`, `RefineOptions`.
    prior_sigma_m: fixed one-sigma error of every position prior, metres; None derives
        it per keyframe as sqrt(floor^2 + sigma(T_W_S)^2 + (drift * distance)^2), where
        distance is the path length from the session's first keyframe.
    prior_sigma_floor_m: the floor of the derived sigma, metres (a prior that is too
        tight keeps the SLAM drift; one that is loose only fixes the gauge).
    prior_drift_per_m: drift rate assumed when the SLAM's stats.json gives none.
    copy_images: copy keyframes into images/ instead of linking them.
    chunk_images: keyframes per extraction task when `run` is given a `map_fn`.
    chunk_pairs: image pairs per matching task when `run` is given a `map_fn`.
    """

    features: FeatureOptions = field(default_factory=FeatureOptions)
    pairs: PairOptions = field(default_factory=PairOptions)
    refine: RefineOptions = field(default_factory=RefineOptions)
    prior_sigma_m: float | None = None
    prior_sigma_floor_m: float = 0.1
    prior_drift_per_m: float = 0.05
    copy_images: bool = False
    chunk_images: int = 32
    chunk_pairs: int = 400

    def __post_init__(self) -> None:
        if self.chunk_images < 1 or self.chunk_pairs < 1:
            raise ValueError("chunk_images and chunk_pairs must be at least 1")
        if self.prior_sigma_m is not None and not self.prior_sigma_m > 0:
            raise ValueError(f"prior_sigma_m must be positive, got {self.prior_sigma_m}")
        if not self.prior_sigma_floor_m > 0 or self.prior_drift_per_m < 0:
            raise ValueError("prior_sigma_floor_m must be > 0 and prior_drift_per_m >= 0")
