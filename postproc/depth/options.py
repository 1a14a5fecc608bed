"""The depth stage's options (`DepthOptions`).

Light on purpose (no NumPy or SciPy here): the command line builds its flags from this
class (postproc.pipeline.options) without importing the stage, which re-exports it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

# Standard deviation of a uniform quantisation error of a 0.1 m depth resolution.
QUANTISATION_SIGMA_M = 0.1 / math.sqrt(12.0)


@dataclass(kw_only=True)
class DepthOptions:
    """Options of the depth stage (units in the names).

    method: "ours" (coarse search then robust Gauss-Newton) or "paper" (the
        paper's 100 Hz cross-correlation and linear regression).
    max_offset_s: largest |dive-computer minus camera| clock offset searched,
        seconds (default 15 h: local wall-clock zones reach +-14 h).
    time_offset_s: the offset when known (dive minus camera at the trajectory's
        first stamp, seconds): the search is skipped and the offset (and a
        zero drift) kept; for a flat profile or a dive that cannot be matched.
    estimate_drift: estimate the dive computer's clock drift (ppm).
    drift_prior_sigma_ppm: zero-mean prior on the drift (one sigma, ppm);
        one dive constrains drift only weakly.
    estimate_scale: estimate depth_scale; otherwise it stays 1 and the
        scale the data would give is reported as `depth_scale_free`.
    fuse: re-optimise the trajectory with depth factors (GTSAM).
    depth_sigma_m: one-sigma error of a depth sample as the depth of the
        trajectory frame (0.1 m resolution, wrist-camera lever arm, waves), m.
    odometry_sigma_m_per_sqrt_s: VIO position drift for the fusion, m/sqrt(s);
        the sync fits a steady z drift under this random walk's prior too.
    odometry_sigma_rad_per_sqrt_s: VIO rotation drift for the fusion, rad/sqrt(s).
    node_interval_s: shortest time between optimised poses in the fusion, s.
    search_step_s: grid step of the coarse offset search, s.
    min_overlap_fraction: share of the possible dive samples that must fall in
        the trajectory for an offset to count.
    max_gap_s: trajectory gaps longer than this (tracking lost) hold no depth, s.
    min_depth_range_m: the overlapping profile must span at least this
        (5-95 percentile), m; 0: no such gate (the default: a profile too flat
        to give a clock offset is refused when the trajectory explains the
        depths no better than a constant depth, by min_evidence).
    max_time_sigma_s: a clock offset less certain than this is refused, s.
    min_evidence: a clearly different offset (or another dive) must fit worse
        than the answer by this much (samples x mean Huber cost difference, a
        log-likelihood ratio for Gaussian noise), or the offset is ambiguous.
    min_overlap_samples: fewer dive samples inside the trajectory make the
        offset ambiguous.
    clock_prior_window_s: the camera's and the dive computer's wall clocks are
        taken to agree within this many seconds, apart from whole time-zone
        steps; used only when the search alone is ambiguous, and only when the
        trajectory's stamps and the dive's are wall-clock dates. None: no prior.
    clock_prior_zone_step_s: time-zone step between the two clocks, s (900:
        any zone difference, quarter hours included; 0: same zone).
    plot: write depth_sync.png.
    trajectory_format: how the trajectory's stamps are spelled: "tum" (decimal
        seconds), "svin" (SVIn2: seconds, '.', unpadded nanoseconds) or "auto"
        (decided per file; see `shared.formats.svin`).

    An ambiguous offset (sync.json's `offset_ambiguity`) is refused with a
    StageError naming the dive and the competing offsets, rather than written
    out: a wrong offset puts the whole dive metres off its true depth.
    """

    method: Literal["ours", "paper"] = "ours"
    max_offset_s: float = 15.0 * 3600.0
    time_offset_s: float | None = None
    estimate_drift: bool = True
    drift_prior_sigma_ppm: float = 50.0
    estimate_scale: bool = False
    fuse: bool = True
    depth_sigma_m: float = math.hypot(QUANTISATION_SIGMA_M, 0.05)
    odometry_sigma_m_per_sqrt_s: float = 0.01
    odometry_sigma_rad_per_sqrt_s: float = 0.001
    node_interval_s: float = 1.0
    search_step_s: float = 1.0
    min_overlap_fraction: float = 0.5
    max_gap_s: float = 5.0
    min_depth_range_m: float = 0.0
    max_time_sigma_s: float = 5.0
    min_evidence: float = 6.0
    min_overlap_samples: int = 4
    clock_prior_window_s: float | None = 300.0
    clock_prior_zone_step_s: float = 900.0
    plot: bool = True
    # The formats of shared.formats.svin.read_trajectory (spelled here: that module
    # imports NumPy; a test checks the two agree).
    trajectory_format: Literal["auto", "tum", "svin"] = "auto"
