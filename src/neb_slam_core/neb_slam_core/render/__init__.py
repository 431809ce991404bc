"""Ray sampling, volume rendering and the losses of the paper (pure functions)."""
