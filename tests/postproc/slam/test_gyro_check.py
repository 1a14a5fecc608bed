"""Gyro vs image rotation: time shift, focal scale and the stabilisation verdict.

Synthetic cases with known truth: a rigid camera (shift and focal scale come
back), a stabilised video (images that turn less and later: "not rigid" with
the evidence that says so), and the cases where the data cannot decide
(too little rotation, images unrelated to the gyro, too few turning pairs,
noisy images), which must stay "unknown" so that the IMU is kept.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from postproc.slam.gyro_check import (
    GyroCheck,
    GyroCheckOptions,
    check_gyro_against_images,
    visual_rotation,
)
from postproc.slam.types import ImuSamples
from shared.geometry import so3_exp, so3_log
from sim.features import DiverMotion, Sinusoids

START_NS = DiverMotion().start_ns
FOCAL_PX = 400.0


def _turning_motion(amplitude_rad: float = 0.4) -> DiverMotion:
    """A camera panning and tilting back and forth (about 1 rad/s at the peaks)."""
    return DiverMotion(
        yaw=Sinusoids(amplitudes=(amplitude_rad,), frequencies_rad_s=(2.1,), phases_rad=(0.0,)),
        pitch=Sinusoids(amplitudes=(0.15,), frequencies_rad_s=(3.3,), phases_rad=(0.4,)),
    )


def _imu(motion: DiverMotion, duration_s: float = 6.0) -> ImuSamples:
    stamps = START_NS + np.arange(-40, round(duration_s * 200) + 40, dtype=np.int64) * 5_000_000
    gyro = motion.angular_rate_body_rad_s(stamps)
    return ImuSamples(stamps, gyro, np.tile([0.0, 0.0, 9.81], (len(stamps), 1)))


def _frame_pairs(duration_s: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    frames = START_NS + np.arange(0, round(duration_s * 30), dtype=np.int64) * 33_333_333
    return frames[:-1], frames[1:]


def _visual(
    motion: DiverMotion,
    starts: np.ndarray,
    ends: np.ndarray,
    *,
    shift_s: float,
    gain: float,
    noise_px: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """`R_Cnow_Cprev` the images would give (C = B): the body rotation at t_cam + shift,
    its angle multiplied by `gain` (what a focal guess `1 / gain` too short does), plus
    `noise_px` of isotropic rotation noise (pixels at FOCAL_PX, per axis)."""
    rng = np.random.default_rng(seed)
    shift_ns = round(shift_s * 1e9)
    prev = motion.world_from_body(starts + shift_ns)[:, :3, :3]
    now = motion.world_from_body(ends + shift_ns)[:, :3, :3]
    out = []
    for R_W_prev, R_W_now in zip(prev, now, strict=True):
        R_prev_now = R_W_prev.T @ R_W_now
        noise = rng.normal(0.0, noise_px / FOCAL_PX, 3)
        out.append(so3_exp(gain * so3_log(R_prev_now) + noise).T)
    return np.array(out)


def _check(
    visual: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    imu: ImuSamples,
    options: GyroCheckOptions | None = None,
) -> GyroCheck:
    return check_gyro_against_images(
        starts_ns=starts,
        ends_ns=ends,
        visual_now_from_prev=visual,
        imu=imu,
        imu_from_cam_rotation=np.eye(3),
        focal_px=FOCAL_PX,
        options=options or GyroCheckOptions(),
    )


def _strict_json(check: GyroCheck) -> dict[str, object]:
    """stats.json must stay valid JSON: no NaN or infinity anywhere."""
    parsed: dict[str, object] = json.loads(json.dumps(check.as_stats(), allow_nan=False))
    return parsed


def test_a_rigid_camera_gives_back_the_time_shift_and_the_focal_scale() -> None:
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=-0.046, gain=1.35, noise_px=0.3)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "rigid", check.reason
    assert check.time_shift_s == pytest.approx(-0.046, abs=0.004)
    assert check.focal_scale == pytest.approx(1.35, rel=0.02)
    assert check.gain_standard_error < 0.02
    assert check.unexplained < 0.1
    assert not check.shift_at_search_bound
    assert min(check.axis_correlation) > 0.9  # every axis turns the same way
    stats = _strict_json(check)
    assert stats["gyro_check"] == "rigid"
    assert stats["gyro_check_focal_scale"] == pytest.approx(1.35, rel=0.02)
    assert "turn with the gyro" in str(stats["gyro_check_reason"])


def test_a_stabilised_video_is_not_rigid_and_says_why() -> None:
    """Images that turn a third as much as the body, 0.25 s late (electronic stabilisation)."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(
        motion, starts - 250_000_000, ends - 250_000_000, shift_s=0.0, gain=0.33, noise_px=0.3
    )
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "not rigid", check.reason
    low = GyroCheckOptions().focal_scale_range[0]
    assert check.gain > 3 * check.gain_standard_error  # the images do follow the body
    assert check.gain + 3 * check.gain_standard_error < low or check.unexplained > 0.5
    assert check.turning_pairs >= GyroCheckOptions().strong_min_pairs
    assert check.visual_rotation_px < 0.5 * check.gyro_rotation_px
    stats = _strict_json(check)
    assert stats["gyro_check"] == "not rigid"
    assert "no rigid model holds" in str(stats["gyro_check_reason"])


