"""Dense reconstruction: undistortion, depth maps (COLMAP PatchMatch on CUDA or our CPU
stereo), COLMAP stereo fusion, screened Poisson meshing, colour correction, evaluation.

Output folder of `wreckmap-post dense` (`postproc.dense.stage.run`):
`workspace/` (a COLMAP dense workspace: `images/`, `sparse/`, `stereo/depth_maps`,
`stereo/normal_maps`), `fused.ply` (+ `fused.ply.vis`), `fused_corrected.ply` when colour
correction is on, `mesh.ply` (trimmed Poisson mesh) and `dense.json` (parameters, timings).
"""
