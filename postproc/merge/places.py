"""Cross-session place recognition and geometric verification (natural-feature merging).

Every place two dives both filmed is a constraint on their session-to-session
transform `T_Sa_Sb`. Per pair of sessions (a, b):

1. **Recognition.** ORB features of every keyframe; a vocabulary of binary
   words by k-means over the sessions' own descriptors (no downloaded
   vocabulary); TF-IDF bag-of-words vectors; each keyframe of b queries the
   keyframes of a by cosine score (`place_candidates`).
2. **Verification.** The reference keyframe's features are triangulated
   against its neighbours in a (a's SLAM poses, `local_map`), the query's
   features matched to those points and `T_Sa_Cq` found by PnP RANSAC
   (`verify_candidate`); with the query's pose `T_Sb_Cq` this gives
   `T_Sa_Sb = T_Sa_Cq @ inv(T_Sb_Cq)`. Both session frames are
   gravity-aligned by their IMUs, so a candidate whose relative roll/pitch
   exceeds `max_tilt_deg` is refused: gravity constrains the two angles no
   image does well. The candidate is then refined by a bundle adjustment of
   the keyframes around the reference and around the query (`refine_place`):
   the images fix the map's shape and the keyframes' poses relative to one
   another, so each keyframe's own SLAM error is averaged over its
   neighbourhood instead of entering whole, and the adjustment's marginal
   covariance says how the place trades yaw against translation.
3. **Consistency.** Verified candidates must agree on `T_Sa_Sb`
   (`consistent_candidates`): the largest group within the rotation and
   translation tolerances of one another wins; fewer than `min_consistent`
   verified, agreeing candidates and the pair is not mergeable, with the
   evidence (scores, inlier counts) kept for the report.
4. **Drift.** Each candidate carries the drift of a at its reference keyframe
   and of b at its query keyframe, two random walks from the session anchors,
   and errors that rotate about the cameras, metres away from Sb's origin:
   `pair_place_mean` is the generalised least-squares mean with that covariance
   (each error modelled where it pivots), so the result leans on the places both
   dives filmed early and its translation is not blurred by the candidates' yaw.
   A keyframe's own pose error is in every candidate that uses it (one query
   keyframe often matches several places of the other dive), so it is modelled
   once for all of them; and a candidate whose residual lies beyond its modelled
   error, tested where it pivots (to centimetres, where the consistency check at
   Sb's origin must allow decimetres), is dropped.

Pure math and OpenCV calls on arrays: no file I/O (the stage reads images and
poses). Covariances follow `averaging`: 6x6 of `[δθ, δt]`, rotation first,
radians and metres, in the parent frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from postproc.merge.align import tilt_vector_rad, yaw_rad
from postproc.merge.averaging import pose_residuals
from postproc.merge.options import PlaceOptions as PlaceOptions
from shared.geometry import invert_pose, make_pose, rotation_angle_rad, so3_exp

FloatArray = npt.NDArray[np.float64]
UInt8Array = npt.NDArray[np.uint8]
IntArray = npt.NDArray[np.int64]


@dataclass
class KeyframeFeatures:
    """One keyframe's features: pixels (N, 2), undistorted rays at z=1 (N, 2), ORB (N, 32)."""

    stamp_ns: int
    pixels: FloatArray
    normalised: FloatArray
    descriptors: UInt8Array
    words: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def extract_features(
    image: UInt8Array, count: int, *, levels: int = 8
) -> tuple[FloatArray, UInt8Array]:
    """ORB keypoints (N, 2) pixels and descriptors (N, 32) of a grayscale image.

    levels: pyramid levels (scale 1.2 each); a keypoint of level l is located to
    about 1.2^l pixels, so fewer levels mean sharper geometry and less scale range.
    """
    import cv2

    orb = cv2.ORB.create(nfeatures=count, fastThreshold=10, nlevels=levels)
    keypoints, descriptors = orb.detectAndCompute(image, None)
    if descriptors is None or not keypoints:
        return np.zeros((0, 2)), np.zeros((0, 32), dtype=np.uint8)
    pixels = np.array([k.pt for k in keypoints], dtype=np.float64)
    return pixels, np.asarray(descriptors, dtype=np.uint8)


@dataclass(frozen=True)
class Vocabulary:
    """Binary words (K, 32) and their inverse document frequencies (K,)."""

    words: UInt8Array
    idf: FloatArray

    def assign(self, descriptors: UInt8Array) -> IntArray:
        """Nearest word (N,) of each descriptor by Hamming distance."""
        import cv2

        if descriptors.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        matches = cv2.BFMatcher(cv2.NORM_HAMMING).match(descriptors, self.words)
        words = np.zeros(descriptors.shape[0], dtype=np.int64)
        for m in matches:
            words[m.queryIdx] = m.trainIdx
        return words

    def vectors(self, word_lists: Sequence[IntArray]) -> FloatArray:
        """TF-IDF vectors (N, K), L2-normalised, one per keyframe."""
        out = np.zeros((len(word_lists), self.words.shape[0]))
        for i, words in enumerate(word_lists):
            if len(words):
                out[i] = np.bincount(words, minlength=self.words.shape[0]) / len(words)
        out *= self.idf
        norm = np.linalg.norm(out, axis=1, keepdims=True)
        return np.asarray(out / np.maximum(norm, 1e-12), dtype=np.float64)


