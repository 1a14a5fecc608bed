"""Fuzz and property tests of every parser (issue 14)."""
