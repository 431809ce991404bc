"""Imports every loader module so that each registers its format (see ``base._import_loaders``)."""

from . import tum  # noqa: F401
