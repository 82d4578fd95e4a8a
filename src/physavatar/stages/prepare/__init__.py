"""Preparing a capture: what it lacks (masks, first-frame mesh, body, segmentation, boundary, UVs)."""
