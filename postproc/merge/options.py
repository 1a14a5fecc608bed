"""The merge stage's options: place recognition (`PlaceOptions`) and `MergeOptions`.

Light on purpose (no NumPy or OpenCV here): the command line builds its flags from
these classes (postproc.pipeline.options) without importing the stage. Each class is
re-exported by the module that uses it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from shared.calibration.aprilgrid_options import DetectionOptions


@dataclass(kw_only=True)
class PlaceOptions:
    """Settings of natural-feature merging.

    features_per_keyframe: ORB keypoints per keyframe image; orb_levels: their pyramid
        levels (`extract_features`).
    vocabulary_words: words of the k-majority vocabulary (fewer for small surveys: at
        least 20 sampled descriptors per word); vocabulary_sample: descriptors
        drawn (over all sessions) to build it; seed: its random generator.
    candidates_per_query: best-scoring keyframes of the other session kept per query.
    min_score: smallest TF-IDF cosine score of a candidate (0-1).
    ratio: Lowe's ratio test of descriptor matches.
    neighbour_window_s: reference neighbours for triangulation lie within this (s).
    max_neighbours: the nearest (in time) neighbours triangulated against.
    min_baseline_m: smallest distance between a reference and a neighbour camera (m).
    min_parallax_deg: smallest angle between the two rays of a triangulated point.
    triangulation_reprojection_px: largest reprojection error (pixels) of a triangulated
        point in either view (loose: neighbouring SLAM poses carry their own noise).
    ransac_reprojection_px: PnP RANSAC inlier threshold (pixels).
    min_inliers: fewest PnP inliers of a verified candidate (SVIn2's loop closures: 25).
    max_tilt_deg: largest relative roll/pitch of the free 6-DoF PnP's `T_Sa_Sb` (a coarse
        gravity check; the candidate itself is then refined in yaw and translation
        with roll and pitch from the IMUs, `refine_place` or `refine_yaw_translation`).
        10, not 3 as before `refine_places`: a map triangulated from keyframes with
        0.15 deg of SLAM error each tilts the PnP by several degrees, and at 3 deg
        two thirds of the true places of the simulated wreck's 120 s dives were lost
        (one-off script).
    consistency_rotation_deg / consistency_translation_m: two candidates agree when
        their `T_Sa_Sb` differ by less than both.
    min_consistent: fewest agreeing verified candidates for a pair to be mergeable.
    noise_floor_rotation_deg / noise_floor_translation_m: smallest per-candidate
        noise (1 sigma) of the drift-aware mean.
    place_gap_s: candidates within this (s) in both sessions film one place and share
        their error (`candidate_clusters`).
    keyframe_noise_rotation_deg / keyframe_noise_translation_m: each keyframe's own SLAM
        pose error besides the drift (1 sigma per axis, about the camera), for sessions
        whose targets do not measure it (`averaging.DriftModel.noise`); every candidate
        that uses a keyframe carries all of it (`places.pair_place_mean`). The targets'
        drift model measured 0.10-0.21 deg and 0.7-1.3 cm on the simulated wreck.
    max_candidate_chi2: a consistent candidate whose residual about the pair's mean,
        whitened by its own modelled covariance (yaw and translation, where its errors
        pivot), exceeds this is dropped (18.5: the 99.9 % point of chi-square with 4 dof;
        `places.pair_place_mean`). None: keep every consistent candidate.
    rotation_from_images: take each candidate's yaw from the query and reference images
        (essential matrix) instead of the PnP against the triangulated local map (off:
        on the simulated wreck it was no better, 0.8 against 0.7 deg per candidate;
        without effect under `refine_places`).
    gravity_sigma_deg: roll/pitch error of each session's gravity alignment (deg, 1
        sigma per axis) given to the pairs' relative tilt when the merge has no tilt
        prior of its own (`MergeOptions.tilt_sigma_deg`).
    refine_places: each verified candidate's `T_Sa_Sb` from a bundle adjustment of the
        keyframes around its reference and its query (`places.refine_place`) instead of
        the one PnP; refine_window_s: those keyframes lie within this (s) of each;
        refine_neighbours: at most this many of them per side (nearest in time);
        refine_min_observations: a neighbour joins with at least this many landmarks
        matched; refine_pixel_sigma_px: the image noise of the adjustment (pixels, 1
        sigma, Huber-weighted); refine_max_change_deg: a candidate whose adjustment
        turns `T_Sa_Sb` further than this from its PnP is dropped (a false match).
    """

    features_per_keyframe: int = 1000
    orb_levels: int = 8
    vocabulary_words: int = 4000
    vocabulary_sample: int = 20000
    seed: int = 0
    candidates_per_query: int = 3
    min_score: float = 0.08
    ratio: float = 0.8
    neighbour_window_s: float = 3.0
    max_neighbours: int = 2
    min_baseline_m: float = 0.1
    min_parallax_deg: float = 1.0
    triangulation_reprojection_px: float = 6.0
    ransac_reprojection_px: float = 4.0
    min_inliers: int = 25
    max_tilt_deg: float = 10.0
    consistency_rotation_deg: float = 1.5
    consistency_translation_m: float = 0.25
    min_consistent: int = 3
    noise_floor_rotation_deg: float = 0.01
    noise_floor_translation_m: float = 0.002
    place_gap_s: float = 5.0
    keyframe_noise_rotation_deg: float = 0.15
    keyframe_noise_translation_m: float = 0.01
    max_candidate_chi2: float | None = 18.5
    gravity_sigma_deg: float = 0.1
    rotation_from_images: bool = False
    refine_places: bool = True
    refine_window_s: float = 3.0
    refine_neighbours: int = 6
    refine_min_observations: int = 10
    refine_pixel_sigma_px: float = 1.0
    refine_max_change_deg: float = 5.0


@dataclass(kw_only=True)
class MergeOptions:
    """Options of the merge stage.

    method: "ours" (whole-grid PnP, robust SE(3) averaging, covariance-weighted
        alignment) or "paper" (per-tag poses, one-sigma rejection, Euler means).
    reference: folder name of the session that defines W; None = the first.
    dof: "auto" (4 when the sessions are depth-fused, else 6), 4 or 6.
    depth_fused: True: use the depth stage's world trajectories (error if
        missing); False: ignore them; None: use them when every session has one.
    min_tags: fewest tags of one target in a keyframe to use the observation.
    max_reprojection_rms_px: observations whose PnP fits worse are dropped (pixels).
    max_distance_m: observations of a target further than this are dropped (metres).
    rotation_mean: "chordal" or "quaternion" (ours).
    outlier_rule: "mad" or "chi2" (ours; see `averaging.robust_pose_mean`).
    mad_threshold: robust sigmas beyond which an observation is an outlier.
    pass_gap_s: keyframes of one target further apart in time than this (s) belong
        to different passes; a pass shares its SLAM drift, so the covariance of a
        target's mean counts passes, not keyframes (`averaging.clustered_covariance`).
    drift_rotation_sigma_deg / drift_translation_sigma_m: the SLAM drift of one
        pass assumed before the data are seen (1 sigma, degrees and metres).
    drift_weighting: (ours) weigh each target's observations by the SLAM's drift
        growth: a random walk from the session's anchor (the first pose of
        `trajectory.tum`, else of `keyframes.tum`) plus per-keyframe noise, fitted
        by generalised least squares (`averaging.drift_weighted_mean`); the
        covariance then includes the drift. Used in sessions where some target
        was filmed in two passes (`pass_gap_s` apart), which measures the drift.
        False: the robust means (all passes alike, the overlay of the maps at the
        targets); where the drift is measured, each target's covariance then grows
        by how far its local map frame drifts from the session's mean frame
        (`averaging.local_frame_variance`), so placement weighs targets for the overlay.
    drift_rejection: (with drift_weighting) after the robust mean's outlier rule, test
        every sighting again against the fitted drift model (`averaging.drift_inliers`:
        predicted from the target's other inliers, so a pass the walk carried away
        from the mean comes back and a gross error stays out) and refit the model.
        False: the robust mean's inliers alone.
    tilt_sigma_deg: (ours) the roll/pitch error of each session's gravity alignment
        (degrees, 1 sigma per axis, as the SLAM reports it). None: no prior (dof 6
        fits the tilt from the targets alone, dof 4 holds it at zero). Given: the
        placement is a 6-DoF fit whose relative roll and pitch get this prior
        (`align.align_6dof`), for dof 6 and for "auto" (depth-fused sessions too:
        the 4-DoF fit is this prior's limit of a perfect gravity alignment); an
        explicit dof 4 still holds the tilt at zero.
    drift_rate_rotation_deg_per_sqrt_s / drift_rate_translation_m_per_sqrt_s: the
        prior drift rate (1 sigma per axis after one second, growing with the square
        root of time); each session's own rate is measured from the differences
        between passes over the same target and shrunk toward this prior (toward
        none for roll and pitch, held by gravity in a visual-inertial SLAM; a session
        whose drift no target measured keeps this prior on all three axes).
    camera: the camchain entry that took the keyframes.
    plot: write the top and side views.
    detection: tag detection settings.
    natural_features: (ours) also match every pair of sessions through the structure
        both filmed and estimate the transforms jointly (`joint.solve_joint`); targets
        become optional. "auto": only when the targets cannot place every session
        (none given, or a session shares no target with the others). On the simulated
        wreck's 240 s dives (four seeds x four draws of the SLAM errors) targets and
        features together place the session frame a little better than the targets
        alone (0.104 against 0.108 deg, 3.48 against 4.54 cm RMS) but overlay the maps
        worse where they meet (6.83 against 6.14 cm at the shared places), take 20x the
        time (35 against 1.7 s), and after SfM every merge gives the same maps
        (docs/benchmarks.md, "Merge").
        True: always. False: targets only, placed session by session
        (`align.place_sessions`), or, where a session's drift was measured, by the
        joint estimate with the targets' edges alone (their shared drift counted).
    places: natural-feature settings (`places.PlaceOptions`).
    depth_sigma_m: (joint) each depth-fused session's absolute-depth error (m, 1 sigma):
        the prior on the sessions' relative z.
    """

    method: Literal["ours", "paper"] = "ours"
    reference: str | None = None
    dof: Literal["auto", 4, 6] = "auto"
    depth_fused: bool | None = None
    min_tags: int = 2
    max_reprojection_rms_px: float = 2.0
    max_distance_m: float = 15.0
    rotation_mean: Literal["chordal", "quaternion"] = "chordal"
    outlier_rule: Literal["mad", "chi2"] = "mad"
    mad_threshold: float = 3.5
    pass_gap_s: float = 5.0
    drift_rotation_sigma_deg: float = 0.2
    drift_translation_sigma_m: float = 0.02
    drift_weighting: bool = True
    drift_rejection: bool = True
    tilt_sigma_deg: float | None = None
    drift_rate_rotation_deg_per_sqrt_s: float = 0.02
    drift_rate_translation_m_per_sqrt_s: float = 0.003
    camera: str = "cam0"
    plot: bool = True
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    natural_features: bool | Literal["auto"] = "auto"
    places: PlaceOptions = field(default_factory=PlaceOptions)
    depth_sigma_m: float = 0.02
