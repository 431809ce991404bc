"""Packaged configuration presets (YAML): see neb_slam_core.config_io. A package only so that setuptools
ships the folder without ambiguity; it has no code."""