def build_vocabulary(
    descriptor_sets: Sequence[UInt8Array],
    *,
    words: int,
    sample: int,
    seed: int,
    iterations: int = 10,
) -> Vocabulary:
    """Binary words by k-majority over the sessions' own descriptors, with their IDF.

    descriptor_sets: one (N, 32) array per keyframe, all sessions. k-majority is
    k-means for binary descriptors (as in DBoW): assign each sampled descriptor to
    its nearest word by Hamming distance, then set each word's bit to the majority
    of its members' bits; an empty word is re-seeded from a random descriptor.
    IDF is `log(keyframes / keyframes containing the word)`. Raises ValueError when
    there are fewer descriptors than words.
    """
    import cv2

    present = [d for d in descriptor_sets if len(d)]
    if not present or sum(len(d) for d in present) < words:
        raise ValueError(
            f"build_vocabulary: {sum(len(d) for d in present)} descriptors for {words} words"
        )
    everything = np.concatenate(present, axis=0)
    rng = np.random.default_rng(seed)
    chosen = everything[rng.choice(everything.shape[0], min(sample, everything.shape[0]), False)]
    bits = np.unpackbits(chosen, axis=1).astype(np.float64)
    centres = chosen[rng.choice(chosen.shape[0], words, replace=False)].copy()
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    for _ in range(iterations):
        labels = np.array([m.trainIdx for m in matcher.match(chosen, centres)], dtype=np.int64)
        counts = np.bincount(labels, minlength=words)
        ones = np.stack(
            [
                np.bincount(labels, weights=bits[:, j], minlength=words)
                for j in range(bits.shape[1])
            ],
            axis=1,
        )
        majority = (2 * ones >= counts[:, None]).astype(np.uint8)
        centres = np.packbits(majority, axis=1)
        empty = np.flatnonzero(counts == 0)
        if len(empty):
            centres[empty] = chosen[rng.choice(chosen.shape[0], len(empty), replace=False)]
    vocabulary = Vocabulary(centres, np.ones(words))
    containing = np.zeros(words)
    for descriptors in descriptor_sets:
        containing[np.unique(vocabulary.assign(descriptors))] += 1
    idf = np.log(len(descriptor_sets) / np.maximum(containing, 1.0))
    return Vocabulary(centres, idf)


def place_candidates(
    query_vectors: FloatArray, database_vectors: FloatArray, *, per_query: int, min_score: float
) -> list[tuple[int, int, float]]:
    """(query index, database index, cosine score) of the best database keyframes per query."""
    if query_vectors.shape[0] == 0 or database_vectors.shape[0] == 0:
        return []
    scores = query_vectors @ database_vectors.T
    out = []
    for q in range(scores.shape[0]):
        for d in np.argsort(-scores[q])[:per_query]:
            if scores[q, d] >= min_score:
                out.append((q, int(d), float(scores[q, d])))
    return out


def match_descriptors(a: UInt8Array, b: UInt8Array, *, ratio: float) -> list[tuple[int, int]]:
    """Mutual nearest neighbours of a in b passing the ratio test: (index in a, index in b)."""
    import cv2

    if a.shape[0] < 2 or b.shape[0] < 2:
        return []
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    forward = matcher.knnMatch(a, b, k=2)
    backward = {m.queryIdx: m.trainIdx for m in matcher.match(b, a)}
    out = []
    for pair in forward:
        if len(pair) < 2:
            continue
        best, second = pair
        if (
            best.distance < ratio * second.distance
            and best.distance <= 64
            and backward.get(best.trainIdx) == best.queryIdx
        ):
            out.append((best.queryIdx, best.trainIdx))
    return out


