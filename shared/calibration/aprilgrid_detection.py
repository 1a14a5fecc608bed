"""AprilGrid detection in images, in Kalibr's convention (beside the target of
`shared.calibration.aprilgrid`; calibration and merging both detect through it).

Kalibr prints 36h11 tags with a two-cell black border and counts corners
counter-clockwise from the bottom-left on the page (see
`shared.calibration.aprilgrid`). We detect with OpenCV's aruco module
(`DICT_APRILTAG_36h11`, `markerBorderBits = 2`), reorder each tag's corners
to Kalibr's order, and refine them with `cv2.cornerSubPix`: every Kalibr tag
corner is an X-junction (the tag's black square touches a small black corner
square diagonally), which is what `cornerSubPix` locates best. The refinement
window scales with the tag's size in the image and stays inside the two-cell
border, so it never reaches the next feature.

Tags are then assigned to targets by id (`tagIdOffset` tells two grids on one
wreck apart); ids that belong to no target are rejected (a tag of another
grid, or a decoding error).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.calibration.aprilgrid import (
    KALIBR_BORDER_BITS,
    OPENCV_CORNER_ORDER,
    TAG_CELLS,
    AprilGridTarget,
)

# Defined in the light options module (no NumPy), re-exported here.
from shared.calibration.aprilgrid_options import DetectionOptions as DetectionOptions

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class TagDetection:
    """One decoded tag: its 36h11 id and its 4 corners (4, 2) in pixels, Kalibr order."""

    tag_id: int
    corners_px: FloatArray


@dataclass(frozen=True)
class GridObservation:
    """The tags of one target seen in one image.

    target_index: index into the targets given to `group_by_target`.
    tag_ids: (K,) ids; image_points_px: (K, 4, 2) pixels; object_points_m: (K, 4, 3)
    in the target frame, both in Kalibr corner order.
    """

    target_index: int
    tag_ids: IntArray
    image_points_px: FloatArray
    object_points_m: FloatArray

    @property
    def corner_count(self) -> int:
        """Number of corners (4 per tag)."""
        return int(self.tag_ids.shape[0] * 4)


def _detector(options: DetectionOptions) -> object:
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    parameters = cv2.aruco.DetectorParameters()
    parameters.markerBorderBits = KALIBR_BORDER_BITS
    # We refine ourselves at the X-junctions; aruco's refiners look at the tag's edges.
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    parameters.adaptiveThreshWinSizeMax = int(options.adaptive_threshold_window_max_px)
    return cv2.aruco.ArucoDetector(dictionary, parameters)


def to_gray(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """A grayscale copy of an 8-bit image (H, W), (H, W, 3) BGR or (H, W, 4) BGRA."""
    import cv2

    array = np.asarray(image)
    if array.dtype != np.uint8:
        raise ValueError(f"expected an 8-bit image, got dtype {array.dtype}")
    if array.ndim == 2:
        return array
    if array.ndim == 3 and array.shape[2] == 3:
        return np.asarray(cv2.cvtColor(array, cv2.COLOR_BGR2GRAY))
    if array.ndim == 3 and array.shape[2] == 4:
        return np.asarray(cv2.cvtColor(array, cv2.COLOR_BGRA2GRAY))
    raise ValueError(f"expected an (H, W), (H, W, 3) or (H, W, 4) image, got {array.shape}")


def detect_tags(
    image: npt.NDArray[np.uint8], options: DetectionOptions | None = None
) -> list[TagDetection]:
    """All 36h11 tags (Kalibr 2-cell border) in an image, corners in Kalibr order (pixels).

    Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).
    When an id is decoded twice (a reflection, or a second grid with the same
    offset) both detections are dropped: the pose could not tell them apart.
    """
    import cv2

    options = options or DetectionOptions()
    gray = to_gray(image)
    detector = _detector(options)
    corners, ids, _rejected = detector.detectMarkers(gray)  # type: ignore[attr-defined]
    if ids is None or len(ids) == 0:
        return []
    ids_flat = np.asarray(ids, dtype=np.int64).reshape(-1)
    unique, counts = np.unique(ids_flat, return_counts=True)
    duplicated = set(unique[counts > 1].tolist())
    detections = []
    for tag_id, tag_corners in zip(ids_flat, corners, strict=True):
        if int(tag_id) in duplicated:
            continue
        opencv_corners = np.asarray(tag_corners, dtype=np.float64).reshape(4, 2)
        kalibr = opencv_corners[list(OPENCV_CORNER_ORDER)]
        side_px = float(np.mean(np.linalg.norm(kalibr - np.roll(kalibr, 1, axis=0), axis=1)))
        if side_px < options.min_tag_side_px:
            continue
        if options.subpix:
            cell_px = side_px / TAG_CELLS
            half = int(
                np.clip(
                    round(options.subpix_window_cells * cell_px),
                    options.subpix_min_half_window_px,
                    options.subpix_max_half_window_px,
                )
            )
            refined = cv2.cornerSubPix(
                gray,
                kalibr.astype(np.float32).reshape(-1, 1, 2).copy(),
                (half, half),
                (-1, -1),
                (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3),
            )
            refined = np.asarray(refined, dtype=np.float64).reshape(4, 2)
            shift = np.linalg.norm(refined - kalibr, axis=1)
            ok = shift <= options.subpix_max_shift_cells * cell_px
            kalibr = np.where(ok[:, None], refined, kalibr)
        detections.append(TagDetection(tag_id=int(tag_id), corners_px=kalibr))
    detections.sort(key=lambda d: d.tag_id)
    return detections


def group_by_target(
    detections: Sequence[TagDetection],
    targets: Sequence[AprilGridTarget],
    *,
    min_tags: int = 1,
) -> tuple[list[GridObservation], list[int]]:
    """Assign tags to targets by id.

    Returns (one observation per target with at least `min_tags` tags, ordered by
    target index; the ids that belong to no target). Raises ValueError when two
    targets claim the same id (their `tagIdOffset`s overlap).
    """
    owner: dict[int, int] = {}
    corner_tables = []
    for index, target in enumerate(targets):
        table = target.corner_points()
        corner_tables.append(table)
        for tag_id in table:
            if tag_id in owner:
                raise ValueError(
                    f"targets {owner[tag_id]} and {index} both contain tag id {tag_id} "
                    "(give each grid its own tagIdOffset)"
                )
            owner[tag_id] = index
    per_target: dict[int, list[TagDetection]] = {}
    foreign: list[int] = []
    for detection in detections:
        owner_index = owner.get(detection.tag_id)
        if owner_index is None:
            foreign.append(detection.tag_id)
            continue
        per_target.setdefault(owner_index, []).append(detection)
    observations = []
    for index in sorted(per_target):
        tags = per_target[index]
        if len(tags) < min_tags:
            continue
        observations.append(
            GridObservation(
                target_index=index,
                tag_ids=np.array([d.tag_id for d in tags], dtype=np.int64),
                image_points_px=np.array([d.corners_px for d in tags]),
                object_points_m=np.array([corner_tables[index][d.tag_id] for d in tags]),
            )
        )
    return observations, sorted(foreign)


def line_fit_residuals_px(
    detections: Sequence[TagDetection], target: AprilGridTarget
) -> FloatArray:
    """Distances (pixels) of corners from lines fitted through grid rows and columns.

    Corners of one target row (the bottom or top edge of a row of tags) lie on
    one straight line of the target; with little lens distortion they lie on a
    straight image line. The residuals measure corner quality on real images
    with no calibration. Lines with fewer than 3 corners are skipped.
    """
    by_id = {d.tag_id: d.corners_px for d in detections}
    lines: list[list[FloatArray]] = []
    for row in range(target.tag_rows):
        for corner_pair in ((0, 1), (3, 2)):  # bottom edge, top edge (Kalibr order)
            points: list[FloatArray] = []
            for col in range(target.tag_cols):
                tag_id = target.tag_id_offset + row * target.tag_cols + col
                if tag_id in by_id:
                    points.extend(by_id[tag_id][list(corner_pair)])
            lines.append(points)
    for col in range(target.tag_cols):
        for corner_pair in ((0, 3), (1, 2)):  # left edge, right edge
            points = []
            for row in range(target.tag_rows):
                tag_id = target.tag_id_offset + row * target.tag_cols + col
                if tag_id in by_id:
                    points.extend(by_id[tag_id][list(corner_pair)])
            lines.append(points)
    residuals = []
    for points in lines:
        if len(points) < 3:
            continue
        p = np.array(points)
        centre = p.mean(axis=0)
        # Total least squares: the normal is the smallest singular direction.
        _, _, vt = np.linalg.svd(p - centre)
        residuals.extend(np.abs((p - centre) @ vt[1]))
    return np.array(residuals, dtype=np.float64)


def homography_residuals_px(
    detections: Sequence[TagDetection], target: AprilGridTarget
) -> FloatArray:
    """Distances (pixels) between corners and the best plane-to-image homography's prediction.

    Exact for a pinhole camera; lens distortion adds a smooth part. Needs at
    least 2 tags (8 corners) of `target`; otherwise an empty array.
    """
    import cv2

    table = target.corner_points()
    image_points = []
    object_points = []
    for detection in detections:
        if detection.tag_id in table:
            image_points.append(detection.corners_px)
            object_points.append(table[detection.tag_id][:, :2])
    if len(image_points) < 2:
        return np.zeros(0)
    src = np.concatenate(object_points)
    dst = np.concatenate(image_points)
    H, _ = cv2.findHomography(src, dst, 0)
    projected = cv2.perspectiveTransform(src.reshape(-1, 1, 2), H).reshape(-1, 2)
    return np.asarray(np.linalg.norm(projected - dst, axis=1), dtype=np.float64)
