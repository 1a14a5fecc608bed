"""Loop closure: recognise a place seen long ago, verify it, constrain the two keyframes.

Pure computation (OpenCV matching and PnP), no file I/O. Following SVIn2's
recipe, adapted to a frame-to-frame KLT frontend:

1. candidates: older keyframes (at least `min_time_gap_s` earlier) whose camera
   is within `max_distance_m` and `max_yaw_deg` of the current estimate, so
   the search stays local and cheap (drift over one dive is far below 6 m);
2. appearance: binary descriptors (ORB at the tracked feature positions)
   matched with the ratio test;
3. geometry: the matched features of the old keyframe that are landmarks give
   2D-3D correspondences; PnP RANSAC must keep at least `min_inliers` (SVIn2:
   25) to accept the loop;
4. the verified pose of the current keyframe relative to the old one becomes a
   `BetweenFactorPose3` under a Cauchy loss in the same ISAM2 graph, so the
   whole trajectory (and every landmark) moves to close the loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from postproc.slam.options import LoopClosureOptions as LoopClosureOptions
from postproc.slam.types import FloatArray, IntArray
from shared.clock import ns_from_seconds
from shared.geometry import invert_pose, make_pose, so3_exp

Descriptors = npt.NDArray[np.uint8]


@dataclass
class LoopConstraint:
    """A verified loop: `T_Bold_Bnew`, the pose of keyframe `new` in keyframe `old`'s body."""

    old: int
    new: int
    old_from_new: FloatArray
    inliers: int


@dataclass
class _KeyframeFeatures:
    stamp_ns: int
    track_ids: IntArray
    xy_normalised: FloatArray
    descriptors: Descriptors


def heading_rad(session_from_cam: FloatArray) -> float:
    """Horizontal heading of the optical axis in S (rad): a yaw that ignores camera roll."""
    axis = session_from_cam[:3, 2]
    return float(np.arctan2(axis[1], axis[0]))


def match_descriptors(
    query: Descriptors, train: Descriptors, *, ratio: float, max_hamming: int
) -> tuple[IntArray, IntArray]:
    """Indices (query, train) of mutual-best-free ratio-test matches under the Hamming bound."""
    if len(query) < 2 or len(train) < 2:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy()
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(query, train, k=2)
    qi, ti = [], []
    for pair in pairs:
        if len(pair) < 2:
            continue
        best, second = pair
        if best.distance <= max_hamming and best.distance < ratio * second.distance:
            qi.append(best.queryIdx)
            ti.append(best.trainIdx)
    return np.array(qi, dtype=np.int64), np.array(ti, dtype=np.int64)