def test_swapped_axes_are_not_declared_rigid() -> None:
    """An IMU whose x and y axes are swapped (an import bug) must not pass as rigid."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=0.0, gain=1.0, noise_px=0.3)
    imu = _imu(motion)
    swapped = ImuSamples(imu.stamps_ns, imu.gyro_rad_s[:, [1, 0, 2]], imu.accel_m_s2)
    assert _check(visual, starts, ends, swapped).verdict != "rigid"


def test_a_camera_that_hardly_turns_gives_no_verdict() -> None:
    motion = _turning_motion(amplitude_rad=0.0)
    motion.pitch = Sinusoids()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=0.0, gain=1.0, noise_px=0.3)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "unknown"
    assert check.turning_pairs < GyroCheckOptions().min_pairs
    assert "too little rotation" in check.reason
    stats = _strict_json(check)
    assert stats["gyro_check_focal_scale"] is None  # not a number: nothing was fitted


@pytest.mark.parametrize("case", ["frozen", "unrelated", "reversed"])
def test_a_degenerate_fit_is_unknown_not_stabilised(case: str) -> None:
    """The issue's "101 % unexplained, apparent focal x inf": images whose rotation does
    not follow the gyro at all (a frozen image, rotations unrelated to the body's, or
    turning against it as a wrong axis sign would) give a gain that is not significantly
    positive. That is no evidence of stabilisation: the verdict is "unknown", the focal
    scale is no number (never infinity), and the IMU is kept."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    if case == "frozen":
        visual = _visual(motion, starts, ends, shift_s=0.0, gain=0.0, noise_px=0.3)
    elif case == "unrelated":
        other = DiverMotion(
            yaw=Sinusoids(amplitudes=(0.4,), frequencies_rad_s=(1.3,), phases_rad=(1.0,)),
            roll=Sinusoids(amplitudes=(0.3,), frequencies_rad_s=(2.7,), phases_rad=(0.2,)),
        )
        visual = _visual(other, starts, ends, shift_s=0.0, gain=1.0, noise_px=0.3)
    else:
        visual = _visual(motion, starts, ends, shift_s=0.0, gain=-1.0, noise_px=0.3)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "unknown", check.reason
    assert "degenerate fit" in check.reason
    assert check.turning_pairs >= GyroCheckOptions().strong_min_pairs  # plenty of rotation
    assert math.isnan(check.focal_scale)
    assert not (check.gain > 3 * check.gain_standard_error)
    assert _strict_json(check)["gyro_check_focal_scale"] is None


