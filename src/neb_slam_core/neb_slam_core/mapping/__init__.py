"""Mapping: optimisers over the growing block map, keyframes, joint optimisation."""
