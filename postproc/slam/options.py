"""The SLAM stage's options: every setting of the frontend, keyframe rule, loop
closure, smoother, estimator and gyro check, and `SlamOptions` that holds them.

Light on purpose (no OpenCV, GTSAM or NumPy here): the command line builds its flags
from these classes (postproc.pipeline.options) without importing the stage. Each class
is re-exported by the module that uses it (`postproc.slam.frontend.FrontendOptions`...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

GRAVITY_M_S2 = 9.81


@dataclass(kw_only=True)
class FrontendOptions:
    """Frontend settings (pixels are frontend-image pixels unless said otherwise).

    width_px: wider images are shrunk to this width (height keeps the aspect); 0 or
        a larger value keeps the recorded size.
    clahe: contrast-limited histogram equalisation; clahe_clip_limit, clahe_tiles.
    max_features: features kept per frame (SVIn2 GoPro: 400).
    grid_cols / grid_rows: detection grid; each cell gets an equal share.
    min_distance_px: minimum spacing of features.
    quality_level: Shi-Tomasi quality relative to the best corner of the cell.
    klt_window_px / klt_levels: Lucas-Kanade window size where the gyro seeds the flow,
        and pyramid levels.
    klt_window_unseeded_px: the window when no gyro rotation seeds the flow (the
        visual-only and stabilised-video paths, the rotation probe). The KLT's cost is
        per feature and per window pixel, not per image pixel (a 480 or 640 px frontend
        left the tracking thread's CPU as it was), and a seeded flow starts within a
        pixel or two of its answer, so the seeded window is 11 px and the unseeded one
        keeps 15: at 11 px the unseeded EuRoC MH_01 run posed 332 of 600 frames
        (1.63 % of the path from the Leica) against 468 (0.91 %) at 15. Seeded at 11 px,
        on 60 s of rendered 960x540, 30 fps video over four draws of the tracks (bias
        lags 8-60), the ATE means were 4.20 / 5.55 mm (PNG / H.264) against 4.65 /
        7.26 mm at 15, and the tracking thread's CPU fell by a third; the Karma clip
        was within 0.57-0.62 % of its path of the drone's log over five lags (1.76-1.80 %
        at 15) (docs/benchmarks.md, SLAM, stop 51).
    klt_iterations / klt_epsilon_px: Lucas-Kanade stops after this many iterations per
        level or once a step is shorter than this (pixels).
        The KLT was most of the tracking thread's CPU. 10 iterations and 0.03 px
        (against 30 and 0.01), with replenish_missing 20 (against 1), cut the tracking
        thread from 28.3-33.0 to 20.5-21.7 s of CPU on 40 s of 960x540, 30 fps video
        (bench_slam --speed, two back-to-back pairs, load about 1.5 on 2 cores; ATE 9.5
        -> 8.8 mm). On the demo's 10 fps dives the ATE (11.9 and 21.0 mm) stayed within
        the spread of runs whose gyro seeds differed by a hair (8.0-14.5 and 17.2-32.6
        mm: which tracks survive, and so the ATE, is that sensitive). A 13 px window
        (with 2 or 3 levels) was cheaper still and as accurate on rendered video, but
        the unseeded visual-only EuRoC MH_01 run and the Karma drone clip then failed
        (that was before the window depended on the seeding: `klt_window_unseeded_px`).
    klt_check_levels: pyramid levels of the backward (checking) pass, at most
        `klt_levels`. Fewer are cheaper (0 cut the tracking thread by a third on 40 s
        of rendered 960x540 video, frame-to-frame errors against the render's truth
        unchanged), but the full pyramid is a stronger check on real video: with 0 the
        visual-only EuRoC MH_01 run failed, with 1 or 2 the Karma clip kept 52-94
        landmarks (200 with 3) and with 2 a 10.6 m path (51.4 m with 3).
    max_forward_backward_px: forward-backward consistency bound.
    ransac_threshold_px: epipolar distance bound of the essential-matrix RANSAC.
    border_px: features closer than this to the image border are dropped.
    replenish_missing: new corners are searched for only once at least this many of
        the `max_features` are missing (1: after every lost feature; a few tracks are
        lost in most frames, and the search was a fifth of the tracking thread's time).
    weak_quality_factor / weak_fill_below: when a frame ends up with fewer than
        `weak_fill_below` features, the grid cells short of their share are searched
        again at `quality_level * weak_quality_factor` (1: never). Only then: in a
        textured image weak corners track worse than the strong ones they would join
        (the visual-only path on EuRoC MH_01 failed with them everywhere).
    drought_min_tracks / drought_max_s / anchor_min_tracks: below `drought_min_tracks`
        surviving tracks the frontend re-tracks the anchor (the last frame that kept at
        least `anchor_min_tracks`) if it is at most `drought_max_s` old.
    """

    width_px: int = 960
    clahe: bool = True
    clahe_clip_limit: float = 2.0
    clahe_tiles: int = 8
    max_features: int = 400
    grid_cols: int = 8
    grid_rows: int = 5
    min_distance_px: int = 12
    quality_level: float = 0.01
    klt_window_px: int = 11
    klt_window_unseeded_px: int = 15
    klt_levels: int = 3
    klt_iterations: int = 10
    klt_epsilon_px: float = 0.03
    klt_check_levels: int = 3
    max_forward_backward_px: float = 1.0
    ransac_threshold_px: float = 1.0
    border_px: int = 4
    replenish_missing: int = 20
    weak_quality_factor: float = 0.1
    weak_fill_below: int = 200
    drought_min_tracks: int = 40
    drought_max_s: float = 2.0
    anchor_min_tracks: int = 80


@dataclass(kw_only=True)
class KeyframeOptions:
    """Thresholds of the keyframe rule.

    overlap_threshold: new keyframe when the hull overlap falls to or below this (0..1).
    match_ratio_threshold: new keyframe when the shared share falls to or below this (0..1).
    min_interval_s / max_interval_s: bounds on the time between keyframes (seconds); the
        0.5 s ceiling keeps at least 2 keyframes a second (SVIn2 ran at 1.6-3.4 Hz), which
        halved the drift on the simulated surveys.
    min_tracks: below this many features a frame becomes a keyframe as soon as allowed
        (the scene is about to be lost).
    """

    overlap_threshold: float = 0.6
    match_ratio_threshold: float = 0.2
    min_interval_s: float = 0.2
    max_interval_s: float = 0.5
    min_tracks: int = 30


@dataclass(kw_only=True)
class LoopClosureOptions:
    """Loop detection settings.

    enabled: look for loops at all.
    max_distance_m / max_yaw_deg: geometric gate on the current estimates (SVIn2: 6 m, 30 deg).
    min_time_gap_s: candidates must be at least this much older (no loop with the recent past).
    max_candidates: nearest gated candidates verified per keyframe.
    min_keyframes_between_loops: after a loop, skip this many keyframes (the next ones
        would close the same loop again and only cost optimisation time).
    ratio_test: Lowe's ratio for descriptor matches; max_hamming: absolute bound (bits).
    min_inliers: PnP RANSAC inliers needed (SVIn2: 25).
    pnp_reprojection_px: RANSAC threshold (frontend pixels).
    rotation_sigma_rad / translation_sigma_m: uncertainty of a loop constraint.
    cauchy_k: Cauchy loss scale (whitened units): a wrong loop must not wreck the map.
    """

    enabled: bool = True
    max_distance_m: float = 6.0
    max_yaw_deg: float = 30.0
    min_time_gap_s: float = 15.0
    max_candidates: int = 3
    min_keyframes_between_loops: int = 5
    ratio_test: float = 0.8
    max_hamming: int = 64
    min_inliers: int = 25
    pnp_reprojection_px: float = 3.0
    rotation_sigma_rad: float = 0.02
    translation_sigma_m: float = 0.05
    cauchy_k: float = 1.0


@dataclass(kw_only=True)
class BackendOptions:
    """Settings of the smoother (units in the names).

    pixel_sigma_px: standard deviation of a tracked feature position (frontend pixels).
    huber_k: Huber threshold in standard deviations (robust to leftover outliers).
    min_parallax_deg: smallest angle between a landmark's extreme rays to add it.
    min_observations: keyframes that must see a track before it becomes a landmark.
    max_landmarks_per_keyframe: at most this many landmarks get factors at a keyframe's
        update: those it observes, then new ones (0: no limit). When more tracks are
        ready to become landmarks than the budget leaves, the longest-seen go first and
        the others wait (still tracked, their observations kept) for a keyframe with
        room. ISAM2's re-elimination grows with the landmarks a keyframe touches, and
        the rendered wreck gives 250-320 a keyframe: at 200 the estimator's CPU fell
        from 10.3-10.9 to 6.6-7.3 s a minute of 960x540 video (bench_slam --speed,
        2.97-3.31x real time against 2.78-2.91x), the ATE over five draws of the tracks
        4.80 / 6.06 mm against 4.70 / 5.38 (PNG / H.264), on bench_slam's two rendered
        sessions 4.46 / 28.9 against 3.96 / 26.6 mm: about a tenth, inside the draws'
        spread (0 gives it back). The real recordings mostly see fewer (the Karma clip
        at most 59, the hand-held clip 60 in the median); where 100-200 cut the
        hand-held clip's richest keyframes its error held, and only 50, below its
        median, changed its scale (docs/benchmarks.md, SLAM, stop 53). VINS-Mono's
        default tracks 150 features.
    max_reprojection_px: triangulation check (frontend pixels).
    max_gate_px: a new observation of a landmark farther than this from its predicted
        projection (frontend pixels) is dropped.
    min_depth_m / max_depth_m: accepted landmark depth in front of each camera.
    imu_noise_inflation: multiplies the Kalibr noise densities and random walks
        (datasheet values are optimistic on a vibrating, warming diver rig).
    min_gyroscope_random_walk / min_accelerometer_random_walk: floors on the bias random
        walks (rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz)) after inflation. A gyro walk far below
        the bias prior makes the bias-to-bias term of every IMU factor 1e7-1e8 times
        stiffer than the prior, and Cholesky then declares the very first update
        indeterminate (a RealSense's Kalibr file says 2.6e-6: ISAM2 failed at keyframe 1,
        "Symbol: b0"). The floors sit at the best MEMS parts' values (EuRoC's ADIS16448:
        1.9e-5 and 3e-3), below the simulator's 2e-5 and 3e-4, so calibrated consumer
        IMUs are left as they are.
    prior_tilt_sigma_rad: first keyframe roll/pitch uncertainty (gravity from a mean
        accelerometer reading); yaw and position are fixed (they define S).
    prior_velocity_sigma_m_s: first keyframe velocity around zero (diver speeds < 1 m/s).
    weak_velocity_sigma_m_s: a prior around zero on every later keyframe's velocity,
        so that no state is ever without a prior of its own (0: none); at 10 m/s its
        information is a ten-millionth of what one IMU factor gives.
    prior_accel_bias_sigma_m_s2 / prior_gyro_bias_sigma_rad_s: initial bias uncertainty.
    zero_velocity_sigma_m_s: strength of the zero-velocity constraint while still.
    landmark_prior_sigma_m: a weak prior on each new landmark at its triangulated
        position (0: none). Without it a landmark whose observations the Huber loss
        down-weights, or whose rays are nearly parallel, can make the Cholesky
        factorisation fail ("indeterminant system") and end the run; at 10 m its
        information is under 1 % of what two 2-degree-parallax rays give at 10 m depth.
    relinearize_threshold: ISAM2 relinearisation threshold (tangent-space units).
    extra_iterations: additional ISAM2 updates after each keyframe.
    factorization: ISAM2's "QR" (slower, survives the poor conditioning of long
        IMU-only stretches, whose tiny bias random walks Cholesky rejects) or "CHOLESKY".
        When a Cholesky update stays indeterminate after the rebuild, the smoother is
        rebuilt once more with QR and keeps QR from then on (`stats.qr_fallbacks`).
    final_batch: refine the window's graph with Levenberg-Marquardt at the end.
    final_batch_relative_tolerance: the refinement stops once an iteration lowers the
        error by less than this share. On 60 s of rendered 960x540 video (120 keyframes,
        47,905 factors, 0.22-0.27 s an iteration) the error fell 20320 -> 14500 -> 14365
        -> 14335 -> 14325 and then by under 0.03 % an iteration: GTSAM's default, 1e-5,
        took 9 iterations (2.0-2.5 s, alone on one core at the end of the run).
    final_batch_max_iterations: its cap.
    window_keyframes: keyframes kept in the smoother after a retirement (0: keep all,
        full smoothing, memory grows with the dive). ISAM2 takes about 5 MB per
        keyframe of the window (measured, 80 features a frame): 150 (+100 step) held
        a 45-minute dive at +1.3 GB, flat, with 4.3 cm ATE over 878 m.
    window_step_keyframes: keyframes retired at once (rebuilding ISAM2 costs one batch
        elimination of the window, so it is done in steps, not per keyframe).
    anchor_*: priors on the first kept keyframe's pose, velocity and biases after a
        retirement (they stand for the retired part of the dive).
    max_landmark_drops: a recovery that finds one more ill-posed landmark drops it too,
        up to this many times, before it falls back to QR.
    recovery_*: weak priors put on the keyframe states GTSAM names when an ISAM2
        update finds the system indeterminate (see `_update_or_recover`); weak enough
        not to pull a well-constrained state, they only fill an unconstrained direction.
    pose_graph_rotation_sigma_rad / pose_graph_translation_sigma_m: uncertainty of the
        relative pose between consecutive keyframes in the global pose graph.
    gravity_m_s2: magnitude of gravity.
    """

    pixel_sigma_px: float = 1.0
    huber_k: float = 2.0
    min_parallax_deg: float = 2.0
    min_observations: int = 3
    max_landmarks_per_keyframe: int = 200
    max_reprojection_px: float = 4.0
    max_gate_px: float = 15.0
    min_depth_m: float = 0.2
    max_depth_m: float = 40.0
    imu_noise_inflation: float = 1.0
    min_gyroscope_random_walk: float = 1.0e-5
    min_accelerometer_random_walk: float = 1.0e-4
    prior_tilt_sigma_rad: float = 0.03
    prior_velocity_sigma_m_s: float = 0.5
    weak_velocity_sigma_m_s: float = 10.0
    prior_accel_bias_sigma_m_s2: float = 0.1
    prior_gyro_bias_sigma_rad_s: float = 0.01
    zero_velocity_sigma_m_s: float = 0.005
    landmark_prior_sigma_m: float = 10.0
    relinearize_threshold: float = 0.1
    extra_iterations: int = 0
    factorization: Literal["QR", "CHOLESKY"] = "CHOLESKY"
    final_batch: bool = True
    final_batch_relative_tolerance: float = 1e-3
    final_batch_max_iterations: int = 30
    window_keyframes: int = 150
    window_step_keyframes: int = 100
    anchor_rotation_sigma_rad: float = 0.002
    anchor_position_sigma_m: float = 0.005
    anchor_velocity_sigma_m_s: float = 0.02
    anchor_accel_bias_sigma_m_s2: float = 0.02
    anchor_gyro_bias_sigma_rad_s: float = 0.001
    recovery_rotation_sigma_rad: float = 0.1
    max_landmark_drops: int = 5
    recovery_position_sigma_m: float = 1.0
    recovery_velocity_sigma_m_s: float = 0.5
    pose_graph_rotation_sigma_rad: float = 0.003
    pose_graph_translation_sigma_m: float = 0.01
    gravity_m_s2: float = GRAVITY_M_S2


@dataclass(kw_only=True)
class EstimatorOptions:
    """How frames become keyframes and states.

    keyframes / backend / loop_closure: see KeyframeOptions, BackendOptions,
        LoopClosureOptions.
    gravity_window_s: accelerometer averaging window after the first keyframe (s; cut
        to the IMU data), each sample turned into the first keyframe's frame by the gyro.
        Long, because a start is not always at rest: the Karma drone sample accelerates
        at 2-3 m/s^2 for its first 5 s, which tilts a 1 s mean by 11-16 degrees (and the
        0.03 rad tilt prior then holds that error); over 10 s the tilt left is
        Delta-v / (g T), 4 degrees there, and the smoother takes it out. Simulated
        dives (bench_slam, 30 s): feature-level ATE 0.8 / 2.7 / 9.6 mm with 1 s, 0.8 /
        2.4 / 9.5 mm with 10 s; rendered 3.7 mm vs 4.1 mm (max error 10.2 vs 8.6 mm).
    gravity_tolerance_m_s2: a start whose mean specific force differs from gravity by
        more than this is refused and retried at the next keyframe (an accelerometer
        still waking up, or one logging in g): over the gravity window a moving body's
        mean departs from g by its change of velocity over the window, well under this.
    init_min_keyframes: keyframes buffered before the visual-inertial alignment is tried.
    init_min_parallax_deg: median ray angle to the first keyframe needed to try it.
    init_min_condition: smallest accepted conditioning of the alignment (scale observable).
    init_max_accel_bias_m_s2: largest accelerometer bias an accepted alignment may solve
        for. Consumer MEMS accelerometers are specified to tens of milli-g of offset
        (0.2-0.5 m/s^2, temperature included); an alignment that needs more is explaining
        something else with the bias (a gravity direction tilted by the start's own
        acceleration, far scenes with little parallax) and is refused: the start waits
        for a better one, or `init_max_s`. The Karma drone sample (accelerating at
        2-3 m/s^2, 16 m up) gave alignments at 0.8-1.3 m/s^2 with distances from the
        first keyframe that shrank and grew again; one at 1.18 m/s^2 (condition 0.009)
        was accepted and the estimate diverged (10.2 m/s between keyframes).
    init_max_s: after this long without a good alignment, start from rest (v = 0): a
        hovering diver never gives scale, and waiting forever would lose the start.
    rest_window_s: length of the IMU windows that `initialization.imu_stillness`
        judges around the first keyframe. When the body rests there and the next
        keyframe's images agree (no derotated flow: the IMU alone cannot tell rest from a
        glide at constant velocity), the backend starts at rest: gravity, the gyro bias
        and the accelerometer bias along gravity from the still IMU, zero velocity held
        to `rest_velocity_sigma_m_s`. A start in motion waits for the alignment instead.
    rest_max_gyro_std_rad_s / rest_max_accel_std_m_s2: the spread of the IMU samples
        below which the body counts as resting (see `imu_stillness`).
    segment_join_rotation_sigma_rad / segment_join_translation_sigma_m: how loosely the
        final pose graph holds the IMU-predicted step from one map segment to the next
        when a loop closes between segments.
    rest_lookback_s: a rest that ended up to this long before the first keyframe (a
        recording that starts at rest, the camera's first frame coming later) still
        starts the estimate: the IMU carries the rest's attitude and zero velocity to the
        first keyframe, the velocity sigma growing by `rest_velocity_growth_m_s2` per
        second (a 0.01 rad tilt error is 0.1 m/s^2; an accelerometer bias as much).
    still_max_flow_px: median feature motion (frontend pixels) between keyframes, with
        the gyro-predicted rotation removed, below which the camera counts as not
        translating (zero-velocity update).
    timeshift_cam_imu_s: Kalibr's camera-to-IMU time shift (t_imu = t_cam + shift).
    blind_keyframe_interval_s: while frames carry no tracks (open water, the camera
        blocked), at most one keyframe per this many seconds (0: no limit). Blind
        keyframes hold nothing but IMU; at the selector's rate (up to 5 per second,
        "few tracks") their chain of short, stiff IMU factors left the smoother's
        system so ill-conditioned (position drift ~12 m against 1e10 bias-walk
        information) that ISAM2's Cholesky failed after about 20 s blind (issue #7).
        One long IMU factor per interval carries the same information, well scaled.
    """

    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    backend: BackendOptions = field(default_factory=BackendOptions)
    loop_closure: LoopClosureOptions = field(default_factory=LoopClosureOptions)
    gravity_window_s: float = 10.0
    gravity_tolerance_m_s2: float = 3.0
    still_max_flow_px: float = 1.5
    timeshift_cam_imu_s: float = 0.0
    init_min_keyframes: int = 4
    init_min_parallax_deg: float = 2.0
    init_min_condition: float = 1e-3
    init_max_accel_bias_m_s2: float = 0.8
    init_max_s: float = 5.0
    rest_window_s: float = 0.5
    rest_max_gyro_std_rad_s: float = 0.01
    rest_max_accel_std_m_s2: float = 0.1
    rest_velocity_sigma_m_s: float = 0.02
    segment_join_rotation_sigma_rad: float = 0.05
    segment_join_translation_sigma_m: float = 0.5
    rest_lookback_s: float = 2.0
    rest_velocity_growth_m_s2: float = 0.2
    blind_keyframe_interval_s: float = 5.0


@dataclass(kw_only=True)
class GyroCheckOptions:
    """Settings of the gyro / image rotation comparison.

    probe_s: seconds of video tracked for the check before the main pass (the check
        runs only when the calibration is a guess, see `SlamOptions.gyro_check`).
    max_shift_s: time offsets searched, +-seconds (t_imu = t_cam + shift).
    shift_step_s: resolution of the offset search.
    min_rotation_px: pairs whose gyro rotation moves the image centre by at least this
        many pixels (at the guessed focal) take part in the gain and rigidity fits.
    still_rotation_px: pairs whose gyro rotation stays below this many pixels bound
        the images' rotation noise (`visual_noise_px`, with the second differences).
    min_pairs: fewer turning pairs: too little rotation to say anything ("unknown").
    strong_min_pairs: turning pairs needed before the video may be declared "not rigid".
    focal_scale_range: accepted focal corrections (outside: not a rigid camera-IMU pair).
    max_unexplained: above this share of unexplained gyro rotation the camera does not
        turn with the IMU (stabilised video, or a wrong axis convention).
    max_gain_relative_error: a "rigid" gain must be known to this fraction of itself.
    min_correlation: a "rigid" verdict needs the angular speeds correlated this well.
    min_gain_sigmas: standard errors by which a gain must clear zero (images follow the
        body) and miss the accepted range before "not rigid" is declared.
    max_noise_fraction: "not rigid" needs the images' rotation noise bound below
        this fraction of the gyro's median turn on the turning pairs.
    """

    probe_s: float = 20.0
    max_shift_s: float = 0.15
    shift_step_s: float = 0.002
    min_rotation_px: float = 4.0
    still_rotation_px: float = 1.0
    min_pairs: int = 5
    strong_min_pairs: int = 20
    focal_scale_range: tuple[float, float] = (0.6, 1.7)
    max_unexplained: float = 0.5
    max_gain_relative_error: float = 0.1
    min_correlation: float = 0.7
    min_gain_sigmas: float = 3.0
    max_noise_fraction: float = 0.5


@dataclass(kw_only=True)
class SlamOptions:
    """Everything the SLAM stage can be told.

    frontend / estimator: see FrontendOptions, EstimatorOptions (keyframe rule and
        backend inside).
    use_imu: use the IMU; without it the visual-only baseline runs
        (postproc.slam.visual_only): arbitrary scale, S = first keyframe's body frame
        (not gravity-aligned), no loop closure.
    max_frames: stop after this many images used (None: all); for quick looks and tests.
    max_rate_hz: use at most this many images per second of the recording (the others
        are not read where the recording allows it, and a video decodes them, for the
        frames after them, but does not convert them); None: every image. For the quick
        look (`wreckmap-post run --quick`): at 10 Hz a 30 fps dive costs a third of the
        tracking and keyframe checks.
    min_rate_hz: a recording at k or more times this rate (k whole) gives every k-th
        image (its rate: the mean step of its first 16 stamps, 2 % tolerance); None:
        every image. At 15: a 30 fps (or 29.97) video every other image, 60 fps every
        fourth; EuRoC's 20 Hz, a 24 fps video or a camera at 19 fps every image. Off
        by default: faster, a little less accurate. At 15, bench_pipeline.py's
        10-minute 960x540 dive: SLAM 181 s against 250 s (3.3x real time), ATE 1.7
        against 1.5 cm, SfM 1.0 against 0.9 cm, mesh at 5 cm 97.3 / 55.9 % against
        97.2 / 58.4 %; bench_slam.py --speed (60 s): 3.85 / 4.38x against 2.40 / 2.78x
        real time from PNG / H.264, ATE 6.9 / 14.5 mm against 5.2 / 11.5 mm. The ATE
        loss is not a draw: over four draws of the tracks (bias lags 8-60) it was 1.16x /
        1.27x every image's in the mean and worse in all eight pairs, and not for its
        fewer keyframes: with more than every image's it was no better (docs/benchmarks.md,
        SLAM, stop 50).
    min_tracks_ok: a frame with fewer tracked features counts as a tracking failure.
    max_speed_m_s: a keyframe-to-keyframe speed above this (m/s) means the estimate has
        diverged (too few landmarks to hold the IMU integration: scenes beyond
        `max_depth_m`, a wrong calibration guess); the stage then raises StageError
        instead of handing a wrong trajectory to depth fusion and SfM. A diver swims
        below 1 m/s and a scooter reaches about 2.5 m/s; None turns the check off
        (not applied to the visual-only baseline, whose scale is arbitrary).
    gyro_check: compare the images' frame-to-frame rotation with the gyro over the first
        `gyro_check_options.probe_s` seconds before the main pass
        (postproc.slam.gyro_check). "auto": only when the input says its calibration is
        a guess (GoPro import without --calib); "on"; "off". When the images turn
        with the gyro, the measured time shift and focal scale replace the guessed
        ones (written to calib/camchain.yaml); when they do not (a stabilised video),
        the path comes from the visual-only estimator, put in a gravity-aligned frame,
        metric when the IMU can weigh it, by postproc.slam.stabilised; stats.json
        says which ("gyro_check", "mode", "metric_scale"). An explicit `camchain`
        turns "auto" off.
    keyframe_images: write each keyframe's image into `keyframes/` (SfM, dense and the
        natural-feature merge read them). The quick look turns it off: its page draws
        none, and encoding them as PNG took 13.4 s of CPU in the frontend's process for
        the 628 keyframes of its 10-minute run (bench_pipeline.py, profiled). Without
        them SfM refuses the folder (keyframe images missing).
    estimator_process: run the estimator (keyframe rule, smoother, loop closure) in a
        second process ("on"), in the frontend's ("off"), or "auto": a second process
        from 300 images on, with at least two cores and one of them idle (the cores busy
        over half a second at the start, from the kernel's CPU counters, at most the
        cores less one; postproc.slam.estimator_process). Sharing a
        process, the estimator and the frontend's threads take turns for Python's GIL;
        apart they run side by side. The result is the same to the bit (trajectory.tum
        of bench_slam --speed, handheld_a, MH01, karma); only the speed differs. 40 s of
        960x540, 30 fps video (bench_slam --speed, runs alternated): on idle cores apart
        took 19.1-19.7 s from PNG and 19.8-24.0 s from H.264 against 21.2-28.4 and
        20.4-27.0 s in-process; on cores busy with other jobs (load 4-11) apart was the
        slower, 54.0 against 50.5 s (PNG) and 49.8 against 44.2 s (H.264), medians of 9
        and 5 runs: it costs about 3 CPU s more, and busy cores leave nothing to overlap.
    """

    frontend: FrontendOptions = field(default_factory=FrontendOptions)
    estimator: EstimatorOptions = field(default_factory=EstimatorOptions)
    use_imu: bool = True
    max_frames: int | None = None
    max_rate_hz: float | None = None
    min_rate_hz: float | None = None
    min_tracks_ok: int = 30
    max_speed_m_s: float | None = 10.0
    gyro_check: Literal["auto", "on", "off"] = "auto"
    gyro_check_options: GyroCheckOptions = field(default_factory=GyroCheckOptions)
    keyframe_images: bool = True
    estimator_process: Literal["auto", "on", "off"] = "auto"