def triangulate(
    cam_from_session_1: FloatArray,
    cam_from_session_2: FloatArray,
    rays_1: FloatArray,
    rays_2: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Linear (DLT) triangulation of normalised rays (N, 2) from two camera poses.

    Returns points (N, 3) in the session frame and the parallax (N,) in radians
    (NaN where a point is behind either camera).
    """
    P1 = cam_from_session_1[:3]
    P2 = cam_from_session_2[:3]
    n = rays_1.shape[0]
    A = np.stack(
        (
            rays_1[:, :1] * P1[2] - P1[0],
            rays_1[:, 1:2] * P1[2] - P1[1],
            rays_2[:, :1] * P2[2] - P2[0],
            rays_2[:, 1:2] * P2[2] - P2[1],
        ),
        axis=1,
    )
    _, _, vt = np.linalg.svd(A)
    w = vt[:, -1, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        points = np.where(np.abs(w[:, None]) > 1e-12, vt[:, -1, :3] / w[:, None], np.nan)
    homogeneous = np.column_stack((points, np.ones(n)))
    z1 = homogeneous @ P1[2]
    z2 = homogeneous @ P2[2]
    centre_1 = invert_pose(cam_from_session_1)[:3, 3]
    centre_2 = invert_pose(cam_from_session_2)[:3, 3]
    d1 = points - centre_1
    d2 = points - centre_2
    cosine = np.sum(d1 * d2, axis=1) / np.maximum(
        np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1), 1e-12
    )
    parallax = np.arccos(np.clip(cosine, -1.0, 1.0))
    parallax[(z1 <= 0) | (z2 <= 0) | ~np.isfinite(z1) | ~np.isfinite(z2)] = np.nan
    return points, parallax


@dataclass(frozen=True)
class LocalMap:
    """Points (N, 3) in a session frame with the reference keyframe's descriptors (N, 32)
    and the indices (N,) of the reference's features they were triangulated from."""

    points_session: FloatArray
    descriptors: UInt8Array
    feature_index: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def local_map(
    reference: KeyframeFeatures,
    session_from_reference: FloatArray,
    neighbours: Sequence[tuple[KeyframeFeatures, FloatArray]],
    options: PlaceOptions,
    *,
    focal_px: float,
) -> LocalMap:
    """The reference keyframe's features triangulated against its neighbours (SLAM poses).

    neighbours: (features, `T_S_C`) of nearby keyframes of the same session, nearest
    first; at most `max_neighbours` of them (with the baseline) are used. A feature
    matched in a neighbour is triangulated with it and that view kept when the
    parallax is at least `min_parallax_deg` and the point reprojects within
    `triangulation_reprojection_px` in both; the point is then triangulated from the
    reference and every kept view at once, which averages the neighbours' pose noise.
    """
    ref_from_session = invert_pose(session_from_reference)
    views: dict[int, list[tuple[FloatArray, FloatArray]]] = {}
    tolerance = options.triangulation_reprojection_px / focal_px
    used = 0
    for features, session_from_cam in neighbours:
        baseline = np.linalg.norm(session_from_cam[:3, 3] - session_from_reference[:3, 3])
        if baseline < options.min_baseline_m:
            continue
        if used >= options.max_neighbours:
            break
        used += 1
        matches = match_descriptors(
            reference.descriptors, features.descriptors, ratio=options.ratio
        )
        if not matches:
            continue
        index = np.array(matches)
        cam_from_session = invert_pose(session_from_cam)
        points, parallax = triangulate(
            ref_from_session,
            cam_from_session,
            reference.normalised[index[:, 0]],
            features.normalised[index[:, 1]],
        )
        good = np.isfinite(parallax) & (parallax >= np.deg2rad(options.min_parallax_deg))
        for pose, rays in (
            (ref_from_session, reference.normalised[index[:, 0]]),
            (cam_from_session, features.normalised[index[:, 1]]),
        ):
            p = points @ pose[:3, :3].T + pose[:3, 3]
            with np.errstate(invalid="ignore", divide="ignore"):
                error = np.linalg.norm(p[:, :2] / p[:, 2:3] - rays, axis=1)
            good &= error <= tolerance
        for (i, j), keep in zip(matches, good, strict=True):
            if keep:
                views.setdefault(i, []).append((cam_from_session, features.normalised[j]))
    chosen: dict[int, FloatArray] = {}
    for i, seen in views.items():
        poses = [ref_from_session] + [v[0] for v in seen]
        rays = np.array([reference.normalised[i]] + [v[1] for v in seen])
        point = triangulate_views(poses, rays)
        if point is None:
            continue
        errors = [
            reprojection_errors(point[None], ray[None], pose)[0]
            for pose, ray in zip(poses, rays, strict=True)
        ]
        if max(errors) <= tolerance:
            chosen[i] = point
    if not chosen:
        return LocalMap(np.zeros((0, 3)), np.zeros((0, 32), dtype=np.uint8))
    keys = sorted(chosen)
    return LocalMap(
        np.array([chosen[k] for k in keys]),
        reference.descriptors[keys],
        np.array(keys, dtype=np.int64),
    )


def triangulate_views(
    cam_from_session: Sequence[FloatArray], rays: FloatArray
) -> FloatArray | None:
    """One point (3,) from its normalised rays (V, 2) in V >= 2 views (linear DLT)."""
    rows = []
    for pose, ray in zip(cam_from_session, rays, strict=True):
        rows.append(ray[0] * pose[2] - pose[0])
        rows.append(ray[1] * pose[2] - pose[1])
    _, _, vt = np.linalg.svd(np.array(rows))
    if abs(vt[-1, 3]) < 1e-12:
        return None
    return np.asarray(vt[-1, :3] / vt[-1, 3], dtype=np.float64)


@dataclass(frozen=True)
class Verification:
    """A geometrically verified candidate: `T_Sa_Sb` from one query keyframe of b.

    inliers: PnP inliers; matches: 2D-3D matches tried; tilt_deg: relative roll/pitch.
    query_features / map_points (inliers,): the inliers' feature in the query and point
    of the local map.
    """

    a_from_b: FloatArray
    inliers: int
    matches: int
    tilt_deg: float
    query_features: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    map_points: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def verify_candidate(
    query: KeyframeFeatures,
    session_b_from_query: FloatArray,
    reference_map: LocalMap,
    options: PlaceOptions,
    *,
    focal_px: float,
    reference: KeyframeFeatures | None = None,
    session_a_from_reference: FloatArray | None = None,
) -> tuple[Verification | None, int, int]:
    """PnP RANSAC of the query's features against the other session's local map, then
    the gravity-constrained refinement (yaw and translation).

    With the reference keyframe (`reference`, its pose `session_a_from_reference`)
    and `rotation_from_images`, the yaw comes from the two images directly (the
    essential matrix's relative rotation, free of the local map's noise) and only the
    translation from the map. Returns (the verification or None when refused,
    matches, inliers): refused for fewer than `min_inliers` inliers or a 6-DoF
    relative tilt over `max_tilt_deg`.
    """
    import cv2

    matches = match_descriptors(query.descriptors, reference_map.descriptors, ratio=options.ratio)
    if len(matches) < max(options.min_inliers, 6):
        return None, len(matches), 0
    index = np.array(matches)
    object_points = reference_map.points_session[index[:, 1]]
    image_points = query.normalised[index[:, 0]]
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        object_points.astype(np.float64),
        image_points.astype(np.float64),
        np.eye(3),
        None,
        iterationsCount=300,
        reprojectionError=options.ransac_reprojection_px / focal_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inliers is None or len(inliers) < options.min_inliers:
        return None, len(matches), 0 if inliers is None else len(inliers)
    chosen = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(
        object_points[chosen], image_points[chosen], np.eye(3), None, rvec, tvec
    )
    rotation, _ = cv2.Rodrigues(rvec)
    cam_from_a = make_pose(rotation, tvec.ravel())
    six_dof = invert_pose(cam_from_a) @ invert_pose(session_b_from_query)
    tilt = float(np.rad2deg(np.linalg.norm(tilt_vector_rad(six_dof[:3, :3]))))
    if tilt > options.max_tilt_deg:
        return None, len(matches), len(chosen)

    def verified(a_from_b: FloatArray, chosen: npt.NDArray[Any]) -> tuple[Verification, int, int]:
        features, points = index[chosen, 0].astype(np.int64), index[chosen, 1].astype(np.int64)
        result = Verification(a_from_b, len(chosen), len(matches), tilt, features, points)
        return result, len(matches), len(chosen)

    if options.refine_places:
        # `refine_place` adjusts the query's pose with the rest: keep the 6-DoF inliers
        # (the yaw-only fit below would lose those the query's own tilt error moves).
        return verified(_without_tilt(six_dof), chosen)
    # Both session frames are gravity-aligned: refine yaw and translation only, with
    # roll and pitch from the IMUs (the image alone trades tilt against translation).
    tolerance = options.ransac_reprojection_px / focal_px
    a_from_b = six_dof
    for _ in range(2):
        a_from_b = refine_yaw_translation(
            object_points[chosen], image_points[chosen], session_b_from_query, a_from_b
        )
        error = reprojection_errors(
            object_points, image_points, invert_pose(a_from_b @ session_b_from_query)
        )
        chosen = np.flatnonzero(error <= tolerance)
        if len(chosen) < options.min_inliers:
            return None, len(matches), len(chosen)
    if (
        options.rotation_from_images
        and reference is not None
        and session_a_from_reference is not None
    ):
        ref_from_query = relative_rotation(query, reference, options, focal_px=focal_px)
        if ref_from_query is not None:
            rotation_ab = (
                session_a_from_reference[:3, :3] @ ref_from_query @ session_b_from_query[:3, :3].T
            )
            start = make_pose(_rot_z(yaw_rad(rotation_ab)), a_from_b[:3, 3])
            image_yaw = refine_yaw_translation(
                object_points[chosen],
                image_points[chosen],
                session_b_from_query,
                start,
                hold_yaw=True,
            )
            error = reprojection_errors(
                object_points, image_points, invert_pose(image_yaw @ session_b_from_query)
            )
            kept = np.flatnonzero(error <= tolerance)
            # The map must still agree with the images' yaw (else the pair is suspect).
            if len(kept) >= options.min_inliers:
                a_from_b, chosen = image_yaw, kept
    return verified(a_from_b, chosen)


def relative_rotation(
    query: KeyframeFeatures, reference: KeyframeFeatures, options: PlaceOptions, *, focal_px: float
) -> FloatArray | None:
    """`R_Cr_Cq` (3, 3) from the two keyframes' matched features (essential matrix, RANSAC).

    None with fewer than `min_inliers` matches or inliers.
    """
    import cv2

    matches = match_descriptors(query.descriptors, reference.descriptors, ratio=options.ratio)
    if len(matches) < options.min_inliers:
        return None
    index = np.array(matches)
    rays_q = query.normalised[index[:, 0]].astype(np.float64)
    rays_r = reference.normalised[index[:, 1]].astype(np.float64)
    threshold = options.ransac_reprojection_px / focal_px
    essential, mask = cv2.findEssentialMat(
        rays_q, rays_r, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=threshold
    )
    if essential is None or essential.shape != (3, 3) or mask is None:
        return None
    count, rotation, _, mask = cv2.recoverPose(essential, rays_q, rays_r, np.eye(3), mask=mask)
    if count < options.min_inliers:
        return None
    return np.asarray(rotation, dtype=np.float64)


@dataclass(frozen=True)
class PlaceCandidate:
    """A verified candidate with what its adjustment reads: the reference keyframe of
    a with its local map and pose `T_Sa_Cr`, the query of b with its pose `T_Sb_Cq`,
    and their neighbours `(features, T_S_C)` in each session, nearest first."""

    verification: Verification
    reference_map: LocalMap
    reference: KeyframeFeatures
    session_a_from_reference: FloatArray
    query: KeyframeFeatures
    session_b_from_query: FloatArray
    neighbours_a: Sequence[tuple[KeyframeFeatures, FloatArray]]
    neighbours_b: Sequence[tuple[KeyframeFeatures, FloatArray]]


@dataclass
class _Camera:
    """A keyframe in the adjustment: its pose in its own session and the landmark each
    of its features sees."""

    side: str
    session_from_cam: FloatArray
    features: KeyframeFeatures
    sees: dict[int, int] = field(default_factory=dict)


def _neighbour_matches(
    descriptors: UInt8Array,
    landmarks: FloatArray,
    neighbour: KeyframeFeatures,
    a_from_cam: FloatArray,
    options: PlaceOptions,
    *,
    tolerance: float,
) -> list[tuple[int, int]]:
    """(landmark row, feature) pairs of one neighbour: its features matched to the
    landmarks' descriptors, kept where the landmark (in a) reprojects within
    `tolerance` (z=1 units) through the neighbour's pose in a."""
    matches = match_descriptors(descriptors, neighbour.descriptors, ratio=options.ratio)
    if not matches:
        return []
    index = np.array(matches)
    error = reprojection_errors(
        landmarks[index[:, 0]], neighbour.normalised[index[:, 1]], invert_pose(a_from_cam)
    )
    return [(int(i), int(j)) for (i, j), e in zip(matches, error, strict=True) if e <= tolerance]


def refine_place(
    candidates: Sequence[PlaceCandidate],
    options: PlaceOptions,
    *,
    focal_px: float,
    tilt_sigma_rad: float,
    start: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """`T_Sa_Sb` (4, 4) and its covariance (6, 6, `[δθ, δt]` in Sa) from a bundle
    adjustment of the keyframes around the candidates' references and queries, or None
    when it cannot be set up, does not converge or turns far from `start`.

    The PnP of one query keyframe against a map triangulated from two or three SLAM
    poses carries those poses' own errors twice: the query's pose error enters
    `T_Sa_Sb` directly, and the neighbours' relative pose errors warp the map, which
    turns the PnP (0.15 deg of SLAM error per keyframe gave candidates up to 1 deg off
    on the simulated wreck). Here the candidates' PnP inliers become landmarks seen by
    the references, the queries and the keyframes around each (matched to the
    landmarks' descriptors; one landmark per feature of a keyframe); every camera pose
    is free but held to its SLAM pose with the keyframe noise (`keyframe_noise_*`,
    robustly), b's through the unknown `T_Sa_Sb`, whose roll and pitch get a prior
    about zero (both frames are gravity-aligned; `tilt_sigma_rad`). The images then
    fix the map's shape and each keyframe's pose relative to its neighbours, and the
    SLAM error that is left is the mean over the neighbourhoods. The covariance (the
    adjustment's marginal) keeps how the place trades yaw against translation: the
    images fix where the filmed structure lies far better than the yaw about it.
    Candidates of one place share keyframes and so their SLAM errors: adjusted together
    they are one measurement, as they should be.

    tilt_sigma_rad: the prior on the relative roll and pitch of `T_Sa_Sb` about zero
    (both frames gravity-aligned: the IMUs' error), estimated with the rest.
    start: the initial `T_Sa_Sb` (its tilt dropped); None: the first candidate's.
    """
    import gtsam

    if not candidates:
        return None
    first = candidates[0].verification.a_from_b if start is None else start
    a_from_b = _without_tilt(first)
    tolerance = options.triangulation_reprojection_px / focal_px
    rows: dict[tuple[int, int], int] = {}
    positions: list[FloatArray] = []
    cameras: dict[tuple[str, int], _Camera] = {}

    def camera(side: str, features: KeyframeFeatures, pose: FloatArray) -> _Camera:
        return cameras.setdefault((side, features.stamp_ns), _Camera(side, pose, features))

    for c in candidates:
        v = c.verification
        ids = []
        for point in v.map_points.tolist():
            key = (c.reference.stamp_ns, point)
            if key not in rows:
                rows[key] = len(positions)
                positions.append(c.reference_map.points_session[point])
            ids.append(rows[key])
        here = np.array(ids, dtype=np.int64)
        reference = camera("a", c.reference, c.session_a_from_reference)
        query = camera("b", c.query, c.session_b_from_query)
        for landmark, feature_r, feature_q in zip(
            here.tolist(),
            c.reference_map.feature_index[v.map_points].tolist(),
            v.query_features.tolist(),
            strict=True,
        ):
            reference.sees.setdefault(feature_r, landmark)
            query.sees.setdefault(feature_q, landmark)
        points = np.array([positions[i] for i in ids]).reshape(-1, 3)
        for side, neighbours, descriptors in (
            ("a", c.neighbours_a, c.reference_map.descriptors[v.map_points]),
            ("b", c.neighbours_b, c.query.descriptors[v.query_features]),
        ):
            for features, session_from_cam in neighbours[: options.refine_neighbours]:
                in_a = session_from_cam if side == "a" else a_from_b @ session_from_cam
                seen = _neighbour_matches(
                    descriptors, points, features, in_a, options, tolerance=tolerance
                )
                if len(seen) < options.refine_min_observations:
                    continue
                neighbour = camera(side, features, session_from_cam)
                for row, feature in seen:
                    neighbour.sees.setdefault(feature, int(here[row]))
    # A feature sees one landmark: a landmark that lost its second view to another
    # (two maps of one place triangulate the same structure) is left out.
    views = np.zeros(len(positions), dtype=np.int64)
    for cam in cameras.values():
        np.add.at(views, np.fromiter(cam.sees.values(), dtype=np.int64), 1)
    for cam in cameras.values():
        cam.sees = {f: lm for f, lm in cam.sees.items() if views[lm] >= 2}
    used = np.flatnonzero(views >= 2)
    if len(used) < options.min_inliers or len(cameras) < 3:
        return None
    X = gtsam.symbol_shorthand.X
    L = gtsam.symbol_shorthand.L
    T = gtsam.symbol_shorthand.T(0)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    # Robust: a keyframe whose SLAM pose is grossly wrong must not bend the rest.
    pose_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(2.0),
        gtsam.noiseModel.Diagonal.Sigmas(
            np.array(
                [np.deg2rad(options.keyframe_noise_rotation_deg)] * 3
                + [options.keyframe_noise_translation_m] * 3
            )
        ),
    )
    pixel_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Isotropic.Sigma(2, options.refine_pixel_sigma_px / focal_px),
    )
    calibration = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    # Roll and pitch of T_Sa_Sb about zero (gravity), yaw and translation free.
    sigmas = np.array([tilt_sigma_rad, tilt_sigma_rad, 10.0, 100.0, 100.0, 100.0])
    graph.add(
        gtsam.PriorFactorPose3(T, gtsam.Pose3(a_from_b), gtsam.noiseModel.Diagonal.Sigmas(sigmas))
    )
    values.insert(T, gtsam.Pose3(a_from_b))
    for k, cam in enumerate(cameras.values()):
        if cam.side == "a":
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(cam.session_from_cam), pose_noise))
            values.insert(X(k), gtsam.Pose3(cam.session_from_cam))
        else:
            graph.add(
                gtsam.BetweenFactorPose3(T, X(k), gtsam.Pose3(cam.session_from_cam), pose_noise)
            )
            values.insert(X(k), gtsam.Pose3(a_from_b @ cam.session_from_cam))
        for feature, landmark in cam.sees.items():
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    np.asarray(cam.features.normalised[feature], dtype=np.float64),
                    pixel_noise,
                    X(k),
                    L(landmark),
                    calibration,
                )
            )
    # A weak prior (1 m) keeps a landmark whose views barely differ determinate.
    landmark_noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    for landmark in used.tolist():
        position = np.asarray(positions[landmark], dtype=np.float64)
        values.insert(L(landmark), position)
        graph.add(gtsam.PriorFactorPoint3(L(landmark), position, landmark_noise))
    parameters = gtsam.LevenbergMarquardtParams()
    parameters.setMaxIterations(30)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, parameters).optimize()
        body = gtsam.Marginals(graph, result).marginalCovariance(T)
    except RuntimeError:
        return None
    refined = np.asarray(result.atPose3(T).matrix(), dtype=np.float64)
    if not np.all(np.isfinite(refined)) or not np.all(np.isfinite(body)):
        return None
    # The adjustment corrects a PnP against a map warped by its keyframes' SLAM errors
    # by a degree or two; one that turned much further went astray (a false match).
    residual = pose_residuals(refined[None], a_from_b)[0]
    if np.rad2deg(np.linalg.norm(residual[:3])) > options.refine_max_change_deg:
        return None
    # GTSAM perturbs on the right (T Exp([ω, v]), body frame); `[δθ, δt]` is on the left.
    rotate = np.kron(np.eye(2), refined[:3, :3])
    covariance = rotate @ np.asarray(body, dtype=np.float64) @ rotate.T
    return refined, 0.5 * (covariance + covariance.T)


