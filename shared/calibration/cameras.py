"""Camera models as Kalibr names them, numerically identical to OpenCV's.

Pure math, no I/O. Every model maps points in the camera frame (OpenCV
convention: x right, y down, z forward, metres) to pixels and back:

    point (x, y, z)  --divide by z-->  normalised (x/z, y/z)
                     --distort------>  distorted normalised (xd, yd)
                     --K------------>  pixel (fx*xd + cx, fy*yd + cy)

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).

Models (`CAMERA_MODELS`, keyed by Kalibr's `(camera_model, distortion_model)`):

- `PinholeRadtan`: Kalibr "pinhole" + "radtan", the OpenCV plumb-bob model
  with k3 = 0 (`cv2.projectPoints`, `cv2.undistortPoints`).
- `PinholeEquidistant`: Kalibr "pinhole" + "equidistant", the OpenCV fisheye
  model (`cv2.fisheye.projectPoints`, `cv2.fisheye.undistortPoints`).

`undistort`/`unproject` invert the distortion with Newton's method run to
convergence (residual below 1e-12 in normalised coordinates), not OpenCV's
fixed five iterations, so they stay exact in the image corners where a
ray-casting renderer needs them. Inputs with no inverse (z <= 0 for
`project`, a fisheye angle at or beyond 90 degrees, a radtan point where the
distortion folds over) give NaN rows rather than wrong numbers.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

# Newton stops when the distortion residual is this small (normalised units).
_NEWTON_TOL = 1e-13
_NEWTON_MAX_ITER = 60
# A point whose residual stalls below this counts as converged (floating-point floor).
_NEWTON_ACCEPT = 1e-11


@runtime_checkable
class CameraModel(Protocol):
    """What every camera model offers (all arrays float64, one row per point)."""

    @property
    def width(self) -> int:
        """Image width in pixels."""
        ...

    @property
    def height(self) -> int:
        """Image height in pixels."""
        ...

    @property
    def fx(self) -> float:
        """Focal length along x, in pixels."""
        ...

    @property
    def fy(self) -> float:
        """Focal length along y, in pixels."""
        ...

    @property
    def cx(self) -> float:
        """Principal point x, in pixels."""
        ...

    @property
    def cy(self) -> float:
        """Principal point y, in pixels."""
        ...

    def project(self, points_cam: ArrayLike) -> FloatArray:
        """(N,3) points in the camera frame -> (N,2) distorted pixels; NaN where z <= 0."""
        ...

    def unproject(self, pixels: ArrayLike) -> FloatArray:
        """(N,2) pixels -> (N,3) rays (x, y, 1) with the distortion removed."""
        ...

    def distort(self, xy_normalised: ArrayLike) -> FloatArray:
        """(N,2) undistorted normalised coordinates -> (N,2) distorted normalised."""
        ...

    def undistort(self, xy_distorted: ArrayLike) -> FloatArray:
        """(N,2) distorted normalised coordinates -> (N,2) undistorted normalised."""
        ...

    @property
    def intrinsic_matrix(self) -> FloatArray:
        """The 3x3 matrix K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels)."""
        ...

    def scaled(self, factor: float) -> Self:
        """The same camera for an image resized by `factor` (cv2.resize pixel centres)."""
        ...

    @property
    def opencv_distortion(self) -> FloatArray:
        """Distortion coefficients in the order the matching cv2 functions take."""
        ...

    @property
    def kalibr_model(self) -> tuple[str, str]:
        """Kalibr's (camera_model, distortion_model), e.g. ("pinhole", "radtan")."""
        ...


def _as_points(values: ArrayLike, columns: int, what: str) -> FloatArray:
    array = np.asarray(values, dtype=np.float64)
    if array.ndim == 1 and array.shape[0] == columns:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != columns:
        raise ValueError(f"{what}: expected an (N,{columns}) array, got shape {array.shape}")
    return array


