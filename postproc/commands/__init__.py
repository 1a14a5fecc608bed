"""Thin command-line layer of `wreckmap-post`, one module per command group."""
