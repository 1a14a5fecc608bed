"""Exports of a finished run for the tools surveyors and archaeologists use.

Pure math (`cameras`, `ortho` rasterisation, the angle conventions in
`camera_reference`) is kept apart from the writers; `stage.run` ties them together and
`postproc.commands.export` is the thin command line (`wreckmap-post export`).
"""
