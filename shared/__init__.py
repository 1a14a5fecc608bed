"""Contracts shared by the field tools and the lab post-processing.

Pure math (geometry, clocks), calibration models, file formats and the MCAP
archive schema. Nothing here imports `field` or `postproc`.
"""
