"""The calibrate stage's options: view selection, intrinsics, camera-IMU and two-rig
estimates, feature rotations, and the options of each calibration (camera, imu, rig) and
of the pipeline's calibrate stage.

Light on purpose (no OpenCV here): the command line builds its flags from these classes
(postproc.pipeline.options) without importing the stage. Each class is re-exported by
the module that uses it (`postproc.calibrate.intrinsics.IntrinsicsOptions`...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from shared.calibration.aprilgrid_options import DetectionOptions

#: Camera models the intrinsics fit knows, by their names on the command line.
CameraModelName = Literal["pinhole-radtan", "pinhole-equidistant"]


@dataclass(kw_only=True)
class FrameSelectionOptions:
    """How views are chosen.

    max_frames: at most this many views go into the calibration.
    min_corners: views with fewer grid corners are skipped.
    min_relative_sharpness: views whose sharpness is below this fraction of the median
        sharpness of all candidates are skipped (motion blur).
    coverage_cells: (columns, rows) of the image grid used to measure coverage.
    angle_bin_deg: viewing angles (tilt of the board about the camera's x and y axes)
        are binned this coarsely.
    angle_weight / sharpness_weight: weights of the angle and sharpness terms of the gain.
    """

    max_frames: int = 40
    min_corners: int = 16
    min_relative_sharpness: float = 0.35
    coverage_cells: tuple[int, int] = (8, 6)
    angle_bin_deg: float = 15.0
    angle_weight: float = 6.0
    sharpness_weight: float = 0.5


@dataclass(kw_only=True)
class IntrinsicsOptions:
    """What is estimated.

    model: "pinhole-radtan" (OpenCV plumb-bob, k3 = 0) or "pinhole-equidistant" (fisheye).
    fix_principal_point: keep (cx, cy) at the image centre ((w - 1) / 2, (h - 1) / 2).
    fix_aspect_ratio: fx = fy.
    zero_distortion: estimate no distortion (all coefficients 0); for few views.
    initial_focal_px: starting focal length (pixels) for fixed-aspect fits; None: width.
    outlier_view_factor / outlier_view_min_px: views above both thresholds (RMS, pixels)
        are dropped after the first fit.
    min_views: fewer usable views than this is an error.
    """

    model: CameraModelName = "pinhole-radtan"
    fix_principal_point: bool = False
    fix_aspect_ratio: bool = False
    zero_distortion: bool = False
    initial_focal_px: float | None = None
    outlier_view_factor: float = 3.0
    outlier_view_min_px: float = 1.0
    min_views: int = 3


@dataclass(kw_only=True)
class CameraImuOptions:
    """Settings of the camera-IMU rotation and time-shift estimate.

    max_timeshift_s: the coarse search covers shifts in [-max, +max] seconds.
    correlation_step_s: grid step of the coarse cross-correlation (s).
    estimate_gyro_bias: fit a constant gyro bias (rad/s) with the rotation and shift.
    robust_scale_rad: Cauchy loss scale on the rotation residuals (rad); residuals much
        larger than this (a bad pose, a wrong feature match) hardly pull the fit.
    outlier_threshold_rad / outlier_mad_factor: after a fit, intervals whose residual
        exceeds both this and `outlier_mad_factor` robust sigmas (1.4826 * median) of the
        residuals are dropped and the fit repeated (up to `max_rounds` fits).
    integration_substeps: midpoint steps per frame interval when integrating the gyro.
    min_intervals: fewer usable frame pairs than this is an error.
    min_axis_excitation: the smallest singular value of the camera's rates over the largest
        must reach this, else the camera turned about one axis only (rotation unobservable).
    min_correlation: the |rate| cross-correlation peak must reach this, else the camera's
        rotations do not follow the gyro at all (the wrong IMU, tracking that failed) and
        no result is given. Real footage with slow turns peaks low (0.2-0.3), so this is
        a loose guard; `min_explained` is the real test.
    min_explained: the fitted model must explain at least this fraction of the camera's
        rotation power (1 - sum residual^2 / sum angle^2), else no result is given.
    """

    max_timeshift_s: float = 0.5
    correlation_step_s: float = 0.002
    estimate_gyro_bias: bool = True
    robust_scale_rad: float = 0.005
    outlier_threshold_rad: float = 0.003
    outlier_mad_factor: float = 5.0
    max_rounds: int = 4
    integration_substeps: int = 8
    min_intervals: int = 20
    min_axis_excitation: float = 0.05
    min_correlation: float = 0.2
    min_explained: float = 0.7


@dataclass(kw_only=True)
class RigSyncOptions:
    """Settings of the two-rig clock offset and rotation.

    max_offset_s: the search covers offsets within this of `prior_offset_s` (s).
    prior_offset_s: the expected clock-1-minus-clock-0 offset (s), e.g. from file times.
    coarse_step_s: grid step of the first, wide cross-correlation (s).
    fine_step_s: grid step of the second, narrow one around the first peak (s).
    smoothing_s: both gyros are averaged over windows this long before correlating (s).
    robust_scale_rad_s: Huber scale of the rate residuals in the joint fit (rad/s).
    fit_rate_hz: rate at which clock-0 times are sampled for the joint fit (Hz).
    min_overlap_s: the recordings must share at least this much motion (s).
    min_axis_excitation: smallest over largest singular value of the rates; below it
        the rigs turned about one axis only and R_10 is not observable.
    min_correlation: the |rate| cross-correlation peak must reach this, else the two
        gyros did not record the same motion (not one mount, no overlap in the range).
    """

    max_offset_s: float = 30.0
    prior_offset_s: float = 0.0
    coarse_step_s: float = 0.02
    fine_step_s: float = 0.002
    smoothing_s: float = 0.02
    robust_scale_rad_s: float = 0.05
    fit_rate_hz: float = 100.0
    min_overlap_s: float = 5.0
    min_axis_excitation: float = 0.05
    min_correlation: float = 0.5


@dataclass(kw_only=True)
class FeatureRotationOptions:
    """KLT tracking and essential-matrix settings.

    max_features: corners tracked per frame pair; min_distance_px: their spacing.
    min_inliers: fewer RANSAC inliers than this gives no rotation.
    ransac_threshold_px: inlier threshold, pixels (converted with the focal length).
    homography_inlier_ratio: a homography with at least this fraction of the essential
        matrix's inliers marks a flat scene: its decomposition gives the rotation.
    pure_rotation_px: when the homography taken as a pure rotation explains the tracks to
        this median error (pixels), the camera is taken as only turning (no parallax).
    """

    max_features: int = 400
    min_distance_px: int = 8
    min_inliers: int = 30
    ransac_threshold_px: float = 1.0
    homography_inlier_ratio: float = 0.9
    pure_rotation_px: float = 0.3


@dataclass(kw_only=True)
class CameraCalibrationOptions:
    """The camera (intrinsics) calibration.

    topic: the camera topic of a session (None: /cam0/video, or /cam0/image stills).
    max_candidate_rate_hz: frames examined for the grid per second of recording (a
        30 fps sweep holds mostly near-duplicates; detection is the slow part; 0: every
        frame).
    min_tags: frames with fewer tags of the target are not used.
    coverage_cells: (columns, rows) of the coverage measure and plot.
    """

    topic: str | None = None
    max_candidate_rate_hz: float = 4.0
    min_tags: int = 4
    coverage_cells: tuple[int, int] = (8, 6)
    selection: FrameSelectionOptions = field(default_factory=FrameSelectionOptions)
    intrinsics: IntrinsicsOptions = field(default_factory=IntrinsicsOptions)
    detection: DetectionOptions = field(default_factory=DetectionOptions)


@dataclass(kw_only=True)
class ImuCalibrationOptions:
    """The camera-IMU rotation and time shift.

    camera_index: which camera of the input camchain (0 = cam0).
    topic: the camera topic of a session (None: the camchain's topic when it names a
        session topic, else /cam0/video).
    imu_topic: the IMU topic of a session.
    use_features: where the grid is not seen in both frames of a pair, use tracked
        features (essential matrix) for the rotation; else skip the pair.
    frame_stride: use every Nth frame (pairs N frames apart): faster on long, high-rate
        videos; the rotation between frames grows, which features tolerate up to a point.
    max_frame_gap_s: pairs of used frames further apart than this are not used (dropped
        frames); scaled by `frame_stride`.
    min_tags: grid detections with fewer tags are not used for a pose.
    """

    camera_index: int = 0
    topic: str | None = None
    imu_topic: str = "/imu0"
    use_features: bool = True
    frame_stride: int = 1
    max_frame_gap_s: float = 0.1
    min_tags: int = 4
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    features: FeatureRotationOptions = field(default_factory=FeatureRotationOptions)
    estimate: CameraImuOptions = field(default_factory=CameraImuOptions)


@dataclass(kw_only=True)
class RigCalibrationOptions:
    """Two rigs (camera + own IMU each) on one mount.

    imu_topic0 / imu_topic1: the IMU topic in each recording (the same session may hold
        both, e.g. /imu0 and /imu1).
    sync: the clock offset and rotation estimate (RigSyncOptions).
    """

    imu_topic0: str = "/imu0"
    imu_topic1: str = "/imu0"
    sync: RigSyncOptions = field(default_factory=RigSyncOptions)


@dataclass(kw_only=True)
class CalibrateOptions:
    """Options of the pipeline's calibrate stage (`calibration.recording` in a project).

    camera: intrinsics from the AprilGrid views (CameraCalibrationOptions).
    imu: camera-IMU rotation and time shift (ImuCalibrationOptions).
    estimate_imu: also estimate the camera-IMU rotation and time shift (else the
        camera-only camchain is used).
    """

    camera: CameraCalibrationOptions = field(default_factory=CameraCalibrationOptions)
    imu: ImuCalibrationOptions = field(default_factory=ImuCalibrationOptions)
    estimate_imu: bool = True
