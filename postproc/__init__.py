"""Lab post-processing: a batch over session and dive folders.

Stages, in the order data flows: slam -> depth -> merge -> sfm -> dense,
driven by `pipeline` (the `wreckmap-post run` batch). Never imported by `field`.
"""