class _Pinhole:
    """Shared pinhole projection; subclasses supply distort/undistort and the fields."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def distort(self, xy_normalised: ArrayLike) -> FloatArray:
        raise NotImplementedError

    def undistort(self, xy_distorted: ArrayLike) -> FloatArray:
        raise NotImplementedError

    def project(self, points_cam: ArrayLike) -> FloatArray:
        """(N,3) points in the camera frame (m) -> (N,2) pixels; NaN rows where z <= 0."""
        points = _as_points(points_cam, 3, "points_cam")
        z = points[:, 2]
        in_front = z > 0
        safe_z = np.where(in_front, z, 1.0)
        xy = points[:, :2] / safe_z[:, None]
        xy[~in_front] = np.nan
        distorted = self.distort(xy)
        return np.column_stack(
            (self.fx * distorted[:, 0] + self.cx, self.fy * distorted[:, 1] + self.cy)
        )

    def unproject(self, pixels: ArrayLike) -> FloatArray:
        """(N,2) pixels -> (N,3) rays (x, y, 1): the normalised undistorted point at z = 1."""
        uv = _as_points(pixels, 2, "pixels")
        xy_d = np.column_stack(((uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy))
        xy = self.undistort(xy_d)
        z = np.where(np.isnan(xy).any(axis=1), np.nan, 1.0)
        return np.column_stack((xy, z))

    @property
    def intrinsic_matrix(self) -> FloatArray:
        """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def scaled(self, factor: float) -> Self:
        """This camera for the image resized by `factor` (cv2.resize pixel-centre convention).

        Pixel centres sit at integer coordinates, so a pixel coordinate u maps to
        (u + 0.5) * factor - 0.5. The size is rounded to whole pixels; distortion
        lives in normalised coordinates and is unchanged.
        """
        if not factor > 0:
            raise ValueError(f"scale factor must be positive, got {factor}")
        return dataclasses.replace(
            self,  # type: ignore[type-var]
            width=round(self.width * factor),
            height=round(self.height * factor),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
        )