def with_tilt_prior(
    a_from_b: FloatArray, covariance: FloatArray, tilt_variance_rad2: float
) -> tuple[FloatArray, FloatArray]:
    """`T_Sa_Sb` and its covariance (6, 6) with gravity's prior on the relative roll and
    pitch (zero, `tilt_variance_rad2` each) added once: the pair's mean over its places
    measured the tilt from the images, each place without that prior (it is one piece
    of information, not one per place). The yaw and translation follow through their
    correlation with the tilt."""
    tilt = tilt_vector_rad(a_from_b[:3, :3])
    information = np.linalg.inv(covariance)
    prior = np.zeros((6, 6))
    prior[0, 0] = prior[1, 1] = 1.0 / tilt_variance_rad2
    fused = np.linalg.inv(information + prior)
    step = fused @ (prior @ np.r_[-tilt, 0.0, 0.0, 0.0, 0.0])
    pose = make_pose(so3_exp(step[:3]) @ a_from_b[:3, :3], a_from_b[:3, 3] + step[3:])
    return pose, 0.5 * (fused + fused.T)


def _without_tilt(pose: FloatArray) -> FloatArray:
    """`pose` (4, 4) with its rotation replaced by the nearest rotation about z."""
    return make_pose(_rot_z(yaw_rad(pose[:3, :3])), pose[:3, 3])


