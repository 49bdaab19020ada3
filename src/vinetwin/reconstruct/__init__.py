"""Captured frames to a vine mesh (issue: reconstruct). Not implemented yet."""
