"""Thin command-line layer of `wreckmap-field`, one module per command group."""