@dataclass(frozen=True)
class PinholeRadtan(_Pinhole):
    """Kalibr pinhole + radtan: OpenCV plumb-bob with k3 = 0.

    xd = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)
    yd = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y

    Focal lengths and principal point in pixels; coefficients dimensionless.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def kalibr_model(self) -> tuple[str, str]:
        return ("pinhole", "radtan")

    @property
    def opencv_distortion(self) -> FloatArray:
        """[k1, k2, p1, p2, k3=0] for cv2.projectPoints / cv2.undistortPoints."""
        return np.array([self.k1, self.k2, self.p1, self.p2, 0.0], dtype=np.float64)

    @property
    def kalibr_distortion_coeffs(self) -> list[float]:
        """[k1, k2, p1, p2] as Kalibr writes `distortion_coeffs`."""
        return [self.k1, self.k2, self.p1, self.p2]

    def distort(self, xy_normalised: ArrayLike) -> FloatArray:
        """(N,2) normalised -> (N,2) distorted normalised coordinates."""
        xy = _as_points(xy_normalised, 2, "xy_normalised")
        return np.column_stack(self._distort_xy(xy[:, 0], xy[:, 1]))

    def _distort_xy(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + self.k2 * r2)
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def _distort_with_jacobian(
        self, x: FloatArray, y: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        # d(radial)/dx = (k1 + 2 k2 r^2) * 2x, likewise for y.
        dradial = 2.0 * (k1 + 2.0 * k2 * r2)
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        dxd_dx = radial + x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        dxd_dy = x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        dyd_dx = x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        dyd_dy = radial + y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        return xd, yd, dxd_dx, dxd_dy, dyd_dx, dyd_dy

    def undistort(self, xy_distorted: ArrayLike) -> FloatArray:
        """(N,2) distorted normalised -> (N,2) normalised, by damped Newton to 1e-13.

        Rows where the iteration fails (the model folds over beyond its valid
        radius, or a NaN input) come back as NaN.
        """
        target = _as_points(xy_distorted, 2, "xy_distorted")
        tx, ty = target[:, 0], target[:, 1]
        x, y = tx.copy(), ty.copy()
        xd, yd = self._distort_xy(x, y)
        error = np.hypot(xd - tx, yd - ty)
        failed = ~np.isfinite(error)
        active = ~failed & (error > _NEWTON_TOL)
        for _ in range(_NEWTON_MAX_ITER):
            if not active.any():
                break
            idx = np.flatnonzero(active)
            xa, ya, old_error = x[idx], y[idx], error[idx]
            xd, yd, a, b, c, d = self._distort_with_jacobian(xa, ya)
            rx, ry = xd - tx[idx], yd - ty[idx]
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                step_x = (d * rx - b * ry) / det
                step_y = (a * ry - c * rx) / det
            # Halve the step where a full one would not reduce the residual, so strong
            # barrel distortion cannot throw a point past the fold of the model.
            scale = 1.0
            pending = np.arange(len(idx))
            for _halving in range(40):
                cand_x = xa[pending] - scale * step_x[pending]
                cand_y = ya[pending] - scale * step_y[pending]
                cxd, cyd = self._distort_xy(cand_x, cand_y)
                cand_error = np.hypot(cxd - tx[idx[pending]], cyd - ty[idx[pending]])
                accept = np.isfinite(cand_error) & (cand_error < old_error[pending])
                accepted = idx[pending[accept]]
                x[accepted], y[accepted] = cand_x[accept], cand_y[accept]
                error[accepted] = cand_error[accept]
                pending = pending[~accept]
                if not len(pending):
                    break
                scale *= 0.5
            # No decrease possible: either at the floating-point floor (converged) or
            # stuck at a fold with no preimage (failed).
            stuck = idx[pending]
            failed[stuck] = error[stuck] > _NEWTON_ACCEPT
            active[idx] = error[idx] > _NEWTON_TOL
            active[stuck] = False
        failed |= active
        # A root where the Jacobian is not positive lies beyond the fold: the image point
        # there is reached from a more central ray first, so the root is not the ray.
        _, _, a, b, c, d = self._distort_with_jacobian(x, y)
        with np.errstate(invalid="ignore"):
            failed |= ~(a * d - b * c > 0)
        x[failed] = np.nan
        y[failed] = np.nan
        return np.column_stack((x, y))

    @classmethod
    def from_kalibr(
        cls, resolution: tuple[int, int], intrinsics: list[float], distortion_coeffs: list[float]
    ) -> Self:
        """From Kalibr's `resolution` [w, h], `intrinsics` [fu, fv, pu, pv], `distortion_coeffs`."""
        if len(distortion_coeffs) != 4:
            raise ValueError("radtan expects 4 distortion coefficients [k1, k2, p1, p2]")
        fx, fy, cx, cy = intrinsics
        k1, k2, p1, p2 = distortion_coeffs
        return cls(resolution[0], resolution[1], fx, fy, cx, cy, k1, k2, p1, p2)


