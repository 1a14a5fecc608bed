"""Simulation with exact truth: the data every stage is measured against (one home).

Modules (pure math unless noted): `scene` (the wreck: boxes, seafloor, two AprilGrids,
procedural textures from `textures`), `render` (ray casting through any shared camera
model, underwater image model, range/depth images), `spline` (B-spline trajectories on
R^3 and SO(3) with exact derivatives), `motion` (diver routes), `imu` (the one IMU
simulator: `simulate_imu` on any trajectory with exact derivatives, Kalibr noise; its
samples are `shared.imu.ImuSamples`), `dive` (the one dive-computer model: the survey's
dive and the depth stage's synthetic dives, logged on the computer's own clock), `mesh`
(truth mesh, PLY writer: I/O) and `survey` (`SurveySimulator`, `run`: I/O). For single
stages: `features` (feature-level SLAM sequences: tracks and IMU, no images),
`targets` (AprilGrid views and SLAM-like folders for merging: I/O), `slam_like` (SLAM-like
folders rendered from the survey, for SfM: I/O) and `calibration` (AprilGrid board views,
hand-held sweeps with IMU, two rigs' gyros).

Layers: `sim` imports `shared`; besides, `features` takes the SLAM frontend's
`FrameTracks` from `postproc.slam.types` (the data it stands in for) and `survey` writes
its GoPro-like MP4 with `field.gopro.writer` (imported inside that function). `field`
imports `sim` for the simulated rig and `wreckmap-field sim`; `postproc` never imports
`sim`; tests and bench do. A camera's pose towards a point is `shared.geometry.look_at`.

Live sources call `SurveySimulator(options).render_frame(session, t_cam_ns)` for one image
(deterministic noise), `world_from_cam` / `world_from_body` for the truth and `imu(session)`
for the IMU samples.

`wreckmap-field sim survey --out DIR` (or `survey.run`) writes::

    DIR/
      truth.json              everything true, JSON (format "wreckmap-sim-truth", version 2):
                              world (frame, gravity_w_m_s2, depth_relation "depth_m = -z_W of
                              the body origin", seafloor_z_m), targets (name, tag_id_offset,
                              rows, cols, tag_size_m, tag_spacing_ratio, world_from_target 4x4,
                              yaml), camera (Kalibr model, intrinsics, distortion, fps,
                              cam_from_imu = T_C_B, timeshift_cam_imu_s), imu (rate and noise),
                              sessions (start_ns/end_ns true time, first_frame_cam_ns,
                              world_from_first_body, world_from_first_cam, initial biases,
                              clocks of every device, relative file paths)
      truth_mesh.ply          binary PLY, world frame W (z up, z = 0 at the surface), vertex
                              colours from the textures; visible faces, seafloor, target boards
      targets/aprilgrid_4x2_id0.yaml, targets/aprilgrid_5x4_id100.yaml
                              Kalibr AprilGrid YAMLs (+ tagIdOffset); 36h11, 88 mm, ratio 0.3
      calib/camchain.yaml     Kalibr camchain of cam0 (pinhole-radtan, T_cam_imu, timeshift)
      calib/imu.yaml          Kalibr IMU noise (continuous-time densities, 200 Hz)
      session_NN/
        euroc/mav0/           EuRoC ASL folder: cam0 (grey PNGs named by the camera-clock
                              stamp, ns), imu0 (200 Hz, true time), state_groundtruth_estimate0
                              (T_W_B, velocity, true biases at the IMU stamps)
        world_from_body.tum   the same ground-truth body poses as TUM text (seconds)
        dive/                 dive folder (dives.json + CSV): the dive computer's log, its own
                              clock (offset of hours plus seconds, drift up to +-50 ppm),
                              10 s samples, 0.1 m steps, descent and ascent around the filming
        gopro/GX010001.MP4    (unless --no-video) GoPro-like MP4: H.264 of the colour frames,
                              GPMF ACCL/GYRO in GoPro axes (ORIN "ZXY", as Hero cameras
                              write them; `gopro import` maps them back to the body frame
                              of calib/camchain.yaml), media time 0 =
                              frame 0; an IMU sample's media time is its true time minus the
                              timeshift minus frame 0's camera stamp; creation time on the
                              GoPro's own clock
        depth/<stamp>.png     (with --depth) each frame's depth map: camera z in millimetres,
                              uint16 PNG, 0 where nothing is hit; named like cam0's images

Clocks: a session's IMU clock is true time (int64 ns since the epoch, UTC). Images are
stamped on the camera clock and were exposed at t_cam + timeshift_cam_imu_s (Kalibr's
t_imu = t_cam + shift). The same seed gives the same bytes, whatever the worker count.
"""
