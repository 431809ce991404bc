"""Tracking: camera pose optimisation by rendering the block map."""
