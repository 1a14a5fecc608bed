"""Camera-rate frontend: grid-spread corners tracked by pyramidal KLT, outliers removed.

Pure image processing (OpenCV), no file I/O. Each image is converted to
grey, shrunk to `width_px` (default 960, SVIn2's GoPro setting), optionally
equalised with CLAHE (turbid water flattens contrast), then:

1. features of the previous frame are tracked with pyramidal Lucas-Kanade,
   seeded with the IMU-predicted rotation when given (fast turns otherwise
   exceed the search window), and kept only when tracking back lands within
   `max_forward_backward_px` of the start;
2. survivors are checked against one essential matrix (RANSAC) on
   undistorted normalised coordinates, which rejects tracks that slid along
   edges or locked onto moving particles;
3. through a feature drought (a dark or blurred frame, the camera swept past the
   wreck: fewer than `drought_min_tracks` survive), the features of the last
   well-tracked frame (the anchor, up to `drought_max_s` old) are tracked
   into the new image, seeded by the gyro rotation accumulated since then (no
   bridge without the gyro); those
   that pass both checks come back with their old ids, so the backend's landmarks
   carry on instead of a new map starting from scratch;
4. new corners (Shi-Tomasi) fill empty cells of a grid so features stay spread
   over the image, up to `max_features`. Each cell's threshold is relative to its
   own strongest corner (a flat cell fills from weaker corners); when the frame
   still has few features, the cells short of their share are searched again at
   `quality_level * weak_quality_factor`.

Features carry stable integer track ids; the output is a `FrameTracks` with
both distorted pixels (in the frontend image) and undistorted normalised
coordinates.
"""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from postproc.slam.options import FrontendOptions as FrontendOptions
from postproc.slam.types import FloatArray, FrameTracks, IntArray
from shared.calibration.cameras import CameraModel
from shared.clock import seconds_from_ns

Image = npt.NDArray[np.uint8]


class _UndistortTable:
    """Undistorted normalised coordinates of frontend pixels, by bilinear table lookup.

    The camera model's undistortion is an iterative Newton solve in Python (a tenth
    of the frontend's time when called per frame). It is smooth, so it is tabulated
    once on a `step_px` grid and interpolated: the interpolation error is
    (step^2 / 8) |second derivative|: about 1e-3 px at the corners for GoPro-like
    distortion at 2 px, a thousandth of the feature noise. Pixels outside the
    table, or next to a cell where the model has no inverse (NaN), fall back to
    the exact solve.
    """

    def __init__(self, camera: CameraModel, step_px: float = 2.0) -> None:
        self.camera = camera
        self.step_px = step_px
        xs = np.arange(0.0, camera.width + step_px, step_px)
        ys = np.arange(0.0, camera.height + step_px, step_px)
        grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        self._table = camera.unproject(grid)[:, :2].reshape(len(ys), len(xs), 2)
        self._shape = (len(ys), len(xs))

    def normalised(self, pixels: FloatArray) -> FloatArray:
        """(N, 2) pixels -> (N, 2) undistorted normalised coordinates (NaN: no inverse)."""
        if not len(pixels):
            return np.zeros((0, 2))
        g = np.asarray(pixels, dtype=np.float64) / self.step_px
        rows, cols = self._shape
        inside = (g[:, 0] >= 0) & (g[:, 1] >= 0) & (g[:, 0] <= cols - 1) & (g[:, 1] <= rows - 1)
        i0 = np.clip(np.floor(g[:, 0]).astype(np.int64), 0, cols - 2)
        j0 = np.clip(np.floor(g[:, 1]).astype(np.int64), 0, rows - 2)
        fx = (g[:, 0] - i0)[:, None]
        fy = (g[:, 1] - j0)[:, None]
        t = self._table
        xy = (1 - fy) * ((1 - fx) * t[j0, i0] + fx * t[j0, i0 + 1]) + fy * (
            (1 - fx) * t[j0 + 1, i0] + fx * t[j0 + 1, i0 + 1]
        )
        exact = ~inside | ~np.all(np.isfinite(xy), axis=1)
        if exact.any():
            xy[exact] = self.camera.unproject(np.asarray(pixels, dtype=np.float64)[exact])[:, :2]
        result: FloatArray = xy
        return result