def reprojection_errors(
    points: FloatArray, rays: FloatArray, cam_from_points: FloatArray
) -> FloatArray:
    """(N,) distance on the z=1 plane between projected points (N, 3) and rays (N, 2);
    infinite behind the camera."""
    p = points @ cam_from_points[:3, :3].T + cam_from_points[:3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        error = np.linalg.norm(p[:, :2] / p[:, 2:3] - rays, axis=1)
    return np.asarray(np.where(p[:, 2] > 1e-6, error, np.inf), dtype=np.float64)


def _rot_z(angle: float) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def refine_yaw_translation(
    points_a: FloatArray,
    rays: FloatArray,
    session_b_from_query: FloatArray,
    start: FloatArray,
    *,
    iterations: int = 10,
    hold_yaw: bool = False,
) -> FloatArray:
    """`T_Sa_Sb` = (Rz(yaw), t) minimising the query's reprojection errors (Huber).

    points_a: (N, 3) in session a; rays: (N, 2) the query's undistorted features;
    session_b_from_query: the query camera's pose in b; start: (4, 4) initial guess
    (its tilt is dropped). Roll and pitch of `T_Sa_Sb` are zero: both frames are
    gravity-aligned. hold_yaw: keep the start's yaw, fit the translation only.
    """
    x = np.concatenate(([yaw_rad(start[:3, :3])], start[:3, 3]))

    def residual(params: FloatArray) -> FloatArray:
        a_from_b = make_pose(_rot_z(float(params[0])), params[1:])
        cam_from_a = invert_pose(a_from_b @ session_b_from_query)
        p = points_a @ cam_from_a[:3, :3].T + cam_from_a[:3, 3]
        return np.asarray((p[:, :2] / p[:, 2:3] - rays).reshape(-1), dtype=np.float64)

    for _ in range(iterations):
        r = residual(x)
        jacobian = np.zeros((r.shape[0], 4))
        for k in range(1 if hold_yaw else 0, 4):
            h = np.zeros(4)
            h[k] = 1e-6
            jacobian[:, k] = (residual(x + h) - residual(x - h)) / 2e-6
        # Huber weights per coordinate at 1.345 robust sigmas (the MAD of the residuals).
        scale = max(1.4826 * float(np.median(np.abs(r))), 1e-6)
        w = np.minimum(1.0, 1.345 * scale / np.maximum(np.abs(r), 1e-15))
        step = np.linalg.lstsq(jacobian * w[:, None] ** 0.5, -r * w**0.5, rcond=None)[0]
        x = x + step
        if np.linalg.norm(step) < 1e-10:
            break
    return make_pose(_rot_z(float(x[0])), x[1:])


def consistent_candidates(
    poses: FloatArray, weights: FloatArray, *, rotation_rad: float, translation_m: float
) -> npt.NDArray[np.bool_]:
    """The largest group (N,) of candidate `T_Sa_Sb` (N, 4, 4) that agree with one another.

    Two candidates agree when they differ by less than both tolerances. The seed is
    the candidate agreeing with the most others (ties: the larger summed weight); the
    group is every candidate agreeing with the seed and with the group's mean.
    """
    n = poses.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool)
    agree = np.zeros((n, n), dtype=bool)
    for i in range(n):
        r = pose_residuals(poses, poses[i])
        agree[i] = (np.linalg.norm(r[:, :3], axis=1) < rotation_rad) & (
            np.linalg.norm(r[:, 3:], axis=1) < translation_m
        )
    support = agree.sum(axis=1) + (agree @ weights) / (np.sum(weights) + 1.0)
    seed = int(np.argmax(support))
    group: npt.NDArray[np.bool_] = agree[seed].copy()
    mean = weighted_pose_mean(poses[group], weights[group])
    r = pose_residuals(poses, mean)
    group &= (np.linalg.norm(r[:, :3], axis=1) < rotation_rad) & (
        np.linalg.norm(r[:, 3:], axis=1) < translation_m
    )
    return group


