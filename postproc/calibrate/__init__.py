"""Calibration without ROS: camera intrinsics from AprilGrid views, the camera-IMU rotation
and time offset from a recording, and the time offset and rotation between two rigs.

Modules: `frame_selection` (which views to use: image coverage, viewing angles,
sharpness), `intrinsics` (pinhole-radtan / equidistant fits, coverage), `camera_imu`
(rotation and time shift between a camera and a gyro, pure math), `two_camera` (two
unsynchronised rigs from their gyros, pure math), `stage` (reading images and IMU,
writing Kalibr YAML, plots, reports: the `run_*` entry points).
"""