def scale_for_width(camera: CameraModel, width_px: int) -> float:
    """Resize factor from the recorded image to the frontend width.

    Images are only ever shrunk: 1.0 for width 0 or a width at or above the recorded one.
    """
    if width_px <= 0 or width_px >= camera.width:
        return 1.0
    return width_px / camera.width


class KltFrontend:
    """Stateful tracker: call `track` once per image in time order.

    camera: the model of the recorded (full-resolution) image; the frontend
    works with `camera.scaled(...)` at `width_px`.
    """

    def __init__(self, options: FrontendOptions, camera: CameraModel) -> None:
        self.options = options
        self.scale = scale_for_width(camera, options.width_px)
        self.camera = camera.scaled(self.scale) if self.scale != 1.0 else camera
        self.image_size = (self.camera.width, self.camera.height)
        self._clahe = (
            cv2.createCLAHE(
                clipLimit=options.clahe_clip_limit,
                tileGridSize=(options.clahe_tiles, options.clahe_tiles),
            )
            if options.clahe
            else None
        )
        self._previous: Image | None = None
        self._points = np.zeros((0, 2), dtype=np.float32)
        # Undistorted normalised coordinates of `_points` (NaN: no inverse), computed once
        # per point position: the KLT seed, the RANSAC and the output all reuse them.
        self._xy = np.zeros((0, 2))
        self._ids = np.zeros(0, dtype=np.int64)
        self._next_id = 0
        self.lost_tracks = 0
        self.rejected_tracks = 0
        self.recovered_tracks = 0  # tracks brought back from the anchor after a drought
        # The last well-tracked frame: image, stamp, points, their normalised coordinates
        # and ids; and R_Cnow_Canchor.
        self._anchor: tuple[Image, int, npt.NDArray[np.float32], FloatArray, IntArray] | None = None
        self._now_from_anchor: FloatArray | None = np.eye(3)
        self._lut = _UndistortTable(self.camera)

    @property
    def focal_px(self) -> float:
        """Focal length of the frontend image (pixels), mean of fx and fy."""
        K = self.camera.intrinsic_matrix
        return float(0.5 * (K[0, 0] + K[1, 1]))

    @property
    def last_image(self) -> Image | None:
        """The prepared (grey, resized, equalised) image of the last `track` call."""
        return self._previous

    def prepare(self, image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]) -> Image:
        """Grey, resized and equalised image the tracker works on (from 8-bit or 16-bit
        grey, BGR or BGRA)."""
        if image.ndim == 3:
            code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            image = cast(npt.NDArray[np.uint8] | npt.NDArray[np.uint16], cv2.cvtColor(image, code))
        # 16-bit PNGs (some dataset tools write them): keep the high byte.
        grey: Image = (
            (image >> 8).astype(np.uint8)
            if image.dtype == np.uint16
            else image.astype(np.uint8, copy=False)
        )
        if grey.shape[1] != self.camera.width or grey.shape[0] != self.camera.height:
            grey = cast(
                Image,
                cv2.resize(
                    grey, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA
                ),
            )
        if self._clahe is not None:
            grey = cast(Image, self._clahe.apply(grey))
        return grey

    def track(
        self,
        stamp_ns: int,
        image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
        *,
        cam_rotation_now_from_prev: FloatArray | None = None,
        prepared: bool = False,
    ) -> FrameTracks:
        """Track into `image` (recorded size, grey or BGR); returns the surviving features.

        `cam_rotation_now_from_prev` (3, 3), the rotation `R_Cnow_Cprev` predicted by
        the gyro, seeds the optical flow. `prepared`: `image` is already `prepare`'s
        output (made in another thread, say).
        """
        grey = cast(Image, image) if prepared else self.prepare(image)
        # (Pre-built pyramids would save the KLT's rebuilds, but OpenCV's Python binding
        # takes only images there.)
        if self._previous is not None and len(self._points):
            self._points, self._xy, self._ids = self._track_points(
                self._previous,
                grey,
                self._points,
                self._xy,
                self._ids,
                cam_rotation_now_from_prev,
            )
        self._bridge_drought(int(stamp_ns), grey, cam_rotation_now_from_prev)
        self._replenish(grey)
        self._previous = grey
        pixels = self._points.astype(np.float64)
        xy = self._xy
        ok = np.all(np.isfinite(xy), axis=1)
        return FrameTracks(
            stamp_ns=int(stamp_ns),
            track_ids=self._ids[ok].copy(),
            xy_normalised=xy[ok],
            pixels=pixels[ok],
            image_size=self.image_size,
        )

    # ------------------------------------------------------------------------- internals

    def _bridge_drought(self, stamp_ns: int, grey: Image, rotation: FloatArray | None) -> None:
        """Bring back the anchor's tracks after a drought; keep the anchor current."""
        o = self.options
        anchor = self._anchor
        if self._now_from_anchor is not None:
            self._now_from_anchor = (
                None if rotation is None else np.asarray(rotation) @ self._now_from_anchor
            )
        # Only with the gyro: without a rotation guess a search from a frame seconds old
        # locks onto wrong corners often enough to corrupt landmarks (visual-only path).
        if (
            anchor is not None
            and self._now_from_anchor is not None
            and len(self._points) < o.drought_min_tracks
            and seconds_from_ns(stamp_ns - anchor[1]) <= o.drought_max_s
            and anchor[0] is not self._previous
        ):
            image, _, points, xy, ids = anchor
            missing = ~np.isin(ids, self._ids)
            if missing.any():
                back, back_xy, back_ids = self._track_points(
                    image,
                    grey,
                    points[missing],
                    xy[missing],
                    ids[missing],
                    self._now_from_anchor,
                )
                if len(back):
                    self.recovered_tracks += len(back)
                    self._points = np.vstack([self._points, back]).astype(np.float32)
                    self._xy = np.vstack([self._xy, back_xy])
                    self._ids = np.concatenate([self._ids, back_ids])
        if len(self._points) >= o.anchor_min_tracks:
            self._anchor = (
                grey,
                stamp_ns,
                self._points.copy(),
                self._xy.copy(),
                self._ids.copy(),
            )
            self._now_from_anchor = np.eye(3)

    def _predict(
        self, points: npt.NDArray[np.float32], xy: FloatArray, rotation: FloatArray | None
    ) -> npt.NDArray[np.float32]:
        """Where the gyro rotation moves `points` (normalised coordinates `xy`)."""
        if rotation is None:
            return points.copy()
        rays = np.column_stack([xy, np.ones(len(xy))])
        predicted = self.camera.project(rays @ np.asarray(rotation).T)
        bad = ~np.all(np.isfinite(predicted), axis=1)
        predicted[bad] = points[bad]
        return predicted.astype(np.float32)

    def _track_points(
        self,
        previous: Image,
        current: Image,
        points: npt.NDArray[np.float32],
        xy: FloatArray,
        ids: IntArray,
        rotation: FloatArray | None,
    ) -> tuple[npt.NDArray[np.float32], FloatArray, IntArray]:
        """KLT of `points` (normalised coordinates `xy`) from `previous` into `current`,
        forward, back to check, then RANSAC; returns the surviving points in `current`,
        their normalised coordinates and their ids."""
        o = self.options
        # A gyro-seeded flow starts close to its answer: a smaller window will do.
        side = o.klt_window_unseeded_px if rotation is None else o.klt_window_px
        window = (side, side)
        criteria = (
            cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
            o.klt_iterations,
            o.klt_epsilon_px,
        )
        start = points.reshape(-1, 1, 2)
        guess = self._predict(points, xy, rotation).reshape(-1, 1, 2)
        forward, status, _ = cv2.calcOpticalFlowPyrLK(
            previous,
            current,
            start,
            guess.copy(),
            winSize=window,
            maxLevel=o.klt_levels,
            criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        # The check starts at the start point: a consistent track needs only the finest
        # levels to come back (see FrontendOptions.klt_check_levels).
        backward, status_back, _ = cv2.calcOpticalFlowPyrLK(
            current,
            previous,
            forward,
            start.copy(),
            winSize=window,
            maxLevel=min(o.klt_check_levels, o.klt_levels),
            criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        forward = forward.reshape(-1, 2)
        fb_error = np.linalg.norm(backward.reshape(-1, 2) - points, axis=1)
        h, w = current.shape[:2]
        b = o.border_px
        keep = (
            (status.ravel() == 1)
            & (status_back.ravel() == 1)
            & (fb_error <= o.max_forward_backward_px)
            & (forward[:, 0] >= b)
            & (forward[:, 0] <= w - 1 - b)
            & (forward[:, 1] >= b)
            & (forward[:, 1] <= h - 1 - b)
        )
        self.lost_tracks += int((~keep).sum())
        before = points[keep]
        after = forward[keep].astype(np.float32)
        after_xy = self._lut.normalised(after.astype(np.float64))
        kept_ids = ids[keep]
        inliers = self._epipolar_inliers(before, after, xy[keep], after_xy)
        self.rejected_tracks += int((~inliers).sum())
        return after[inliers], after_xy[inliers], kept_ids[inliers]

    def _epipolar_inliers(
        self,
        previous: npt.NDArray[np.float32],
        current: npt.NDArray[np.float32],
        a: FloatArray,
        b: FloatArray,
    ) -> npt.NDArray[np.bool_]:
        """Tracks (pixels `previous` -> `current`, normalised `a` -> `b`) that agree with
        one essential matrix."""
        n = len(previous)
        if n < 8:
            return np.ones(n, dtype=bool)
        finite: npt.NDArray[np.bool_] = np.all(np.isfinite(a), axis=1) & np.all(
            np.isfinite(b), axis=1
        )
        if finite.sum() < 8:
            return finite
        # Hardly any motion: the essential matrix is undefined; keep the KLT survivors.
        if np.median(np.linalg.norm(current - previous, axis=1)) < 0.5:
            return finite
        _, mask = cv2.findEssentialMat(
            a[finite],
            b[finite],
            np.eye(3),
            method=cv2.RANSAC,
            prob=0.999,
            threshold=self.options.ransac_threshold_px / self.focal_px,
        )
        inliers = np.zeros(n, dtype=bool)
        if mask is None:
            inliers[finite] = True
        else:
            inliers[np.flatnonzero(finite)] = mask.ravel().astype(bool)
        return inliers

    def _replenish(self, grey: Image) -> None:
        o = self.options
        if len(self._points) > o.max_features - max(o.replenish_missing, 1):
            return
        h, w = grey.shape
        mask = np.full((h, w), 255, dtype=np.uint8)
        b = o.border_px
        mask[:b, :] = 0
        mask[h - b :, :] = 0
        mask[:, :b] = 0
        mask[:, w - b :] = 0
        self._block(mask, self._points)
        quota = max(o.max_features // (o.grid_cols * o.grid_rows), 1)
        xs = np.linspace(0, w, o.grid_cols + 1).astype(int)
        ys = np.linspace(0, h, o.grid_rows + 1).astype(int)
        cell_of = np.zeros(len(self._points), dtype=np.int64)
        if len(self._points):
            cx = np.clip(
                np.searchsorted(xs, self._points[:, 0], side="right") - 1, 0, o.grid_cols - 1
            )
            cy = np.clip(
                np.searchsorted(ys, self._points[:, 1], side="right") - 1, 0, o.grid_rows - 1
            )
            cell_of = cy * o.grid_cols + cx
        counts = np.bincount(cell_of, minlength=o.grid_cols * o.grid_rows)
        order = np.argsort(counts, kind="stable")
        new_points = self._detect(grey, mask, xs, ys, order, counts, quota, o.quality_level)
        total = len(self._points) + sum(len(p) for p in new_points)
        if total < o.weak_fill_below and o.weak_quality_factor < 1.0:
            # A flat image: each cell's strongest corner set a bar its texture stays
            # under. Search the cells still short at a lower bar rather than leave them
            # empty (only then: weak corners in a rich image are worse than none).
            found = np.vstack(new_points) if new_points else np.zeros((0, 2), np.float32)
            self._block(mask, found)
            r = np.minimum(np.searchsorted(ys, found[:, 1], side="right") - 1, o.grid_rows - 1)
            c = np.minimum(np.searchsorted(xs, found[:, 0], side="right") - 1, o.grid_cols - 1)
            np.add.at(counts, r * o.grid_cols + c, 1)
            new_points += self._detect(
                grey, mask, xs, ys, order, counts, quota, o.quality_level * o.weak_quality_factor
            )
        if not new_points:
            return
        # Emptier cells come first in the list; cut at the overall budget.
        added = np.vstack(new_points).astype(np.float32)[: o.max_features - len(self._points)]
        self._points = np.vstack([self._points, added]).astype(np.float32)
        self._xy = np.vstack([self._xy, self._lut.normalised(added.astype(np.float64))])
        ids = np.arange(self._next_id, self._next_id + len(added), dtype=np.int64)
        self._next_id += len(added)
        self._ids = np.concatenate([self._ids, ids])

    def _block(self, mask: Image, points: npt.NDArray[np.float32]) -> None:
        """Zero `mask` within `min_distance_px` of every point (filled circles)."""
        # Rounded at once (half to even, as Python's round), drawn one by one: a
        # fancy-indexed stamp of every disk is slower than OpenCV's circle.
        centres = np.round(points.astype(np.float64)).astype(np.int64).tolist()
        radius = self.options.min_distance_px
        for x, y in centres:
            cv2.circle(mask, (x, y), radius, 0, -1)

    def _detect(
        self,
        grey: Image,
        mask: Image,
        xs: IntArray,
        ys: IntArray,
        order: IntArray,
        counts: IntArray,
        quota: int,
        quality_level: float,
    ) -> list[npt.NDArray[np.float32]]:
        """Shi-Tomasi corners in every grid cell short of `quota`, emptier cells first."""
        o = self.options
        found = []
        for cell in order:
            r, c = divmod(int(cell), o.grid_cols)
            want = quota - int(counts[cell])
            if want <= 0:
                continue
            x0, x1, y0, y1 = xs[c], xs[c + 1], ys[r], ys[r + 1]
            corners = cv2.goodFeaturesToTrack(
                grey[y0:y1, x0:x1],
                maxCorners=want,
                qualityLevel=quality_level,
                minDistance=o.min_distance_px,
                mask=mask[y0:y1, x0:x1],
            )
            if corners is not None:
                # goodFeaturesToTrack returns float32 corners.
                found.append(
                    cast(npt.NDArray[np.float32], corners.reshape(-1, 2))
                    + np.array([x0, y0], np.float32)
                )
        return found


def track_ids_in_both(a: FrameTracks, b: FrameTracks) -> tuple[IntArray, IntArray]:
    """Indices into a and b of the tracks the two frames share (same id)."""
    _, ia, ib = np.intersect1d(a.track_ids, b.track_ids, return_indices=True)
    return ia.astype(np.int64), ib.astype(np.int64)
