"""The simulated wreck: axis-aligned boxes on a flat seafloor, two AprilGrids, textures.

Pure math (no I/O; `sim.mesh` writes the truth mesh). World frame W of
docs/conventions.md: z up, z = 0 at the sea surface, metres. The wreck lies along x on a
seafloor at z = -17 m: a hull of stepped boxes (bow, stern, a collapsed midship section),
deck plates at about 12 m depth, a superstructure up to 8.4 m depth, a mast, hatch
coamings and debris. Two Kalibr AprilGrids (tag36h11, 88 mm tags, spacing ratio 0.3) are
fixed on faces that divers swim past: a 4x2 grid (ids from 0) on the starboard (+y) hull
side and a 5x4 grid (ids from 100) on the starboard wall of the superstructure.

Faces are numbered `6 * box + 2 * axis + side` (side 0: the face at the box's minimum
along `axis`, 1: at its maximum); the seafloor is face `6 * len(boxes)`. Each face has its
own texture (unique, never tiled) addressed by texture coordinates in metres:
`col = (p[u_axis] - lo[u_axis]) / texel`, `row = (hi[v_axis] - p[v_axis]) / texel`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from shared.calibration.aprilgrid import AprilGridTarget, texture_margin_m
from sim import textures

FloatArray = npt.NDArray[np.float64]

#: In-plane (u, v) axes of a face whose normal is along axis 0, 1, 2. v is z on vertical
#: faces so texture rows run downwards.
FACE_UV_AXES: tuple[tuple[int, int], ...] = ((1, 2), (0, 2), (0, 1))

SEAFLOOR_Z_M = -17.0


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in the world, `lo_m` < `hi_m` (metres); material names a texture."""

    name: str
    lo_m: tuple[float, float, float]
    hi_m: tuple[float, float, float]
    material: str = "plating"


@dataclass(frozen=True)
class TargetPlacement:
    """An AprilGrid fixed in the world: `world_from_target` maps target-frame points (x right,
    y up, z out of the printed face, metres) to the world."""

    name: str
    target: AprilGridTarget
    world_from_target: FloatArray

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the printed board in the target frame (with margin)."""
        margin = texture_margin_m(self.target)
        width, height = self.target.extent_m
        return (-margin, width + margin, -margin, height + margin)


@dataclass(kw_only=True)
class WreckScene:
    """Geometry and albedo of the simulated site.

    boxes: the wreck; seafloor_z_m: height of the flat seafloor (m, negative);
    seafloor_extent_m: (x_min, x_max, y_min, y_max) of the textured seafloor (beyond it the
    texture edge repeats); targets: the AprilGrids; textures: one RGB uint8 image per face
    (index as in the module docstring); texel_m: metres per texel of each face texture.
    """

    boxes: list[Box]
    seafloor_z_m: float = SEAFLOOR_Z_M
    seafloor_extent_m: tuple[float, float, float, float] = (-25.0, 25.0, -15.0, 15.0)
    targets: list[TargetPlacement] = field(default_factory=list)
    textures: list[npt.NDArray[np.uint8]] = field(default_factory=list)
    texel_m: list[float] = field(default_factory=list)

    @property
    def seafloor_face(self) -> int:
        return 6 * len(self.boxes)

    def box_arrays(self) -> tuple[FloatArray, FloatArray]:
        """(B,3) lower and (B,3) upper corners of all boxes (m)."""
        lo = np.array([b.lo_m for b in self.boxes], dtype=np.float64)
        hi = np.array([b.hi_m for b in self.boxes], dtype=np.float64)
        return lo, hi

    def face_frame(self, face: int) -> tuple[int, int, float, float]:
        """(u_axis, v_axis, u_origin_m, v_top_m) of a face's texture coordinates."""
        if face == self.seafloor_face:
            x0, _, _, y1 = self.seafloor_extent_m
            return 0, 1, x0, y1
        box = self.boxes[face // 6]
        axis = (face % 6) // 2
        u_axis, v_axis = FACE_UV_AXES[axis]
        return u_axis, v_axis, box.lo_m[u_axis], box.hi_m[v_axis]


def wreck_boxes() -> list[Box]:
    """The wreck's boxes (world frame, metres). Hull bottoms are buried 0.5 m in the sand."""
    floor = SEAFLOOR_Z_M - 0.5
    return [
        Box("stern", (-14.0, -3.0, floor), (-11.0, 3.0, -12.3)),
        Box("hull_aft", (-11.0, -3.5, floor), (-3.0, 3.5, -12.15)),
        Box("hull_collapsed", (-3.0, -3.3, floor), (-0.5, 3.3, -13.8)),
        Box("hull_fore", (-0.5, -3.5, floor), (9.0, 3.5, -12.15)),
        Box("bow", (9.0, -2.6, floor), (12.0, 2.6, -11.7)),
        Box("stem", (12.0, -1.5, floor), (14.5, 1.5, -11.4)),
        Box("deck_aft", (-11.2, -3.65, -12.15), (-3.0, 3.65, -12.0), "deck"),
        Box("deck_fore", (-0.5, -3.65, -12.15), (9.2, 3.65, -12.0), "deck"),
        Box("bridge", (-9.0, -2.5, -12.0), (-4.0, 2.5, -9.6)),
        Box("wheelhouse", (-8.0, -1.8, -9.6), (-5.5, 1.8, -8.4)),
        Box("mast", (3.0, -0.15, -12.0), (3.3, 0.15, -5.5)),
        Box("hatch_1", (0.8, -1.5, -12.0), (2.6, 1.5, -11.4)),
        Box("hatch_2", (5.0, -1.5, -12.0), (7.2, 1.5, -11.5)),
        Box("winch", (10.0, -0.6, -11.7), (10.9, 0.6, -11.1)),
        Box("bollard_port", (-2.0, -4.8, SEAFLOOR_Z_M - 0.2), (-1.1, -4.1, -16.3)),
        Box("crate", (-6.0, 5.0, SEAFLOOR_Z_M - 0.2), (-4.9, 6.2, -16.45)),
        Box("plate_debris", (10.5, -6.5, SEAFLOOR_Z_M - 0.2), (12.5, -5.0, -16.8)),
    ]


def _target_pose(rotation: FloatArray, origin_m: tuple[float, float, float]) -> FloatArray:
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = origin_m
    return pose


def wreck_targets() -> list[TargetPlacement]:
    """The two AprilGrids, 5 mm proud of the face they are screwed to, printed side out."""
    small = AprilGridTarget(
        tag_rows=2, tag_cols=4, tag_size_m=0.088, tag_spacing_ratio=0.3, tag_id_offset=0
    )
    large = AprilGridTarget(
        tag_rows=4, tag_cols=5, tag_size_m=0.088, tag_spacing_ratio=0.3, tag_id_offset=100
    )
    # On a +y face the printed side faces +y: target x = world -x, y = world z, z = world +y.
    facing_plus_y = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]).T
    return [
        TargetPlacement(
            "aprilgrid_4x2_id0", small, _target_pose(facing_plus_y, (2.6, 3.505, -14.6))
        ),
        TargetPlacement(
            "aprilgrid_5x4_id100", large, _target_pose(facing_plus_y, (-6.0, 2.505, -11.3))
        ),
    ]


