"""Imports every loader module so that each registers its format (see ``base._import_loaders``)."""

from . import (
    apartment,  # noqa: F401
    bag,  # noqa: F401
    neural_rgbd,  # noqa: F401
    replica,  # noqa: F401
    scannet,  # noqa: F401
    seven_scenes,  # noqa: F401
    tum,  # noqa: F401
)
