"""Keyframe visual-inertial SLAM (stage 2 of docs/method.md; replaces SVIn2).

Modules, from pixels to the result folder:

- `frontend`: grey, resize, CLAHE, grid-spread corners, KLT with a gyro-seeded
  guess, forward-backward and essential-matrix RANSAC checks, undistortion by
  table lookup -> `FrameTracks`.
- `keyframes`: the OKVIS/SVIn2 overlap / match-ratio rule with interval bounds.
- `initialization`: gravity from the rotation-compensated accelerometer mean,
  rest from the IMU's spread, linear visual-inertial alignment (velocity,
  accelerometer bias, scale), zero-velocity detection.
- `backend`: GTSAM ISAM2 smoother with CombinedImuFactor between keyframes and
  Huber projection factors to triangulated landmarks, over a sliding window of
  keyframes (older ones retired and frozen, so memory stays flat on long dives),
  plus a global pose graph for loops that reach retired keyframes.
- `loop_closure`: gated candidates, ORB matching, PnP RANSAC, robust
  between-factors in the same graph.
- `estimator`: ties the above together frame by frame (pure computation).
- `visual_only`: the IMU-free baseline (`--no-imu`).
- `inputs`: EuRoC (also camera-only) and session-folder readers behind one Protocol.
  (Real IMU rows, with repeated or backward stamps or gyro and accelerometer merged
  from separate sensors, become one strictly increasing stream in `shared.imu`.)
- `stage`: `SlamOptions` and `run(options, input_path, out_dir)` writing the
  SLAM result folder of docs/conventions.md.
"""
