"""Rigid-body geometry: SE(3) helpers and camera rays."""