def test_too_few_turning_pairs_cannot_reject_the_rigid_model() -> None:
    """A stabilised-looking fit on a handful of turning pairs is mixed evidence."""
    motion = _turning_motion()
    starts, ends = _frame_pairs(duration_s=0.5)
    visual = _visual(motion, starts, ends, shift_s=0.0, gain=0.33, noise_px=0.3)
    check = _check(visual, starts, ends, _imu(motion, duration_s=0.5))
    options = GyroCheckOptions()
    assert options.min_pairs <= check.turning_pairs < options.strong_min_pairs
    assert check.verdict == "unknown"
    assert f"need {options.strong_min_pairs} to reject" in check.reason


def test_noisy_images_cannot_reject_the_rigid_model() -> None:
    """Image rotations as noisy as the turns themselves: no verdict either way."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=0.0, gain=0.33, noise_px=6.0, seed=4)
    check = _check(visual, starts, ends, _imu(motion))
    assert check.verdict == "unknown", check.reason


def test_visual_rotation_recovers_a_rotation_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    rays = np.column_stack([rng.uniform(-0.8, 0.8, (200, 2)), np.ones(200)])
    R_now_prev = so3_exp([0.02, -0.05, 0.01])
    moved = rays @ R_now_prev.T
    xy_prev = rays[:, :2]
    xy_now = moved[:, :2] / moved[:, 2:3]
    xy_now[:40] += rng.uniform(-0.1, 0.1, (40, 2))  # 20 % gross outliers
    estimate, inliers = visual_rotation(
        xy_prev, xy_now, rng=np.random.default_rng(0), threshold_rad=0.002
    )
    assert inliers >= 155
    assert np.linalg.norm(so3_log(estimate.T @ R_now_prev)) < 1e-6


def test_visual_rotation_needs_eight_points() -> None:
    estimate, inliers = visual_rotation(
        np.zeros((5, 2)), np.zeros((5, 2)), rng=np.random.default_rng(0), threshold_rad=0.01
    )
    assert inliers == 0
    np.testing.assert_array_equal(estimate, np.eye(3))


def test_no_pairs_at_all_is_unknown() -> None:
    motion = _turning_motion()
    empty = np.zeros(0, dtype=np.int64)
    check = _check(np.zeros((0, 3, 3)), empty, empty, _imu(motion))
    assert check.verdict == "unknown" and check.pairs == 0


def test_an_imu_that_starts_late_and_ends_early_uses_the_pairs_it_covers() -> None:
    """Real cameras start the IMU after the first frame (59 ms on one GoPro clip)."""
    motion = _turning_motion()
    starts, ends = _frame_pairs()
    visual = _visual(motion, starts, ends, shift_s=-0.02, gain=1.2, noise_px=0.3)
    imu = _imu(motion)
    keep = (imu.stamps_ns >= START_NS + 59_000_000) & (imu.stamps_ns <= ends[-1] - 300_000_000)
    late = ImuSamples(imu.stamps_ns[keep], imu.gyro_rad_s[keep], imu.accel_m_s2[keep])
    check = _check(visual, starts, ends, late)
    assert check.verdict == "rigid", check.reason
    assert check.focal_scale == pytest.approx(1.2, rel=0.02)
    assert check.time_shift_s == pytest.approx(-0.02, abs=0.004)


def test_a_stabilised_video_that_never_stops_turning_is_still_judged() -> None:
    """No still moment to measure the image noise on: the jitter of consecutive image
    rotations bounds it instead, so strong evidence still gives "not rigid"."""
    circling = DiverMotion(
        yaw=Sinusoids(amplitudes=(0.4,), frequencies_rad_s=(2.1,), phases_rad=(0.0,)),
        pitch=Sinusoids(amplitudes=(0.4,), frequencies_rad_s=(2.1,), phases_rad=(np.pi / 2,)),
    )
    starts, ends = _frame_pairs()
    visual = _visual(
        circling, starts - 250_000_000, ends - 250_000_000, shift_s=0.0, gain=0.33, noise_px=0.3
    )
    check = _check(visual, starts, ends, _imu(circling))
    assert check.still_pairs == 0
    assert check.visual_noise_px < 0.5 * check.gyro_rotation_px
    assert check.verdict == "not rigid", check.reason
