"""Depth stage: dive-computer clock sync, true depth, and depth factors (`stage.run`)."""