class LoopDetector:
    """Keeps keyframe descriptors; proposes and verifies loops for the newest keyframe.

    focal_px: frontend focal length (pixels), for the RANSAC threshold.
    imu_from_cam: `T_B_C` (4, 4).
    """

    def __init__(self, options: LoopClosureOptions, *, focal_px: float, imu_from_cam: FloatArray):
        self.options = options
        self.focal_px = focal_px
        self.imu_from_cam = np.asarray(imu_from_cam, dtype=np.float64)
        self._keyframes: dict[int, _KeyframeFeatures] = {}
        self.attempts = 0

    def add_keyframe(
        self,
        index: int,
        stamp_ns: int,
        track_ids: IntArray,
        xy_normalised: FloatArray,
        descriptors: Descriptors,
    ) -> None:
        """Remember keyframe `index`'s features (rows aligned: ids, coordinates, descriptors)."""
        if not (len(track_ids) == len(xy_normalised) == len(descriptors)):
            raise ValueError("track_ids, xy_normalised and descriptors must have the same length")
        self._keyframes[index] = _KeyframeFeatures(
            stamp_ns, np.asarray(track_ids), np.asarray(xy_normalised), np.asarray(descriptors)
        )

    def candidates(self, index: int, session_from_body: list[FloatArray]) -> list[int]:
        """Older keyframes inside the distance, heading and time gates, nearest first."""
        o = self.options
        current = self._keyframes.get(index)
        if current is None:
            return []
        T_new = session_from_body[index] @ self.imu_from_cam
        gap_ns = ns_from_seconds(o.min_time_gap_s)
        scored = []
        for j, features in self._keyframes.items():
            if j >= index or current.stamp_ns - features.stamp_ns < gap_ns:
                continue
            T_old = session_from_body[j] @ self.imu_from_cam
            distance = float(np.linalg.norm(T_old[:3, 3] - T_new[:3, 3]))
            dyaw = abs(np.angle(np.exp(1j * (heading_rad(T_old) - heading_rad(T_new)))))
            if distance <= o.max_distance_m and np.degrees(dyaw) <= o.max_yaw_deg:
                scored.append((distance, j))
        return [j for _, j in sorted(scored)[: o.max_candidates]]

    def verify(
        self,
        old: int,
        new: int,
        *,
        old_session_from_body: FloatArray,
        landmark: Callable[[int], FloatArray | None],
        rng_seed: int = 0,
    ) -> LoopConstraint | None:
        """PnP of keyframe `new` against the landmarks of keyframe `old`; None if it fails.

        `landmark(track_id)` returns the current position in S of a landmark
        (None for tracks that never became one). The relative pose is measured
        against the old keyframe's current estimate, since both it and those
        landmarks belong to the same (old) part of the map.
        """
        o = self.options
        self.attempts += 1
        a = self._keyframes[old]
        b = self._keyframes[new]
        qi, ti = match_descriptors(
            b.descriptors, a.descriptors, ratio=o.ratio_test, max_hamming=o.max_hamming
        )
        points, observed = [], []
        for q, t in zip(qi.tolist(), ti.tolist(), strict=True):
            p = landmark(int(a.track_ids[t]))
            if p is not None:
                points.append(p)
                observed.append(b.xy_normalised[q])
        if len(points) < o.min_inliers:
            return None
        cv2.setRNGSeed(rng_seed)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            np.asarray(points, dtype=np.float64),
            np.asarray(observed, dtype=np.float64),
            np.eye(3),
            None,
            reprojectionError=o.pnp_reprojection_px / self.focal_px,
            iterationsCount=300,
            confidence=0.999,
            # A minimal solver: OpenCV 5's RANSAC with EPnP or the iterative solver keeps
            # only a handful of exact inliers under a threshold in normalised units.
            flags=cv2.SOLVEPNP_AP3P,
        )
        if not ok or inliers is None or len(inliers) < o.min_inliers:
            return None
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(
            np.asarray(points, dtype=np.float64)[inl],
            np.asarray(observed, dtype=np.float64)[inl],
            np.eye(3),
            None,
            rvec,
            tvec,
        )
        cam_from_session = make_pose(so3_exp(rvec.ravel()), tvec.ravel())
        session_from_new_body = invert_pose(cam_from_session) @ invert_pose(self.imu_from_cam)
        old_from_new = invert_pose(old_session_from_body) @ session_from_new_body
        return LoopConstraint(old=old, new=new, old_from_new=old_from_new, inliers=len(inl))


def orb_descriptors(
    image: npt.NDArray[np.uint8], pixels: FloatArray, *, orb: cv2.ORB | None = None
) -> tuple[IntArray, Descriptors]:
    """ORB descriptors at given pixels of a grey image: (indices kept, (K, 32) uint8).

    ORB drops points whose patch leaves the image; the indices say which rows survived.
    """
    orb = orb or cv2.ORB.create(edgeThreshold=15, patchSize=31)
    keypoints = [
        cv2.KeyPoint(float(x), float(y), 31.0, -1, 0, 0, i) for i, (x, y) in enumerate(pixels)
    ]
    kept, descriptors = orb.compute(image, keypoints)
    if descriptors is None or not kept:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 32), dtype=np.uint8)
    # ORB descriptors are uint8.
    return np.array([k.class_id for k in kept], dtype=np.int64), cast(Descriptors, descriptors)
