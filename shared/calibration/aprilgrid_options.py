"""The options of AprilGrid detection (`shared.calibration.aprilgrid_detection`).

Light on purpose (no NumPy or OpenCV): the calibrate stage's options, and so its
command line's flags, are built from it without importing the detector.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(kw_only=True)
class DetectionOptions:
    """How tags are found and refined.

    subpix: refine corners with cv2.cornerSubPix (else aruco's corners as found).
    subpix_window_cells: half-size of the refinement window in tag cells
        (a Kalibr tag is 10 cells across; the X-junction is clean for 2 cells).
    subpix_max_half_window_px / subpix_min_half_window_px: bounds of the half-size (pixels).
    subpix_max_shift_cells: a refined corner that moved further than this
        (cells) from aruco's estimate is kept at aruco's estimate. (With a
        2-cell border, aruco's contour corners sit about 0.7 cell inside the
        true corner, so the refinement must be allowed to move that far.)
    min_tag_side_px: tags smaller than this (mean side, pixels) are dropped:
        their corners are too uncertain for pose estimation.
    adaptive_threshold_window_max_px: largest adaptive-threshold window aruco
        tries (pixels); larger finds big tags in high-resolution images.
    """

    subpix: bool = True
    subpix_window_cells: float = 1.5
    subpix_max_half_window_px: int = 10
    subpix_min_half_window_px: int = 2
    subpix_max_shift_cells: float = 2.0
    min_tag_side_px: float = 12.0
    adaptive_threshold_window_max_px: int = 53
