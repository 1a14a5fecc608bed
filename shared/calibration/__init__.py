"""Camera and IMU calibration: camera models, Kalibr YAML files, AprilGrid targets."""
