"""Natural-feature constraints between sessions: the I/O side of `places`.

Reads each session's keyframe images, extracts ORB features, builds the
vocabulary from all sessions together, and for every pair of sessions runs
recognition, verification, the consistency check and the drift-aware mean
(`places`). The result per pair is a `PairEvidence`: mergeable with
`T_Sa_Sb` and its covariance, or not, with the scores and inlier counts that
say why.
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from postproc.merge.places import (
    KeyframeFeatures,
    LocalMap,
    PairEvidence,
    PlaceCandidate,
    PlaceOptions,
    build_vocabulary,
    candidate_clusters,
    consistent_candidates,
    extract_features,
    local_map,
    pair_place_mean,
    place_candidates,
    refine_place,
    verify_candidate,
    weighted_pose_mean,
    with_tilt_prior,
)
from shared.clock import ns_from_seconds, seconds_from_ns
from shared.errors import InputError
from shared.progress import progress

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
# The prior of the places' adjustments on the pair's relative roll and pitch: loose, so
# that the images measure them; gravity's own prior goes once onto the pair's mean
# (`with_tilt_prior`), not once per place.
IMAGE_TILT_SIGMA_RAD = 1.0


def session_features(options: PlaceOptions, session: Any) -> list[KeyframeFeatures]:
    """ORB features of every keyframe with an image, in keyframe order (read and
    extracted over a thread pool: OpenCV releases Python's lock)."""
    import cv2

    def features(item: tuple[int, Path]) -> KeyframeFeatures:
        stamp, path = item
        # IMREAD_GRAYSCALE always decodes to 8-bit.
        image = cast(npt.NDArray[np.uint8], cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
        if image is None:
            raise InputError(f"{path}: cannot read the keyframe image")
        pixels, descriptors = extract_features(
            image, options.features_per_keyframe, levels=options.orb_levels
        )
        rays = session.camera.unproject(pixels)[:, :2] if len(pixels) else np.zeros((0, 2))
        finite = np.all(np.isfinite(rays), axis=1)
        return KeyframeFeatures(stamp, pixels[finite], rays[finite], descriptors[finite])

    stamps = [int(s) for s in session.keyframes.stamps_ns.tolist()]
    items = [(s, session.images[s]) for s in stamps if s in session.images]
    with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        return list(
            progress(
                pool.map(features, items),
                total=len(items),
                desc=f"merge: {session.name} features",
                unit="kf",
            )
        )


def match_sessions(
    options: PlaceOptions,
    sessions: Sequence[Any],
    *,
    drift_rates: Mapping[str, FloatArray],
    tilt_variance_rad2: float,
    keyframe_noise: Mapping[str, FloatArray] | None = None,
) -> list[PairEvidence]:
    """Place recognition and verification for every pair of sessions (a before b).

    sessions: the stage's `Session` objects (name, camera, keyframes `T_S_C`,
    images, anchor_ns). drift_rates: per session the random-walk variance rates
    (6,) (rad²/s, m²/s) of its SLAM. tilt_variance_rad2: the variance given to each
    pair's relative roll and pitch, which the candidates take from gravity (zero) and
    do not measure: the two IMUs' tilt errors (2σ²), or a large value when the joint
    estimate applies the gravity prior itself. keyframe_noise: per session each
    keyframe's own pose error variances (6,) (rad², m²) where measured (its targets'
    drift model); the others get `keyframe_noise_*` of the options. Returns one
    `PairEvidence` per pair.
    """
    prior_noise = np.array(
        [np.deg2rad(options.keyframe_noise_rotation_deg) ** 2] * 3
        + [options.keyframe_noise_translation_m**2] * 3
    )
    noise = {s.name: prior_noise for s in sessions}
    noise.update(keyframe_noise or {})
    features = {s.name: session_features(options, s) for s in sessions}
    descriptors = [f.descriptors for kfs in features.values() for f in kfs]
    total = sum(len(d) for d in descriptors)
    vocabulary = build_vocabulary(
        descriptors,
        # Small surveys get fewer words: about 20 sampled descriptors per word.
        words=max(min(options.vocabulary_words, min(total, options.vocabulary_sample) // 20), 16),
        sample=options.vocabulary_sample,
        seed=options.seed,
    )
    vectors = {}
    for name, kfs in features.items():
        for f in kfs:
            f.words = vocabulary.assign(f.descriptors)
        vectors[name] = vocabulary.vectors([f.words for f in kfs])
    results = []
    for i, a in enumerate(sessions):
        for b in sessions[i + 1 :]:
            results.append(
                _match_pair(
                    options,
                    a,
                    b,
                    features,
                    vectors,
                    drift_rates=drift_rates,
                    tilt_variance_rad2=tilt_variance_rad2,
                    keyframe_noise=noise,
                )
            )
    return results


def _nearby(
    features: Sequence[KeyframeFeatures],
    poses: Mapping[int, FloatArray],
    index: int,
    window_s: float,
) -> list[tuple[KeyframeFeatures, FloatArray]]:
    """(features, `T_S_C`) of the session's other keyframes within `window_s` of the one
    at `index`, nearest in time first (`features` in keyframe order: increasing stamps)."""
    stamp = features[index].stamp_ns
    window = ns_from_seconds(window_s)
    lo, hi = index, index + 1
    while lo > 0 and stamp - features[lo - 1].stamp_ns <= window:
        lo -= 1
    while hi < len(features) and features[hi].stamp_ns - stamp <= window:
        hi += 1
    out = [(f, poses[f.stamp_ns]) for f in [*features[lo:index], *features[index + 1 : hi]]]
    out.sort(key=lambda n: abs(n[0].stamp_ns - stamp))
    return out


def _match_pair(
    options: PlaceOptions,
    a: Any,
    b: Any,
    features: Mapping[str, list[KeyframeFeatures]],
    vectors: Mapping[str, FloatArray],
    *,
    drift_rates: Mapping[str, FloatArray],
    tilt_variance_rad2: float,
    keyframe_noise: Mapping[str, FloatArray],
) -> PairEvidence:
    evidence = PairEvidence(a.name, b.name)
    fa, fb = features[a.name], features[b.name]
    pose_a = {int(s): p for s, p in zip(a.keyframes.stamps_ns, a.keyframes.poses, strict=True)}
    pose_b = {int(s): p for s, p in zip(b.keyframes.stamps_ns, b.keyframes.poses, strict=True)}
    focal = float(np.mean(np.diag(a.camera.intrinsic_matrix)[:2]))
    verified = []
    # With `refine_places`: each verified candidate as its adjustment reads it.
    prepared: list[PlaceCandidate] = []
    candidates = place_candidates(
        vectors[b.name],
        vectors[a.name],
        per_query=options.candidates_per_query,
        min_score=options.min_score,
    )

    def reference_map(d: int) -> LocalMap:
        neighbours = _nearby(fa, pose_a, d, options.neighbour_window_s)
        return local_map(fa[d], pose_a[fa[d].stamp_ns], neighbours, options, focal_px=focal)

    # The references' local maps over a thread pool (OpenCV's matching releases
    # Python's lock); the candidates then in order.
    references = sorted({d for _, d, _ in candidates})
    with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        built = progress(
            pool.map(reference_map, references),
            total=len(references),
            desc=f"merge: local maps of {a.name}",
            unit="kf",
        )
        maps = dict(zip(references, built, strict=True))
    for q, d, score in progress(
        candidates, total=len(candidates), desc=f"merge: places {a.name}-{b.name}", unit="cand"
    ):
        query, reference = fb[q], fa[d]
        evidence.candidates.append((query.stamp_ns, reference.stamp_ns, score))
        if maps[d].points_session.shape[0] < options.min_inliers:
            evidence.inliers_tried.append(0)
            continue
        result, _, inliers = verify_candidate(
            query,
            pose_b[query.stamp_ns],
            maps[d],
            options,
            focal_px=focal,
            reference=reference,
            session_a_from_reference=pose_a[reference.stamp_ns],
        )
        evidence.inliers_tried.append(inliers)
        if result is None:
            continue
        if options.refine_places:
            candidate = PlaceCandidate(
                result,
                maps[d],
                reference,
                pose_a[reference.stamp_ns],
                query,
                pose_b[query.stamp_ns],
                _nearby(fa, pose_a, d, options.refine_window_s),
                _nearby(fb, pose_b, q, options.refine_window_s),
            )
            refined = refine_place(
                [candidate], options, focal_px=focal, tilt_sigma_rad=IMAGE_TILT_SIGMA_RAD
            )
            if refined is None:
                continue
            result = replace(result, a_from_b=refined[0])
            prepared.append(replace(candidate, verification=result))
        evidence.verified.append((query.stamp_ns, reference.stamp_ns, result.inliers))
        verified.append((query.stamp_ns, reference.stamp_ns, result))
    if len(verified) < options.min_consistent:
        evidence.reason = (
            f"{len(verified)} candidate(s) passed PnP and the gravity check "
            f"(at least {options.min_consistent} agreeing ones needed)"
        )
        return evidence
    poses = np.array([v[2].a_from_b for v in verified])
    weights = np.array([float(v[2].inliers) for v in verified])
    group = consistent_candidates(
        poses,
        weights,
        rotation_rad=np.deg2rad(options.consistency_rotation_deg),
        translation_m=options.consistency_translation_m,
    )
    evidence.consistent = [(v[0], v[1]) for v, keep in zip(verified, group, strict=True) if keep]
    if int(np.count_nonzero(group)) < options.min_consistent:
        evidence.reason = (
            f"{len(verified)} verified candidate(s) but only {int(np.count_nonzero(group))} "
            f"agree on T_Sa_Sb (at least {options.min_consistent} needed)"
        )
        return evidence
    chosen = poses[group]
    kept = [v for v, keep in zip(verified, group, strict=True) if keep]
    times_a = seconds_from_ns([v[1] - a.anchor_ns for v in kept])
    times_b = seconds_from_ns([v[0] - b.anchor_ns for v in kept])
    start = weighted_pose_mean(chosen, weights[group])
    floor = np.array(
        [np.deg2rad(options.noise_floor_rotation_deg) ** 2] * 3
        + [options.noise_floor_translation_m**2] * 3
    )
    clusters = candidate_clusters(times_a, times_b, gap_s=options.place_gap_s)
    if options.refine_places:
        # The candidates of one place share keyframes, and so their SLAM errors: one
        # adjustment of them all is the place's measurement.
        places, members = [], []
        for label in range(int(clusters.max()) + 1):
            inside = np.flatnonzero(clusters == label)
            refined = refine_place(
                [prepared[i] for i in np.flatnonzero(group)[inside]],
                options,
                focal_px=focal,
                tilt_sigma_rad=IMAGE_TILT_SIGMA_RAD,
                start=weighted_pose_mean(chosen[inside], weights[group][inside]),
            )
            if refined is not None:
                places.append(refined)
                members.append(inside)
        if not places:
            evidence.reason = (
                f"{len(chosen)} verified candidates agree on T_Sa_Sb but no place's "
                "adjustment converged"
            )
            return evidence
        place_poses = np.array([p[0] for p in places])
        place_times_a = np.array([times_a[m].mean() for m in members])
        place_times_b = np.array([times_b[m].mean() for m in members])
        pair = pair_place_mean(
            place_poses,
            place_times_a,
            place_times_b,
            np.array([np.mean([pose_a[kept[i][1]][:3, 3] for i in m], axis=0) for m in members]),
            np.array(
                [
                    np.mean([(p[0] @ pose_b[kept[i][0]])[:3, 3] for i in m], axis=0)
                    for m, p in zip(members, places, strict=True)
                ]
            ),
            rate_a=drift_rates[a.name],
            rate_b=drift_rates[b.name],
            clusters=np.arange(len(places)),
            floor=floor,
            start=start,
            max_whitened_sq=options.max_candidate_chi2,
            covariances=np.array([p[1] for p in places]),
        )
        used = np.zeros(len(kept), dtype=bool)
        for m, keep in zip(members, pair.inliers, strict=True):
            used[m] = keep
        place_times_a = place_times_a[pair.inliers]
        place_times_b = place_times_b[pair.inliers]
    else:
        pair = pair_place_mean(
            chosen,
            times_a,
            times_b,
            np.array([pose_a[v[1]][:3, 3] for v in kept]),
            np.array([(v[2].a_from_b @ pose_b[v[0]])[:3, 3] for v in kept]),
            rate_a=drift_rates[a.name],
            rate_b=drift_rates[b.name],
            clusters=clusters,
            floor=floor,
            start=start,
            fixed_axes=2,
            keyframe_noise_a=keyframe_noise[a.name],
            keyframe_noise_b=keyframe_noise[b.name],
            max_whitened_sq=options.max_candidate_chi2,
        )
        used = pair.inliers
        place_times_a, place_times_b = times_a[used], times_b[used]
    rejected = int(np.count_nonzero(~used))
    group_stamps = evidence.consistent
    evidence.rejected = [c for c, keep in zip(group_stamps, used, strict=True) if not keep]
    evidence.consistent = [c for c, keep in zip(group_stamps, used, strict=True) if keep]
    if len(evidence.consistent) < options.min_consistent:
        evidence.reason = (
            f"{len(chosen)} verified candidates agree on T_Sa_Sb but {rejected} of them lie "
            f"beyond their modelled errors (at least {options.min_consistent} needed)"
        )
        return evidence
    if options.refine_places:
        pose, covariance = with_tilt_prior(pair.a_from_b, pair.covariance, tilt_variance_rad2)
    else:
        pose, covariance = pair.a_from_b, pair.covariance.copy()
        # Roll and pitch come from gravity, not from the images (`refine_yaw_translation`).
        covariance[:2, :] = 0.0
        covariance[:, :2] = 0.0
        covariance[0, 0] = covariance[1, 1] = tilt_variance_rad2
    evidence.gains_a = pair.gains_a[pair.inliers]
    evidence.gains_b = pair.gains_b[pair.inliers]
    evidence.times_a_s = place_times_a
    evidence.times_b_s = place_times_b
    evidence.mergeable = True
    evidence.reason = f"{len(chosen)} of {len(verified)} verified candidates agree" + (
        f", {rejected} of them dropped beyond their modelled errors" if rejected else ""
    )
    evidence.a_from_b = pose
    evidence.covariance = covariance
    evidence.poses = chosen[used]
    log.info(
        "%s-%s: %d candidates, %d verified, %d consistent",
        a.name,
        b.name,
        len(evidence.candidates),
        len(verified),
        len(evidence.consistent),
    )
    return evidence