@dataclass(frozen=True)
class PinholeEquidistant(_Pinhole):
    """Kalibr pinhole + equidistant: the OpenCV fisheye (Kannala-Brandt, 4 terms) model.

    theta = atan(r) with r = |(x, y)|, theta_d = theta (1 + k1 theta^2 + k2 theta^4
    + k3 theta^6 + k4 theta^8), (xd, yd) = (theta_d / r) (x, y).

    Focal lengths and principal point in pixels; coefficients dimensionless.
    Points at or beyond 90 degrees from the optical axis have no (x, y, 1) ray
    and unproject to NaN.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    @property
    def kalibr_model(self) -> tuple[str, str]:
        return ("pinhole", "equidistant")

    @property
    def opencv_distortion(self) -> FloatArray:
        """[k1, k2, k3, k4] for cv2.fisheye.projectPoints / cv2.fisheye.undistortPoints."""
        return np.array([self.k1, self.k2, self.k3, self.k4], dtype=np.float64)

    @property
    def kalibr_distortion_coeffs(self) -> list[float]:
        """[k1, k2, k3, k4] as Kalibr writes `distortion_coeffs`."""
        return [self.k1, self.k2, self.k3, self.k4]

    def _theta_d(self, theta: FloatArray) -> FloatArray:
        t2 = theta * theta
        poly: FloatArray = 1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4)))
        return theta * poly

    def distort(self, xy_normalised: ArrayLike) -> FloatArray:
        """(N,2) normalised -> (N,2) distorted normalised coordinates."""
        xy = _as_points(xy_normalised, 2, "xy_normalised")
        r = np.hypot(xy[:, 0], xy[:, 1])
        theta = np.arctan(r)
        theta_d = self._theta_d(theta)
        # theta_d / r -> 1 as r -> 0.
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(r > 1e-15, theta_d / np.where(r > 1e-15, r, 1.0), 1.0)
        return xy * ratio[:, None]

    def undistort(self, xy_distorted: ArrayLike) -> FloatArray:
        """(N,2) distorted normalised -> (N,2) normalised, Newton on theta to 1e-14 rad.

        NaN where theta_d has no inverse with 0 <= theta < pi/2.
        """
        target = _as_points(xy_distorted, 2, "xy_distorted")
        theta_d = np.hypot(target[:, 0], target[:, 1])
        theta = theta_d.copy()
        active = np.isfinite(theta_d) & (theta_d > 0)
        converged = ~active.copy()
        ks = (self.k1, self.k2, self.k3, self.k4)
        for _ in range(_NEWTON_MAX_ITER):
            if not active.any():
                break
            idx = np.flatnonzero(active)
            t = theta[idx]
            t2 = t * t
            residual = self._theta_d(t) - theta_d[idx]
            slope = 1.0 + t2 * (
                3.0 * ks[0] + t2 * (5.0 * ks[1] + t2 * (7.0 * ks[2] + t2 * 9.0 * ks[3]))
            )
            with np.errstate(divide="ignore", invalid="ignore"):
                step = residual / slope
            t_new = t - step
            theta[idx] = t_new
            done = np.abs(step) < 1e-15 + 1e-15 * np.abs(t_new)
            done |= np.abs(residual) < 1e-15
            converged[idx[done]] = True
            active[idx[done | ~np.isfinite(t_new)]] = False
        theta[~converged] = np.nan
        # A root past 90 degrees, or a negative one, has no (x, y, 1) ray.
        theta[(theta < 0) | (theta >= np.pi / 2)] = np.nan
        if (np.nan_to_num(theta, nan=0.0) > 0).any():
            # Confirm the final residual (Newton's last step is tiny, but be strict).
            resid = np.abs(self._theta_d(theta) - theta_d)
            theta[resid > 1e-12] = np.nan
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(theta_d > 0, np.tan(theta) / np.where(theta_d > 0, theta_d, 1.0), 1.0)
        out = target * ratio[:, None]
        out[~np.isfinite(ratio)] = np.nan
        return out

    @classmethod
    def from_kalibr(
        cls, resolution: tuple[int, int], intrinsics: list[float], distortion_coeffs: list[float]
    ) -> Self:
        """From Kalibr's `resolution` [w, h], `intrinsics` [fu, fv, pu, pv], `distortion_coeffs`."""
        if len(distortion_coeffs) != 4:
            raise ValueError("equidistant expects 4 distortion coefficients [k1, k2, k3, k4]")
        fx, fy, cx, cy = intrinsics
        k1, k2, k3, k4 = distortion_coeffs
        return cls(resolution[0], resolution[1], fx, fy, cx, cy, k1, k2, k3, k4)


KalibrCameraClass = type[PinholeRadtan] | type[PinholeEquidistant]

CAMERA_MODELS: dict[tuple[str, str], KalibrCameraClass] = {
    ("pinhole", "radtan"): PinholeRadtan,
    ("pinhole", "equidistant"): PinholeEquidistant,
}
"""Camera classes by Kalibr (camera_model, distortion_model)."""
