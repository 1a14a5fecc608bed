"""Stage 4: multi-session merging through AprilGrid targets.

Tags are found by `shared.calibration.aprilgrid_detection` (Kalibr's convention,
sub-pixel corners). Modules: `target_pose` (whole-grid PnP through the camera
model), `averaging` (robust SE(3) means and their covariances; pure math), `align`
(session-to-session transforms, 4 and 6 DoF; pure math), `paper` (the paper's
method, for comparison), `plots`, and `stage` (`MergeOptions`, `run`). Simulated
surveys for its tests and bench: `sim.targets`.
"""
