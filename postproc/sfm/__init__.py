"""Global SfM refinement seeded by SLAM poses (COLMAP through pycolmap, CPU).

`pairs` chooses which keyframes to match from the prior poses (pure math),
`database` writes the COLMAP database (cameras, rigs, frames, images, pose
priors), `features` runs SIFT extraction and matching with bounded budgets,
`refine` triangulates with the prior poses and bundle-adjusts with pose priors,
and `stage` ties them into `run(options, input_dirs, out_dir)`.
"""
