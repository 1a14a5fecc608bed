"""Ray-cast renderer for the simulated wreck, through any camera model of shared/.

Pure math (numpy, cv2 only for resampling-free helpers; no I/O). Every pixel's ray comes
from `camera.unproject` once per camera (so radtan or equidistant distortion is exact, not a
resampled approximation); each frame rotates the precomputed rays into the world and
intersects them with the scene's axis-aligned boxes (slab test), the seafloor plane and the
AprilGrid boards. Rays are culled per 16x16 tile against each box's projection (clipped to
the camera's front half-space, so the culling is conservative).

Image model (per RGB channel c, linear intensity in [0, 1]):
    E_c = exp(-Kd_c * depth_of_hit) * (ambient + diffuse * max(0, n_z))  downwelling light
    I_c = J_c * E_c * exp(-beta_c * r) + B_c * (1 - exp(-beta_c * r))    attenuation + backscatter
with J the albedo, r the range along the ray (m) and B_c the veiling light. Then vignetting
(cos^4 law blended by `vignetting`), a display gamma of 1/2.2, and sensor noise in 8-bit
digital numbers (DN): sigma^2 = read_noise_dn^2 + shot_noise_gain * I_dn.
Pixels whose ray hits the AprilGrid are supersampled (`target_supersampling`^2 sub-rays) so
the printed edges are antialiased and tag corners stay unbiased.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from shared.calibration.aprilgrid import render_target_texture, texture_margin_m
from shared.calibration.cameras import CameraModel
from sim.scene import TargetPlacement, WreckScene

F32 = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]

TILE_PX = 16
# Camera-frame depth at which a box is clipped before culling (m).
_NEAR_CLIP_M = 1e-3
# AprilGrid texture resolution (pixels per metre of the printed board).
_TARGET_PIXELS_PER_M = 1500.0
# Reflectance of the printed board's white paper and black ink.
_PAPER_WHITE, _INK_BLACK = 0.80, 0.04
# Display gamma 1/2.2 as a lookup table over this many linear levels.
_GAMMA_LEVELS = 4096
_GAMMA_TABLE = (255.0 * np.linspace(0.0, 1.0, _GAMMA_LEVELS) ** (1.0 / 2.2)).astype(np.float32)


@dataclass(kw_only=True)
class WaterModel:
    """Water, light and sensor parameters of the image model (see the module docstring).

    attenuation_per_m: beta_c for R, G, B (1/m); backscatter: B_c for R, G, B (linear, 0..1);
    downwelling_per_m: Kd_c for R, G, B (1/m), dimming light with the hit point's depth;
    ambient, diffuse: light on vertical faces and the extra on upward faces (linear);
    exposure: gain on the linear intensity; vignetting: 0 (none) .. 1 (full cos^4);
    read_noise_dn, shot_noise_gain: sensor noise in 8-bit digital numbers.
    """

    attenuation_per_m: tuple[float, float, float] = (0.40, 0.13, 0.11)
    backscatter: tuple[float, float, float] = (0.02, 0.13, 0.16)
    downwelling_per_m: tuple[float, float, float] = (0.08, 0.025, 0.02)
    ambient: float = 0.75
    diffuse: float = 0.45
    exposure: float = 2.2
    vignetting: float = 0.5
    read_noise_dn: float = 1.2
    shot_noise_gain: float = 0.08

    @classmethod
    def clear(cls) -> WaterModel:
        """No water, no vignetting, no noise: albedo under even light (for geometry tests)."""
        return cls(
            attenuation_per_m=(0.0, 0.0, 0.0),
            backscatter=(0.0, 0.0, 0.0),
            downwelling_per_m=(0.0, 0.0, 0.0),
            ambient=1.0,
            diffuse=0.0,
            exposure=1.0,
            vignetting=0.0,
            read_noise_dn=0.0,
            shot_noise_gain=0.0,
        )


@dataclass
class RenderedFrame:
    """One rendered view.

    image_rgb: (H, W, 3) uint8; range_m: (H, W) float32 distance from the camera centre
    along each pixel's ray (inf where the ray hits nothing); depth_m: (H, W) float32 camera
    z of the hit (the depth-map convention); face: (H, W) int32 face index of the hit
    (scene numbering, targets after the seafloor, -1 for none).
    """

    image_rgb: npt.NDArray[np.uint8]
    range_m: F32
    depth_m: F32
    face: npt.NDArray[np.int32]


class Renderer:
    """Renders `scene` through `camera` from any `world_from_cam` pose.

    Construction precomputes the camera's rays (and the sub-pixel rays for the targets)
    and flattens the scene's textures; `render` is then one call per frame. Safe to share
    between forked worker processes (read-only after construction).
    """

    def __init__(
        self,
        scene: WreckScene,
        camera: CameraModel,
        water: WaterModel | None = None,
        *,
        target_supersampling: int = 3,
    ) -> None:
        self.scene = scene
        self.camera = camera
        self.water = water if water is not None else WaterModel()
        self.width, self.height = int(camera.width), int(camera.height)
        vv, uu = np.mgrid[0 : self.height, 0 : self.width]
        pixels = np.column_stack((uu.ravel(), vv.ravel())).astype(np.float64)
        rays = camera.unproject(pixels)
        self._valid = np.all(np.isfinite(rays), axis=1)
        rays[~self._valid] = (0.0, 0.0, 1.0)
        self._rays_cam = rays.astype(np.float32)  # (N,3) with z = 1: t is the camera depth
        self._ray_norm = np.linalg.norm(self._rays_cam, axis=1).astype(np.float32)
        self._tiles = self._build_tiles(rays)
        s = max(int(target_supersampling), 1)
        offsets = (np.arange(s) + 0.5) / s - 0.5
        self._sub_offsets = np.array([(du, dv) for dv in offsets for du in offsets])
        self._sub_ray_cache: list[F32] | None = None
        self._boxes_lo, self._boxes_hi = (a.astype(np.float64) for a in scene.box_arrays())
        self._build_texture_table()
        cos_theta = 1.0 / self._ray_norm
        v = float(self.water.vignetting)
        self._vignette = ((1.0 - v) + v * cos_theta**4).astype(np.float32)

    def prepare(self) -> None:
        """Compute what is otherwise made on first use (the sub-pixel rays), e.g. before
        forking worker processes so they share it."""
        self._sub_rays()

    # ----------------------------------------------------------------- set-up

    def _build_tiles(self, rays: FloatArray) -> list[tuple[npt.NDArray[np.int64], FloatArray]]:
        """Pixel indices of each tile and the (x, y) bounds of its normalised rays."""
        tiles = []
        index = np.arange(self.width * self.height).reshape(self.height, self.width)
        for r0 in range(0, self.height, TILE_PX):
            for c0 in range(0, self.width, TILE_PX):
                idx = index[r0 : r0 + TILE_PX, c0 : c0 + TILE_PX].ravel()
                xy = rays[idx, :2]
                bounds = np.array([xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()])
                tiles.append((idx, bounds))
        self._tile_bounds = np.array([b for _, b in tiles])
        return tiles

    def _build_texture_table(self) -> None:
        scene = self.scene
        images = list(scene.textures)
        frames = [scene.face_frame(f) for f in range(len(images))]
        texel = list(scene.texel_m)
        self._target_textures = []
        for placement in scene.targets:
            gray = render_target_texture(placement.target, _TARGET_PIXELS_PER_M)
            self._target_textures.append(gray.astype(np.float32) / 255.0)
            albedo = _INK_BLACK + (_PAPER_WHITE - _INK_BLACK) * gray.astype(np.float32) / 255.0
            images.append(np.repeat((albedo * 255.0 + 0.5).astype(np.uint8)[..., None], 3, axis=2))
            margin = texture_margin_m(placement.target)
            top = placement.target.extent_m[1] + margin
            # Target faces use target-frame coordinates (x, y) as (u, v).
            frames.append((0, 1, -margin, top))
            texel.append(1.0 / _TARGET_PIXELS_PER_M)
        self._first_target_face = len(scene.textures)
        sizes = np.array([im.shape[0] * im.shape[1] for im in images], dtype=np.int64)
        self._tex_offset = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        self._tex_rows = np.array([im.shape[0] for im in images], dtype=np.int64)
        self._tex_cols = np.array([im.shape[1] for im in images], dtype=np.int64)
        flat = np.concatenate([im.reshape(-1, 3) for im in images]).astype(np.uint8)
        rgba = np.zeros((len(flat), 4), dtype=np.uint8)
        rgba[:, :3] = flat
        self._tex_packed = rgba.view(np.uint32).ravel()
        self._face_u_axis = np.array([f[0] for f in frames], dtype=np.int64)
        self._face_v_axis = np.array([f[1] for f in frames], dtype=np.int64)
        self._face_u0 = np.array([f[2] for f in frames], dtype=np.float64)
        self._face_vtop = np.array([f[3] for f in frames], dtype=np.float64)
        self._face_texel = np.array(texel, dtype=np.float64)
        normal_z = np.zeros(len(images), dtype=np.float32)
        for f in range(6 * len(scene.boxes)):
            if (f % 6) // 2 == 2:
                normal_z[f] = 1.0 if f % 2 == 1 else -1.0
        normal_z[scene.seafloor_face] = 1.0
        self._face_normal_z = normal_z

    # ----------------------------------------------------------------- rendering

    def _tile_pixels(self, corners_cam: FloatArray) -> npt.NDArray[np.int64] | None:
        """Pixels whose rays may hit the convex hull of `corners_cam`; None means all."""
        z = corners_cam[:, 2]
        front = corners_cam[z > _NEAR_CLIP_M]
        if len(front) == 0:
            return np.zeros(0, dtype=np.int64)
        points = [front]
        if len(front) < len(corners_cam):
            # Where segments between corners cross the near plane: with the front corners
            # these span the visible part of the convex hull (all pairs include the edges).
            count = len(corners_cam)
            for a in range(count):
                for b in range(a + 1, count):
                    za, zb = z[a], z[b]
                    if (za - _NEAR_CLIP_M) * (zb - _NEAR_CLIP_M) < 0:
                        w = (_NEAR_CLIP_M - za) / (zb - za)
                        points.append(
                            (corners_cam[a] + w * (corners_cam[b] - corners_cam[a]))[None]
                        )
        pts = np.concatenate(points)
        xy = pts[:, :2] / pts[:, 2:3]
        bx0, by0 = xy.min(axis=0)
        bx1, by1 = xy.max(axis=0)
        tb = self._tile_bounds
        hit = (tb[:, 1] >= bx0) & (tb[:, 0] <= bx1) & (tb[:, 3] >= by0) & (tb[:, 2] <= by1)
        count = int(hit.sum())
        if count == len(tb):
            return None
        if count == 0:
            return np.zeros(0, dtype=np.int64)
        return np.concatenate([self._tiles[i][0] for i in np.flatnonzero(hit)])

    def render(
        self, world_from_cam: npt.ArrayLike, *, rng: np.random.Generator | None = None
    ) -> RenderedFrame:
        """Render the view of a camera at `world_from_cam` (4x4, metres).

        rng: source of the sensor noise (None: no noise, whatever the water model says).
        """
        pose = np.asarray(world_from_cam, dtype=np.float64)
        rot, origin = pose[:3, :3], pose[:3, 3]
        n = self.width * self.height
        # World ray directions, one contiguous array per axis (fast elementwise slabs).
        rx, ry = self._rays_cam[:, 0], self._rays_cam[:, 1]
        r32 = rot.astype(np.float32)
        dirs = [r32[a, 0] * rx + r32[a, 1] * ry + r32[a, 2] for a in range(3)]
        with np.errstate(divide="ignore"):
            inv = [np.float32(1.0) / d for d in dirs]
        best_t = np.full(n, np.inf, dtype=np.float32)
        best_face = np.full(n, -1, dtype=np.int32)
        cam_from_world_rot = rot.T
        corner_bits = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
        for b in range(len(self._boxes_lo)):
            lo, hi = self._boxes_lo[b], self._boxes_hi[b]
            corners = np.where(corner_bits, hi, lo)
            sel = self._tile_pixels((corners - origin) @ cam_from_world_rot.T)
            if sel is not None and len(sel) == 0:
                continue
            t_min = []
            t_near: F32 | None = None
            t_far: F32 | None = None
            for a in range(3):
                inv_a = inv[a] if sel is None else inv[a][sel]
                t0 = np.float32(lo[a] - origin[a]) * inv_a
                t1 = np.float32(hi[a] - origin[a]) * inv_a
                near = np.minimum(t0, t1)
                far = np.maximum(t0, t1, out=t1)
                t_min.append(near)
                t_near = near.copy() if t_near is None else np.maximum(t_near, near, out=t_near)
                t_far = far if t_far is None else np.minimum(t_far, far, out=t_far)
            assert t_near is not None and t_far is not None
            current = best_t if sel is None else best_t[sel]
            hit = np.flatnonzero((t_near <= t_far) & (t_near > 0) & (t_near < current))
            if len(hit) == 0:
                continue
            # The face entered last is the one hit: its slab's entry time is the largest.
            tx, ty, tz = (t[hit] for t in t_min)
            axis = np.where((tx >= ty) & (tx >= tz), 0, np.where(ty >= tz, 1, 2))
            d_axis = np.choose(axis, [d[hit if sel is None else sel[hit]] for d in dirs])
            face = 6 * b + 2 * axis + (d_axis <= 0)
            chosen = hit if sel is None else sel[hit]
            best_t[chosen] = t_near[hit]
            best_face[chosen] = face
        # Seafloor plane.
        dz = dirs[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.float32(self.scene.seafloor_z_m - origin[2]) * inv[2]
        floor_hit = (dz < 0) & (t_floor > 0) & (t_floor < best_t)
        best_t[floor_hit] = t_floor[floor_hit]
        best_face[floor_hit] = self.scene.seafloor_face
        # AprilGrid boards (thin rectangles just proud of their faces).
        for k, placement in enumerate(self.scene.targets):
            self._hit_target(k, placement, pose, dirs, best_t, best_face)
        best_t[~self._valid] = np.inf
        best_face[~self._valid] = -1
        return self._shade(pose, dirs, best_t, best_face, rng)

    def _hit_target(
        self,
        k: int,
        placement: TargetPlacement,
        pose: FloatArray,
        dirs: list[F32],
        best_t: F32,
        best_face: npt.NDArray[np.int32],
    ) -> None:
        """Mark (in place) the pixels whose nearest hit is the board of target k."""
        T = placement.world_from_target
        x0, x1, y0, y1 = placement.bounds_m
        board = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
        board_w = board @ T[:3, :3].T + T[:3, 3]
        origin = pose[:3, 3]
        # Seen from behind, the board is hidden by the face it is screwed to.
        if float((origin - T[:3, 3]) @ T[:3, 2]) <= 0:
            return
        sel = self._tile_pixels((board_w - origin) @ pose[:3, :3])
        if sel is not None and len(sel) == 0:
            return
        idx = np.arange(len(best_t)) if sel is None else sel
        d = np.column_stack([dirs[a][idx] for a in range(3)]).astype(np.float64)
        normal = T[:3, 2]
        denom = d @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = float(normal @ (T[:3, 3] - origin)) / denom
        points = origin + t[:, None] * d
        local = (points - T[:3, 3]) @ T[:3, :2]
        inside = (
            (denom < 0)
            & (t > 0)
            & (t < best_t[idx])
            & (local[:, 0] >= x0)
            & (local[:, 0] <= x1)
            & (local[:, 1] >= y0)
            & (local[:, 1] <= y1)
        )
        chosen = idx[inside]
        best_t[chosen] = t[inside]
        best_face[chosen] = self._first_target_face + k

    def _sample_faces(self, faces: npt.NDArray[np.int64], points: list[FloatArray]) -> F32:
        """Bilinear albedo (M,3) in [0,1] of `points` (3 arrays of M world coordinates)."""
        u_axis = self._face_u_axis[faces]
        v_axis = self._face_v_axis[faces]
        texel = self._face_texel[faces]
        pu = np.choose(u_axis, points)
        pv = np.choose(v_axis, points)
        col = (pu - self._face_u0[faces]) / texel - 0.5
        row = (self._face_vtop[faces] - pv) / texel - 0.5
        return self._bilinear(faces, col, row)

    def _bilinear(self, faces: npt.NDArray[np.int64], col: FloatArray, row: FloatArray) -> F32:
        cols = self._tex_cols[faces]
        rows = self._tex_rows[faces]
        col = np.clip(col, 0.0, cols - 1.001)
        row = np.clip(row, 0.0, rows - 1.001)
        c0 = col.astype(np.int64)
        r0 = row.astype(np.int64)
        fc = (col - c0).astype(np.float32)[:, None]
        fr = (row - r0).astype(np.float32)[:, None]
        base = self._tex_offset[faces] + r0 * cols + c0
        # Texels are packed RGBA in one uint32: one gather per neighbour instead of three.
        tex = self._tex_packed

        def texel_rgb(index: npt.NDArray[np.int64]) -> F32:
            return tex[index].view(np.uint8).reshape(-1, 4)[:, :3].astype(np.float32)

        top = texel_rgb(base)
        top += (texel_rgb(base + 1) - top) * fc
        bottom = texel_rgb(base + cols)
        bottom += (texel_rgb(base + cols + 1) - bottom) * fc
        top += (bottom - top) * fr
        top *= np.float32(1.0 / 255.0)
        return top

    def _target_supersampled(self, k: int, pixels: npt.NDArray[np.int64], pose: FloatArray) -> F32:
        """Mean albedo of `target_supersampling`^2 sub-rays per pixel on target k (M,)."""
        placement = self.scene.targets[k]
        texture = self._target_textures[k]
        target_from_cam = np.linalg.inv(placement.world_from_target) @ pose
        margin = texture_margin_m(placement.target)
        top = placement.target.extent_m[1] + margin
        o = target_from_cam[:3, 3]
        total = np.zeros(len(pixels), dtype=np.float64)
        count = np.zeros(len(pixels), dtype=np.float64)
        for sub_rays in self._sub_rays():
            d = sub_rays[pixels].astype(np.float64) @ target_from_cam[:3, :3].T
            # Sub-rays outside a fisheye's field of view are NaN: they miss (ok is False).
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -o[2] / d[:, 2]
                ok = np.isfinite(t) & (t > 0)
                x = o[0] + t * d[:, 0]
                y = o[1] + t * d[:, 1]
            col = np.nan_to_num((x + margin) * _TARGET_PIXELS_PER_M - 0.5)
            row = np.nan_to_num((top - y) * _TARGET_PIXELS_PER_M - 0.5)
            col = np.clip(col, 0, texture.shape[1] - 1.001)
            row = np.clip(row, 0, texture.shape[0] - 1.001)
            c0, r0 = col.astype(np.int64), row.astype(np.int64)
            fc, fr = col - c0, row - r0
            value = (
                texture[r0, c0] * (1 - fc) * (1 - fr)
                + texture[r0, c0 + 1] * fc * (1 - fr)
                + texture[r0 + 1, c0] * (1 - fc) * fr
                + texture[r0 + 1, c0 + 1] * fc * fr
            )
            total += np.where(ok, value, 0.0)
            count += ok
        gray = total / np.maximum(count, 1)
        return (_INK_BLACK + (_PAPER_WHITE - _INK_BLACK) * gray).astype(np.float32)

    def _sub_rays(self) -> list[F32]:
        """Rays (N,3) through each sub-pixel offset, computed on first use."""
        if self._sub_ray_cache is None:
            vv, uu = np.mgrid[0 : self.height, 0 : self.width]
            u, v = uu.ravel().astype(np.float64), vv.ravel().astype(np.float64)
            cache = []
            for du, dv in self._sub_offsets:
                rays = self.camera.unproject(np.column_stack((u + du, v + dv)))
                cache.append(np.nan_to_num(rays, nan=0.0).astype(np.float32))
            self._sub_ray_cache = cache
        return self._sub_ray_cache

    def _shade(
        self,
        pose: FloatArray,
        dirs: list[F32],
        best_t: F32,
        best_face: npt.NDArray[np.int32],
        rng: np.random.Generator | None,
    ) -> RenderedFrame:
        water = self.water
        n = len(best_t)
        origin = pose[:3, 3]
        hit = np.flatnonzero(best_face >= 0)
        faces = best_face[hit].astype(np.int64)
        t_hit = best_t[hit].astype(np.float64)
        points = [origin[a] + t_hit * dirs[a][hit] for a in range(3)]
        albedo = self._sample_faces(faces, points)
        # Boards are sampled in their own frame (and supersampled), never from the table.
        for k in range(len(self.scene.targets)):
            on_target = np.flatnonzero(faces == self._first_target_face + k)
            if len(on_target):
                gray = self._target_supersampled(k, hit[on_target], pose)
                albedo[on_target] = gray[:, None]
        range_m = best_t * self._ray_norm
        kd = np.asarray(water.downwelling_per_m, dtype=np.float32)
        beta = np.asarray(water.attenuation_per_m, dtype=np.float32)
        veil = np.asarray(water.backscatter, dtype=np.float32)
        hit_depth = np.maximum(-points[2], 0.0).astype(np.float32)
        light = np.exp(-kd[None, :] * hit_depth[:, None])
        light *= (water.ambient + water.diffuse * np.maximum(self._face_normal_z[faces], 0.0))[
            :, None
        ]
        camera_depth = max(-float(origin[2]), 0.0)
        veil_here = (veil * np.exp(-kd * camera_depth)).astype(np.float32)
        linear = np.empty((n, 3), dtype=np.float32)
        linear[:] = veil_here  # rays into open water see only the veiling light
        transmission = np.exp(-beta[None, :] * range_m[hit, None])
        albedo *= light
        albedo -= veil_here
        albedo *= transmission
        albedo += veil_here
        linear[hit] = albedo
        linear *= np.float32(water.exposure) * self._vignette[:, None]
        # Display gamma through a table: 4096 linear levels are finer than 8-bit output.
        levels = np.minimum(linear * np.float32(_GAMMA_LEVELS - 1) + 0.5, _GAMMA_LEVELS - 1)
        dn = _GAMMA_TABLE[levels.astype(np.int32)]
        if rng is not None and (water.read_noise_dn > 0 or water.shot_noise_gain > 0):
            sigma = np.sqrt(
                np.float32(water.read_noise_dn**2) + np.float32(water.shot_noise_gain) * dn
            )
            dn += sigma * rng.standard_normal(dn.shape, dtype=np.float32)
        dn += np.float32(0.5)
        image = np.clip(dn, 0, 255).astype(np.uint8).reshape(self.height, self.width, 3)
        depth = best_t.copy()
        depth[best_face < 0] = np.inf
        range_m[best_face < 0] = np.inf
        shape = (self.height, self.width)
        return RenderedFrame(
            image_rgb=image,
            range_m=range_m.reshape(shape),
            depth_m=depth.reshape(shape),
            face=best_face.reshape(shape),
        )