def weighted_pose_mean(poses: FloatArray, weights: FloatArray) -> FloatArray:
    from shared.geometry import rotation_mean_chordal

    rotation = rotation_mean_chordal(poses[:, :3, :3], weights)
    translation = np.average(poses[:, :3, 3], axis=0, weights=weights)
    return make_pose(rotation, translation)


def candidate_clusters(
    times_a_s: FloatArray, times_b_s: FloatArray, *, gap_s: float
) -> npt.NDArray[np.int64]:
    """Label (N,) candidates into places: linked when within `gap_s` in both sessions.

    Candidates of one place share their map and their query's neighbourhood, so their
    errors are not independent (the targets' passes, `averaging.clustered_covariance`).
    """
    n = len(times_a_s)
    labels = np.arange(n)
    for i in range(n):
        for j in range(i + 1, n):
            if (
                abs(times_a_s[i] - times_a_s[j]) <= gap_s
                and abs(times_b_s[i] - times_b_s[j]) <= gap_s
            ):
                old, new = labels[j], labels[i]
                labels[labels == old] = new
    _, out = np.unique(labels, return_inverse=True)
    return np.asarray(out, dtype=np.int64)


def candidate_noise(
    residuals: FloatArray, clusters: npt.NDArray[np.int64], *, floor: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per-axis variances (6,) of a candidate's own noise and of its place's shared error.

    residuals: (N, 6) about the candidates' mean. Moments, robust (median-based): the
    scatter inside places gives the independent part; the whole scatter minus it the
    part a place's candidates share (drift differences between places end up there
    too, which errs on the side of a looser covariance). With fewer than 3
    candidates both are 100 x `floor`.
    """
    n = residuals.shape[0]
    if n < 3:
        return floor * 100.0, floor * 100.0
    # Median of squares of a normal variable is 0.455 times its variance.
    total = np.median(residuals**2, axis=0) / 0.455
    differences = [
        residuals[i] - residuals[j]
        for i in range(n)
        for j in range(i + 1, n)
        if clusters[i] == clusters[j]
    ]
    if len(differences) >= 3:
        independent = 0.5 * np.median(np.array(differences) ** 2, axis=0) / 0.455
    else:
        independent = total
    independent = np.maximum(independent, floor)
    shared = np.maximum(total - independent, 0.0)
    return np.asarray(independent, dtype=np.float64), np.asarray(shared, dtype=np.float64)


@dataclass
class PairEvidence:
    """What place recognition found between sessions a (reference side) and b (queries).

    candidates: (query stamp, reference stamp, score) tried; verified: those passing
    PnP and the gravity check with their inliers; consistent: stamps of the verified
    ones in the agreeing group that the pair's mean uses; rejected: those of the group
    beyond their modelled errors (`pair_place_mean`); mergeable: at least
    `min_consistent` consistent ones.
    times_*_s, gains_*: the consistent candidates' times since each anchor and how
    each session's drift there enters `a_from_b` (`PairMean`).
    """

    session_a: str
    session_b: str
    candidates: list[tuple[int, int, float]] = field(default_factory=list)
    verified: list[tuple[int, int, int]] = field(default_factory=list)
    inliers_tried: list[int] = field(default_factory=list)
    consistent: list[tuple[int, int]] = field(default_factory=list)
    rejected: list[tuple[int, int]] = field(default_factory=list)
    mergeable: bool = False
    reason: str = ""
    a_from_b: FloatArray | None = None
    covariance: FloatArray | None = None
    poses: FloatArray | None = None
    times_a_s: FloatArray | None = None
    times_b_s: FloatArray | None = None
    gains_a: FloatArray | None = None
    gains_b: FloatArray | None = None

    def summary(self) -> dict[str, object]:
        """The evidence as JSON-ready numbers."""
        scores = sorted((c[2] for c in self.candidates), reverse=True)
        inliers = sorted((v[2] for v in self.verified), reverse=True)
        return {
            "sessions": [self.session_a, self.session_b],
            "mergeable": self.mergeable,
            "reason": self.reason,
            "candidates": len(self.candidates),
            "best_scores": [round(s, 4) for s in scores[:10]],
            "verified": len(self.verified),
            "verified_inliers": inliers[:20],
            "best_inliers_tried": sorted(self.inliers_tried, reverse=True)[:10],
            "consistent": len(self.consistent),
            "consistent_stamps_ns": [list(c) for c in self.consistent],
            "rejected_stamps_ns": [list(c) for c in self.rejected],
        }


def angle_deg(a: FloatArray, b: FloatArray) -> float:
    """Rotation angle (deg) between two poses."""
    return float(np.rad2deg(rotation_angle_rad(a[:3, :3].T @ b[:3, :3])))


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def pivot_jacobian(lever: FloatArray, rotation: FloatArray | None = None) -> FloatArray:
    """(6, 6) map from an error `[ω, u]` pivoting about a point to the residual of
    `T_Sa_Sb` (`[δθ, δt]`, pivoting about Sb's origin): `δθ = Rω`, `δt = Ru + Rω × lever`.

    lever (3,): from the pivot to Sb's origin, in Sa; rotation: R from the error's frame
    into Sa (identity when None).
    """
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[3:, 3:] = R
    out[3:, :3] = -_skew(np.asarray(lever, dtype=np.float64)) @ R
    return out


@dataclass(frozen=True)
class PairMean:
    """A pair's `T_Sa_Sb` (4, 4), its covariance (6, 6) and the drift it carries.

    gains_a / gains_b (N, 6, 6): how the drift of session a at each candidate's
    reference keyframe (of b at its query) enters the mean's error (`joint.DriftShare`);
    zero for a rejected candidate. inliers (N,): the candidates the mean is made of
    (the others' whitened residual exceeded `max_whitened_sq`).
    """

    a_from_b: FloatArray
    covariance: FloatArray
    gains_a: FloatArray
    gains_b: FloatArray
    inliers: npt.NDArray[np.bool_]


def same_keyframe(times_s: FloatArray, *, tolerance_s: float = 1e-3) -> FloatArray:
    """(N, N) 1 where two candidates use the same keyframe (equal times), else 0."""
    t = np.asarray(times_s, dtype=np.float64)
    return (np.abs(t[:, None] - t[None]) <= tolerance_s).astype(np.float64)


def pair_place_mean(
    poses: FloatArray,
    times_a_s: FloatArray,
    times_b_s: FloatArray,
    reference_positions: FloatArray,
    query_positions: FloatArray,
    *,
    rate_a: FloatArray,
    rate_b: FloatArray,
    clusters: npt.NDArray[np.int64],
    floor: FloatArray,
    start: FloatArray,
    fixed_axes: int = 0,
    iterations: int = 2,
    keyframe_noise_a: FloatArray | None = None,
    keyframe_noise_b: FloatArray | None = None,
    max_whitened_sq: float | None = None,
    covariances: FloatArray | None = None,
) -> PairMean:
    """Generalised least-squares `T_Sa_Sb` from candidates whose errors pivot about places.

    A candidate is `T_Sa_Cq @ inv(T_Sb_Cq)`: an error of the query's pose or of the PnP
    is a rotation about the query camera, the drift of a rotates about a's reference
    camera, that of b about the query camera in b. Seen from Sb's origin (the pose's
    convention) a rotation error ω about a camera a lever L away moves the translation
    by ω × L: with levers of 10 m, 0.3 deg of yaw is 5 cm, and the candidates'
    translations scatter with their yaw. Here each error is modelled where it pivots
    (`pivot_jacobian`), so the translation is not blurred by the yaw, and the
    covariance (full 6x6) keeps their coupling.

    poses (N, 4, 4): candidates; times_* (N,): seconds since each session's anchor;
    reference_positions / query_positions (N, 3): the reference camera and the query
    camera in Sa (metres). rate_* (6,): drift variance rates (rad²/s, m²/s) of each
    session in its pivot form `[ω, u]`. clusters (N,): the candidates' places
    (`candidate_clusters`); the independent noise and a place's shared error are
    estimated from the pivot-form residuals (`candidate_noise`, at least `floor` (6,)).
    Per candidate i and j the covariance is
    `A_i (q_a min(ta_i, ta_j) + k_a [same reference keyframe]) A_jᵀ + B_i (q_b min(tb_i,
    tb_j) + k_b [same query keyframe]) B_jᵀ + Q_i (c [same place] + s δ_ij) Q_jᵀ` (A, B,
    Q: pivots at the reference camera, the query camera in b, the query camera in a).
    keyframe_noise_* (6,): each keyframe's own SLAM pose error besides the drift
    (variances of `[ω, u]` about the camera, rad² and m²; None: 0). Every candidate
    that uses a keyframe carries all of its error: one query keyframe matched against
    four places of a moves all four candidates alike, so they are one measurement of
    that keyframe, not four (the same for a reference keyframe and its local map).
    Scaled up by the a posteriori variance factor when the candidates scatter more
    than that; fixed_axes: how many axes every candidate holds at the same value by
    construction (2: roll and pitch from gravity), which carry no scatter and are left
    out of the factor's degrees of freedom and of the outlier test.

    max_whitened_sq: a candidate whose residual about the mean, whitened by its own
    modelled covariance (drift, keyframe and place noise, the mean's uncertainty) over
    the free axes, exceeds this is rejected and the mean recomputed without it, until
    no more go (never below 3 candidates). The consistency check before
    (`consistent_candidates`) compares the candidates at Sb's origin, where a yaw error
    of 1 deg at a place 15 m away is 26 cm, so its translation tolerance must be wide;
    here the translation is tested where it pivots, to centimetres. None: no test.

    covariances (N, 6, 6): each candidate's own measured covariance (`[δθ, δt]` in Sa,
    `refine_place`, its keyframes' SLAM errors included): it then stands for the
    noise estimated from the scatter, the places' shared error and the keyframe noise.
    """
    T = np.asarray(poses, dtype=np.float64)
    keep = np.ones(T.shape[0], dtype=bool)
    while True:
        chosen = np.flatnonzero(keep)
        mean, whitened_sq = _pair_place_gls(
            T[chosen],
            np.asarray(times_a_s, dtype=np.float64)[chosen],
            np.asarray(times_b_s, dtype=np.float64)[chosen],
            np.asarray(reference_positions, dtype=np.float64)[chosen],
            np.asarray(query_positions, dtype=np.float64)[chosen],
            rate_a=np.asarray(rate_a, dtype=np.float64),
            rate_b=np.asarray(rate_b, dtype=np.float64),
            clusters=np.asarray(clusters)[chosen],
            floor=floor,
            start=start,
            fixed_axes=fixed_axes,
            iterations=iterations,
            keyframe_noise_a=keyframe_noise_a,
            keyframe_noise_b=keyframe_noise_b,
            covariances=None if covariances is None else np.asarray(covariances)[chosen],
        )
        if max_whitened_sq is None or len(chosen) <= 3:
            break
        worst = int(np.argmax(whitened_sq))
        if whitened_sq[worst] <= max_whitened_sq:
            break
        # One at a time, the worst first: a gross candidate inflates the noise estimate
        # and the others' residuals until it is gone.
        keep[chosen[worst]] = False
    n = T.shape[0]
    gains_a = np.zeros((n, 6, 6))
    gains_b = np.zeros((n, 6, 6))
    gains_a[keep] = mean.gains_a
    gains_b[keep] = mean.gains_b
    return PairMean(mean.a_from_b, mean.covariance, gains_a, gains_b, keep)


def _pair_place_gls(
    T: FloatArray,
    times_a_s: FloatArray,
    times_b_s: FloatArray,
    reference_positions: FloatArray,
    query_positions: FloatArray,
    *,
    rate_a: FloatArray,
    rate_b: FloatArray,
    clusters: npt.NDArray[np.int64],
    floor: FloatArray,
    start: FloatArray,
    fixed_axes: int,
    iterations: int,
    keyframe_noise_a: FloatArray | None,
    keyframe_noise_b: FloatArray | None,
    covariances: FloatArray | None = None,
) -> tuple[PairMean, FloatArray]:
    """`pair_place_mean` over the given candidates; with each one's whitened squared
    residual (N,) over the free axes."""
    n = T.shape[0]
    ta = np.maximum(times_a_s, 0.0)
    tb = np.maximum(times_b_s, 0.0)
    same = (clusters[:, None] == clusters[None]).astype(np.float64)
    # A keyframe's own error reaches every candidate that uses it: a's through the
    # reference camera (its local map), b's through the query camera.
    shared_a = np.minimum.outer(ta, ta)[:, None, :] * rate_a[None, :, None]
    shared_b = np.minimum.outer(tb, tb)[:, None, :] * rate_b[None, :, None]
    if keyframe_noise_a is not None and covariances is None:
        shared_a = shared_a + same_keyframe(ta)[:, None, :] * keyframe_noise_a[None, :, None]
    if keyframe_noise_b is not None and covariances is None:
        shared_b = shared_b + same_keyframe(tb)[:, None, :] * keyframe_noise_b[None, :, None]
    mean = np.asarray(start, dtype=np.float64).copy()
    design = np.tile(np.eye(6), (n, 1))
    covariance: FloatArray = np.eye(6)
    gain = np.zeros((6, 6 * n))
    A = np.zeros((n, 6, 6))
    B = np.zeros((n, 6, 6))
    Q = np.zeros((n, 6, 6))
    sigma = np.eye(6 * n)
    factor = 1.0
    for _ in range(max(iterations, 1)):
        r = pose_residuals(T, mean)
        rotation = mean[:3, :3]
        for i in range(n):
            A[i] = pivot_jacobian(mean[:3, 3] - reference_positions[i])
            B[i] = -pivot_jacobian(mean[:3, 3] - query_positions[i], rotation)
            Q[i] = pivot_jacobian(mean[:3, 3] - query_positions[i])
        pivoted = np.einsum("iab,ib->ia", np.linalg.inv(Q), r)
        pivoted -= np.median(pivoted, axis=0)
        if covariances is None:
            noise, shared = candidate_noise(pivoted, clusters, floor=floor)
        else:
            noise, shared = floor, np.zeros(6)
        sigma = np.einsum("iak,ikj,jbk->iajb", A, shared_a, A)
        sigma += np.einsum("iak,ikj,jbk->iajb", B, shared_b, B)
        sigma += np.einsum("iak,k,ij,jbk->iajb", Q, shared, same, Q)
        sigma += np.einsum("iak,k,ij,jbk->iajb", Q, noise, np.eye(n), Q)
        if covariances is not None:
            sigma += np.einsum("ij,iab->iajb", np.eye(n), covariances)
        sigma = sigma.reshape(6 * n, 6 * n)
        solved = np.linalg.solve(sigma, np.column_stack((design, r.reshape(-1))))
        information = design.T @ solved[:, :6]
        covariance = np.asarray(np.linalg.inv(information), dtype=np.float64)
        step = covariance @ (design.T @ solved[:, 6])
        about = r.reshape(-1) - design @ step
        dof = (6 - fixed_axes) * (n - 1)
        factor = max(float(about @ np.linalg.solve(sigma, about)) / max(dof, 1), 1.0)
        covariance = covariance * factor
        gain = np.linalg.inv(information) @ solved[:, :6].T
        mean = make_pose(so3_exp(step[:3]) @ mean[:3, :3], mean[:3, 3] + step[3:])
    r = pose_residuals(T, mean)
    free = np.arange(fixed_axes, 6)
    whitened_sq = np.zeros(n)
    # The modelled covariance, not scaled by the a posteriori factor: a gross candidate
    # inflates that factor and would hide itself; the noise estimate is median-based.
    model_covariance = covariance / factor
    for i in range(n):
        own = sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] + model_covariance
        block = own[np.ix_(free, free)]
        whitened_sq[i] = float(r[i, free] @ np.linalg.solve(block, r[i, free]))
    blocks = gain.reshape(6, n, 6).transpose(1, 0, 2)
    return (
        PairMean(
            a_from_b=mean,
            covariance=0.5 * (covariance + covariance.T),
            gains_a=np.einsum("iab,ibc->iac", blocks, A),
            gains_b=np.einsum("iab,ibc->iac", blocks, B),
            inliers=np.ones(n, dtype=bool),
        ),
        whitened_sq,
    )