def face_hidden(boxes: list[Box], face: int, seafloor_z_m: float = SEAFLOOR_Z_M) -> bool:
    """True when face `face` can never be seen: a bottom resting on or under the seafloor,
    or a face lying against another box that covers all of it."""
    box = boxes[face // 6]
    axis, side = (face % 6) // 2, face % 2
    if axis == 2 and side == 0 and box.lo_m[2] <= seafloor_z_m + 1e-9:
        return True
    plane = box.hi_m[axis] if side else box.lo_m[axis]
    u_axis, v_axis = FACE_UV_AXES[axis]
    for other in boxes:
        if other is box:
            continue
        beyond = other.hi_m[axis] > plane if side else other.lo_m[axis] < plane
        touches = other.lo_m[axis] <= plane <= other.hi_m[axis]
        covers = all(
            other.lo_m[a] <= box.lo_m[a] + 1e-9 and box.hi_m[a] <= other.hi_m[a] + 1e-9
            for a in (u_axis, v_axis)
        )
        if beyond and touches and covers:
            return True
    return False


def _face_texture(
    task: tuple[np.random.SeedSequence, tuple[int, int], str, float, bool],
) -> npt.NDArray[np.uint8]:
    seed, shape, material, texel_m, vertical = task
    rng = np.random.default_rng(seed)
    if material == "deck":
        return textures.deck_texture(rng, shape, texel_m)
    if material == "sand":
        return textures.sand_texture(rng, shape, texel_m)
    return textures.plating_texture(rng, shape, texel_m, vertical=vertical)


def build_wreck_scene(
    *, seed: int, texel_m: float = 0.005, seafloor_texel_m: float = 0.015, workers: int = 1
) -> WreckScene:
    """The wreck with its targets and freshly generated textures (deterministic in `seed`).

    texel_m: metres per texel on the wreck (5 mm resolves detail to about 1.5 m range at
    640 px across a 90 degree view); seafloor_texel_m: the same on the sand; workers:
    processes generating textures (each face has its own random stream, so the result
    does not depend on it).
    """
    scene = WreckScene(boxes=wreck_boxes(), targets=wreck_targets())
    root = np.random.SeedSequence([seed, 0x5EC4])
    children = root.spawn(len(scene.boxes) * 6 + 1)
    tasks: list[tuple[np.random.SeedSequence, tuple[int, int], str, float, bool]] = []
    for face in range(6 * len(scene.boxes)):
        box = scene.boxes[face // 6]
        axis = (face % 6) // 2
        u_axis, v_axis = FACE_UV_AXES[axis]
        if face_hidden(scene.boxes, face, scene.seafloor_z_m):
            tasks.append((children[face], (2, 2), "plating", 1.0, False))
            continue
        size_u = box.hi_m[u_axis] - box.lo_m[u_axis]
        size_v = box.hi_m[v_axis] - box.lo_m[v_axis]
        shape = (
            max(int(np.ceil(size_v / texel_m)) + 1, 2),
            max(int(np.ceil(size_u / texel_m)) + 1, 2),
        )
        material = "deck" if box.material == "deck" and axis == 2 else "plating"
        tasks.append((children[face], shape, material, texel_m, axis != 2))
    x0, x1, y0, y1 = scene.seafloor_extent_m
    shape = (
        int(np.ceil((y1 - y0) / seafloor_texel_m)) + 1,
        int(np.ceil((x1 - x0) / seafloor_texel_m)) + 1,
    )
    tasks.append((children[-1], shape, "sand", seafloor_texel_m, False))
    if workers > 1:
        from shared.forkpool import fork_pool

        # Biggest first, so the two workers finish together.
        order = sorted(range(len(tasks)), key=lambda i: -tasks[i][1][0] * tasks[i][1][1])
        with fork_pool(workers) as pool:
            made = pool.map(_face_texture, [tasks[i] for i in order], chunksize=1)
        images: list[npt.NDArray[np.uint8]] = [np.empty(0, np.uint8)] * len(tasks)
        for i, image in zip(order, made, strict=True):
            images[i] = image
    else:
        images = [_face_texture(task) for task in tasks]
    scene.textures = images
    scene.texel_m = [task[3] for task in tasks]
    return scene
