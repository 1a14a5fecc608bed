"""Which views of the AprilGrid to calibrate with: image coverage, viewing angles, sharpness.

Pure math, no I/O (OpenCV only for the Laplacian and a homography). A video of a
calibration sweep holds thousands of frames showing the grid, most of them near
duplicates; the intrinsics need views that together put corners in every part of the
image (distortion lives at the edges) and that see the board from many directions (the
focal length and principal point are observable only through perspective).

Selection is greedy with diminishing returns: each candidate's gain is
    sum over the image cells it covers of 1 / (1 + views already covering the cell)
  + angle_weight * 1 / (1 + views already in its viewing-angle bin)
  + sharpness_weight * its sharpness relative to the sharpest candidate,
and the best candidate is taken until `max_frames` views or no candidate adds anything.
Blurred frames (variance of the Laplacian below `min_relative_sharpness` times the
median of the candidates) and frames with few corners are never taken.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from postproc.calibrate.options import FrameSelectionOptions as FrameSelectionOptions

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class GridView:
    """The grid corners found in one frame.

    index: position of the frame in its source; stamp_ns: its time stamp (ns, the
    source's clock); image_points_px (N,2) pixels; object_points_m (N,3) target frame;
    sharpness: variance of the Laplacian of the frame (grey levels squared).
    """

    index: int
    stamp_ns: int
    image_points_px: FloatArray
    object_points_m: FloatArray
    sharpness: float

    @property
    def corner_count(self) -> int:
        return len(self.image_points_px)


def sharpness(gray: npt.NDArray[np.uint8]) -> float:
    """Variance of the Laplacian of a grey image: falls sharply with blur."""
    import cv2

    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def covered_cells(
    image_points_px: FloatArray, image_size: tuple[int, int], cells: tuple[int, int]
) -> npt.NDArray[np.int64]:
    """Flat indices of the `cells` = (columns, rows) image cells that hold a corner."""
    width, height = image_size
    columns, rows = cells
    u = np.clip((image_points_px[:, 0] + 0.5) / width * columns, 0, columns - 1).astype(np.int64)
    v = np.clip((image_points_px[:, 1] + 0.5) / height * rows, 0, rows - 1).astype(np.int64)
    return np.unique(v * columns + u)


def coverage_fraction(
    views: list[GridView], image_size: tuple[int, int], cells: tuple[int, int]
) -> float:
    """Fraction of the image cells holding at least one corner of any of `views`."""
    if not views:
        return 0.0
    hit = np.unique(
        np.concatenate([covered_cells(v.image_points_px, image_size, cells) for v in views])
    )
    return float(len(hit)) / float(cells[0] * cells[1])


def viewing_angles_deg(view: GridView, image_size: tuple[int, int]) -> tuple[float, float]:
    """Rough tilt of the board about the camera x and y axes (degrees).

    From the board-to-image homography with a guessed camera (focal length the image
    width, principal point at the centre, no distortion): good enough to bin views,
    not a measurement.
    """
    import cv2

    width, height = image_size
    focal = float(width)
    camera = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    homography, _ = cv2.findHomography(view.object_points_m[:, :2], view.image_points_px)
    if homography is None:
        return 0.0, 0.0
    columns = np.linalg.solve(camera, homography)
    r1 = columns[:, 0] / np.linalg.norm(columns[:, 0])
    r2 = columns[:, 1] / np.linalg.norm(columns[:, 1])
    normal = np.cross(r1, r2)
    normal /= np.linalg.norm(normal)
    if normal[2] > 0:
        normal = -normal
    # The normal points back at the camera: its x, y components give the tilt.
    return (
        float(np.degrees(np.arctan2(normal[1], -normal[2]))),
        float(np.degrees(np.arctan2(normal[0], -normal[2]))),
    )


def select_frames(
    views: list[GridView], image_size: tuple[int, int], options: FrameSelectionOptions
) -> list[int]:
    """Indices into `views` of the chosen views, in the order of `views`."""
    if not views:
        return []
    eligible = [i for i, v in enumerate(views) if v.corner_count >= options.min_corners]
    if not eligible:
        return []
    median_sharpness = float(np.median([views[i].sharpness for i in eligible]))
    eligible = [
        i
        for i in eligible
        if views[i].sharpness >= options.min_relative_sharpness * median_sharpness
    ]
    if not eligible:
        return []
    top_sharpness = max(views[i].sharpness for i in eligible) or 1.0
    cells = {
        i: covered_cells(views[i].image_points_px, image_size, options.coverage_cells)
        for i in eligible
    }
    angle_bins = {}
    for i in eligible:
        tilt_x, tilt_y = viewing_angles_deg(views[i], image_size)
        angle_bins[i] = (
            round(tilt_x / options.angle_bin_deg),
            round(tilt_y / options.angle_bin_deg),
        )
    cell_counts = np.zeros(options.coverage_cells[0] * options.coverage_cells[1])
    bin_counts: dict[tuple[int, int], int] = {}
    chosen: list[int] = []
    remaining = set(eligible)
    while remaining and len(chosen) < options.max_frames:
        best, best_gain = -1, 0.0
        for i in sorted(remaining):
            gain = float(np.sum(1.0 / (1.0 + cell_counts[cells[i]])))
            gain += options.angle_weight / (1.0 + bin_counts.get(angle_bins[i], 0))
            gain += options.sharpness_weight * views[i].sharpness / top_sharpness
            if gain > best_gain:
                best, best_gain = i, gain
        if best < 0:
            break
        chosen.append(best)
        remaining.discard(best)
        cell_counts[cells[best]] += 1
        bin_counts[angle_bins[best]] = bin_counts.get(angle_bins[best], 0) + 1
    return sorted(chosen)
