"""Synthetic D405 depth and reference clouds (issue: render). Not implemented yet."""
