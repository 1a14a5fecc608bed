"""The dense stage's options: view selection, neighbours, CPU stereo, fusion, meshing,
colour correction, and `DenseOptions` that holds them.

Light on purpose (no OpenCV, pycolmap or NumPy here): the command line builds its flags
from these classes (postproc.pipeline.options) without importing the stage. Each class
is re-exported by the module that uses it (`postproc.dense.fusion.FusionOptions`...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal


@dataclass(kw_only=True)
class NeighbourOptions:
    """How neighbours are scored.

    max_neighbours: partners kept per image; min_angle_deg / max_angle_deg: triangulation
    angle at the reference's scene depth outside which a pair is rejected;
    best_angle_deg: the angle scored highest; min_overlap: smallest fraction of the
    reference's view (sampled on a grid at its scene depth) that must land in the partner;
    min_sideways: smallest sine of the angle between the baseline and the reference's
    optical axis (0: any motion, 1: purely sideways); far_neighbours: extra partners,
    beyond `max_neighbours`, scored at the reference's far scene depth (a long oblique
    wall or the seafloor 5-8 m away needs a longer baseline than its median depth asks
    for: the triangulation angle falls with depth), when far depths are given.

    3 + 1 partners (instead of 4 + 2): stereo time per reference x 0.71 (same process,
    960x540), accuracy / completeness at 5 cm 97.5 / 71.5 % instead of 97.3 / 72.1 %
    (`bench_dense.py`, 960x540, reference views of the default selection).
    """

    max_neighbours: int = 3
    far_neighbours: int = 1
    min_angle_deg: float = 2.0
    max_angle_deg: float = 30.0
    best_angle_deg: float = 10.0
    min_overlap: float = 0.3
    min_sideways: float = 0.5


@dataclass(kw_only=True)
class ViewSelectionOptions:
    """Which keyframes get a depth map of their own (reference views).

    SLAM keeps a keyframe every few tenths of a second; a depth map for each of them
    computes the same surface many times over (and twice where the diver swims back).
    A keyframe becomes a reference unless a reference already chosen lies within
    `min_baseline_rel` times its scene depth (median sparse-point depth, m) AND looks in
    a direction within `min_rotation_deg` of its own (angle between optical axes, so a
    roll about the axis does not count): dense work then grows with the surveyed
    surface, not with the time spent over it. Every keyframe remains a stereo source.

    The defaults space references about a third of a footprint apart (0.10 of the scene
    depth, 7 degrees), so a surface lies in two or more reference depth maps: the mesh
    keeps only points that two maps agree on (`mesh_min_images`). At 0.3 / 20 degrees
    most surface was in one map only, and a simulated 10-minute dive (1227 keyframes)
    got 39 references and a mesh covering 16 % of the filmed surface at 5 cm; at 0.15 /
    10 degrees, 130 references and 55 %, for 1.7x the dense time. On bench_pipeline's
    10-minute dive at x264 CRF 18 (1218 keyframes, one-off script on the run's SfM),
    0.15 / 10 degrees gave 134 references and a mesh of 96.5 / 64.8 % (accuracy /
    completeness at 5 cm) in 203 s; 0.10 / 7 degrees 301 references and 92.3 / 74.6 %
    in 424 s, 96.3 / 69.6 % with `DenseOptions.mesh_stray_neighbours` 10 (98.3 / 59.3 %
    with 134 references).

    enabled: False makes every keyframe a reference.
    min_baseline_rel: distance to the nearest reference, as a fraction of the scene
        depth, beyond which a keyframe sees enough new surface (0.10 at 2.5 m: 0.25 m).
    min_rotation_deg: turn beyond which a keyframe sees another part of the scene or the
        same surface from another side.
    """

    enabled: bool = True
    min_baseline_rel: float = 0.10
    min_rotation_deg: float = 7.0


@dataclass(kw_only=True)
class CpuStereoOptions:
    """Matching parameters.

    block_size_px: SGBM window (odd); p1, p2: SGBM smoothness penalties per channel and
    pixel of window (scaled by block area); uniqueness_pct: SGBM uniqueness margin;
    lr_max_diff_px: left-right check tolerance (SGBM disp12MaxDiff); max_disparities:
    cap on the disparity search width (px); min_consistent: pairs that must agree on a
    pixel's depth; consistency_rel: their agreement as a fraction of the depth;
    max_rect_scale: cap on the rectified image size relative to the reference image;
    normal_step_px: pixel spacing of the finite differences behind the normals;
    support_tolerance_m: how close a pair's depth must be to the depth kept to count in
    the pixel's support (`DenseOptions.mesh_single_image_min_pairs`).

    Defaults measured on the simulated survey (640x360, true poses; pixel coverage of
    depths 5-6 m / 6-8 m against the true depth): 7 px blocks and a strong P2 keep the
    low-contrast far water-hazed surfaces matched (0.37 -> 0.63, 0.13 -> 0.33 with
    min_consistent 1); min_consistent 1 keeps a pixel that one pair matched through its
    left-right check when no other pair saw it (far and image-border pixels), since
    stereo fusion checks every depth against the other images again (its
    min_num_pixels).
    """

    block_size_px: int = 7
    p1: float = 8.0
    p2: float = 96.0
    uniqueness_pct: int = 10
    lr_max_diff_px: int = 1
    speckle_window_px: int = 100
    speckle_range: int = 2
    max_disparities: int = 256
    min_consistent: int = 1
    consistency_rel: float = 0.02
    max_rect_scale: float = 2.0
    normal_step_px: int = 2
    support_tolerance_m: float = 0.02


@dataclass(kw_only=True)
class FusionOptions:
    """COLMAP StereoFusionOptions we set (the rest keep COLMAP's defaults).

    min_num_pixels: images that must agree on a point.
    max_reproj_error_px: reprojection agreement.
    max_depth_error_rel: depth agreement as a fraction of the depth.
    max_normal_error_deg: normal agreement (our CPU normals come from finite differences of
        the depth, noisier than PatchMatch's, so the default is looser than COLMAP's 10).
    check_num_images: overlapping images checked per reference image.
    input_type: "geometric" (filtered maps) or "photometric".
    num_threads: worker threads (-1: all cores).
    max_tile_pixels: valid depth pixels fused by one COLMAP call; more are fused box by
        box (space cut so that no box holds more), which bounds memory: one call keeps
        about 450 bytes for each point it fuses (0: always one call).

    min_num_pixels 2 and max_depth_error_rel 0.02 (looser than COLMAP's 5 and 0.01) were
    measured on the simulated survey (640x360, true poses): completeness at 5 cm 58.7 ->
    67.6 %, accuracy 99.9 -> 99.3 %. Far surfaces (5-8 m through hazy water) are matched
    by few images and with depth errors near 1-2 %: the stricter rules dropped them.
    min_num_pixels 1 since depth maps exist for reference views only (about a third of
    the keyframes, `ViewSelectionOptions`): each far surface is then in fewer depth maps
    (`bench_dense.py`, 960x540, 19 of 56 keyframes: accuracy / completeness at 5 cm
    99.9 / 48.9 % with 2, 97.3 / 72.1 % with 1). Every depth kept already passed the
    stereo's left-right check.
    max_depth_error_rel back to COLMAP's 0.01 since fusion checks each reference against
    the other references alone (`postproc.dense.fusion.references_workspace`), so that
    references meet more often: on the 10-minute dive (`bench_pipeline.py`, fusion
    variants scored outside the bench) the mesh at 5 cm was 96.9 / 55.6 % before, 95.9 /
    58.9 % with 0.02 and 96.8 / 57.3 % with 0.01; `bench_dense.py` (40 s) 99.4 / 61.4 %
    with 0.02, 99.8 / 59.4 % with 0.01.
    """

    min_num_pixels: int = 1
    max_reproj_error_px: float = 2.0
    max_depth_error_rel: float = 0.01
    max_normal_error_deg: float = 25.0
    check_num_images: int = 50
    input_type: Literal["geometric", "photometric"] = "geometric"
    num_threads: int = -1
    max_tile_pixels: int = 24_000_000


@dataclass(kw_only=True)
class MeshingOptions:
    """Screened Poisson meshing of the fused points.

    octree_depth: Poisson octree depth (None: chosen from the scene).
    min_depth / max_depth: bounds of the octree depth chosen from the scene.
    point_weight: screening weight (COLMAP's default 1).
    poisson_trim: COLMAP's density trim (0: off, we trim by distance instead).
    trim_distance_spacings: drop vertices farther than this many point spacings (or octree
        cells, when coarser) from the fused points (0: keep everything).
    num_threads: worker threads (-1: all cores).

    bench_pipeline.py's 10-minute dive (points 3.0 mm apart over 19 m), its dense folder
    meshed again by a one-off script (accuracy / completeness at 5 cm, meshing and carving
    seconds): depth 10 (1.85 cm cells), trim 2.5, 96.4 / 70.6 %, 26 s; trim 2.0, 96.9 /
    69.8 %; depth 11 (0.93 cm), trim 2.5, 98.0 / 69.2 %, 78 s; depth 11, trim 4.0 (3.7
    cm, the defaults from stop 44 to 54), 97.6 / 70.4 %, 76 s. Finer cells follow edges
    and thin parts the coarser ones round off; the wider trim keeps the completeness.
    Trim 4 -> 6 spacings on the same folders: stop 54's run 97.5 / 69.2 -> 97.3 / 70.2 %,
    stop 55's 98.3 / 71.3 -> 98.0 / 72.1 %, their 3-minute prefixes 98.2 / 65.8 -> 98.0 /
    66.7 % and 97.6 / 65.5 -> 97.3 / 66.5 %, bench_dense's session 99.7 / 63.7 -> 99.6 /
    64.2 %: every scene gains more completeness than it loses accuracy (6 since stop 55).
    """

    octree_depth: int | None = None
    min_depth: int = 6
    max_depth: int = 11
    point_weight: float = 1.0
    poisson_trim: float = 0.0
    trim_distance_spacings: float = 6.0
    num_threads: int = -1


@dataclass(kw_only=True)
class ColourOptions:
    """The water's colour model (see the module postproc.dense.colour).

    attenuation_per_m: known attenuation beta per R, G, B (None: estimated from the points).
    backscatter: known veiling light B per R, G, B, linear 0..1 (None: estimated).
    gamma: display gamma of the images.
    white_balance: divide out the per-channel illumination (grey world).
    min_range_span_m: smallest spread (5-95 %) of point ranges that makes the estimate
        meaningful.
    """

    attenuation_per_m: tuple[float, float, float] | None = None
    backscatter: tuple[float, float, float] | None = None
    gamma: float = 2.2
    white_balance: bool = True
    min_range_span_m: float = 0.5


@dataclass(kw_only=True)
class DenseOptions:
    """What the dense stage does.

    max_image_size_px: longest side of the undistorted images (and so of the depth maps).
    backend: "auto" (PatchMatch when pycolmap has CUDA, else CPU), "cpu" or "patchmatch".
    image_dir: the images the model names (None: look beside the model).
    fallback_depth_range_m: (near, far) camera depths searched by an image that sees too
        few sparse points to know its own.
    view_selection: which images get a depth map of their own (the CPU backend; every
        image stays a stereo source).
    neighbours: how the stereo sources of a reference image are scored.
    stereo: the CPU stereo's matching.
    fusion: COLMAP's stereo fusion.
    meshing: the screened Poisson mesh.
    colour_correction: also write `fused_corrected.ply` (attenuation removed) and mesh it.
    colour: the water's attenuation and veiling light (estimated when not given).
    make_mesh: run Poisson meshing.
    mesh_min_images: fused points seen in fewer images than this are left out of the
        mesh (`fused_supported.ply`: with fusion's min_num_pixels 1, single-image depths
        complete the cloud, but scattered ones make Poisson grow surface nothing
        supports).
    mesh_single_image_neighbours / mesh_single_image_radius_m: a density rule that keeps
        some of the points seen in fewer than `mesh_min_images` images in the mesh: one
        with at least this many fused points (any support) within the radius (m) is part
        of a surface patch, not a stray (0: leave every such point out).
    mesh_single_image_min_pairs: a per-pixel stereo confidence rule that keeps such a
        point when, at its pixel, at least this many of its depth map's stereo pairs
        agreed on the depth within `CpuStereoOptions.support_tolerance_m` (so that many + 1
        images matched it; CPU stereo only; 0: off). Measured (`bench_dense.py`, 40 s at
        960x540, true poses, 31 of 56 depth maps): of the points of one depth map, those 3
        pairs support lie within 5 cm of the truth 99.6 % of the time (2 pairs: 96.6 %, 1:
        72.8 %); the mesh (accuracy / completeness at 5 cm) went from 99.5 / 60.4 % to
        99.4 / 61.4 % with 4, 98.8 / 63.3 % with 3 and 91.9 / 70.4 % with 2. On
        bench_pipeline's 2-minute dive (SfM poses) the same mesh was 95.9 / 62.7 % without
        the rule, 95.9 / 63.2 % with 4 and 93.4 / 64.7 % with 3: sparse far points of one
        map spread Poisson surface, so 4 (every pair of the default 3 + 1).
    mesh_single_image_near_min_pairs / mesh_single_image_near_range_m: the same rule
        with fewer pairs for the points no farther than the range (m) from their map's
        camera (0 pairs: off, the default). Through water a far surface loses contrast,
        and there a few pairs agree on a wrong depth by chance. On uncompressed frames
        (`bench_dense.py`, 40 s at 960x540, PNG, true poses, the simulator's water: green
        attenuation length 7.7 m) two pairs are enough nearer than 6 m (99.0 % of such
        points within 5 cm at 2-4 m, 92.8 % at 5-6 m, 55.4 % at 6-7 m), and 2 pairs within
        6 m took the mesh at 5 cm from 99.8 / 59.3 % to 97.9 / 67.9 %. On H.264 video they
        are not: on bench_pipeline's 10-minute dive (the simulator's video at CRF 28, SfM
        poses) two-pair points at 2-3 m are 85 % within 5 cm, and the rule took the mesh
        from 97.2 / 58.3 % to 82.1 / 65.9 % (6 m) or 95.1 / 58.5 % (2 m); one-off script on
        the run's folder. So use it on uncompressed or lightly compressed images only, with
        the range at about the water's visibility.
    mesh_stray_neighbours / mesh_stray_radius_m: after those rules, a point with fewer
        than this many other mesh points within the radius (m) is a stray and is left
        out, however many images saw it (0: off). Poisson grows a blob of surface around
        each lone point, and the trim keeps it (its vertices lie near that point). On
        bench_pipeline's 10-minute dive (x264 CRF 18, SfM poses, 301 depth maps, one-off
        script on the run's folder), the mesh at 5 cm went from 92.3 / 74.6 % to 94.7 /
        72.8 % with 5 neighbours within 5 cm, 95.7 / 71.0 % with 8, 96.3 / 69.6 % with 10
        (0.7 % of the points left out), 96.8 / 66.5 % with 15 and 97.1 / 63.6 % with 20.
        8 since free-space carving (below) removes what 8 leaves and 10 did not.
    mesh_stray_radius_spacings: the stray rule's radius is at least this many median
        point spacings: a coarse cloud (small images, a distant survey) has fewer points
        in 5 cm, all of them surface. That dive's spacing (3.0 mm) leaves 5 cm in force.
        On the demo's dives (depth maps 320 px wide, spacing 1.0 cm; one-off script on
        its folder) the mesh at 5 / 10 cm was 90.9 / 66.0 % and 97.0 / 76.6 % without
        the rule, 96.7 / 40.6 % and 98.6 / 46.3 % with 10 neighbours within 5 cm,
        94.0 / 63.1 % and 97.9 / 71.8 % within 10 spacings, 92.5 / 66.1 % and 97.5 / 75.7 %
        within 15.
    mesh_carve_min_views / mesh_carve_tolerance_rel: free-space carving of the mesh
        (`postproc.dense.carving`): a vertex that at least this many depth maps saw past
        (it lies nearer than their measured depth by more than the tolerance, a fraction
        of that depth), and more maps than agree with it, is removed with its triangles
        (0 views: off). On that 10-minute dive (one-off script on the run's folder,
        accuracy / completeness at 5 cm), carving with 2 views took the mesh with 8 stray
        neighbours from 95.8 / 71.0 % to 96.9 / 70.3 % at 0.02 (0.015: 97.1 / 69.9 %;
        0.01: 97.3 / 69.0 %), and with 10 from 96.2 / 69.6 % to 97.1 / 69.0 % at 0.02; the
        stray rule alone trades far more completeness for the same accuracy (above).
    """

    max_image_size_px: int = 960
    backend: Literal["auto", "cpu", "patchmatch"] = "auto"
    image_dir: Path | None = None
    fallback_depth_range_m: tuple[float, float] = (0.3, 20.0)
    view_selection: ViewSelectionOptions = field(default_factory=ViewSelectionOptions)
    neighbours: NeighbourOptions = field(default_factory=NeighbourOptions)
    stereo: CpuStereoOptions = field(default_factory=CpuStereoOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    meshing: MeshingOptions = field(default_factory=MeshingOptions)
    colour_correction: bool = False
    colour: ColourOptions = field(default_factory=ColourOptions)
    make_mesh: bool = True
    mesh_min_images: int = 2
    mesh_single_image_neighbours: int = 0
    mesh_single_image_radius_m: float = 0.05
    mesh_single_image_min_pairs: int = 4
    mesh_single_image_near_min_pairs: int = 0
    mesh_single_image_near_range_m: float = 6.0
    mesh_stray_neighbours: int = 8
    mesh_stray_radius_m: float = 0.05
    mesh_stray_radius_spacings: float = 15.0
    mesh_carve_min_views: int = 2
    mesh_carve_tolerance_rel: float = 0.02
