"""Field tools: run on the dive-boat laptop or an embedded logger.

Data flows: GoPro files or live cameras -> time-stamped MCAP session folders;
dive computers -> dive folders; a zenoh live preview. Never imports `postproc`.
"""
