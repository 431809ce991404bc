"""File formats: trajectories, bags, run directories."""
