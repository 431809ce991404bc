"""Imports every loader module so that each registers its format (see ``base._import_loaders``)."""

from . import apartment  # noqa: F401
from . import bag  # noqa: F401
from . import neural_rgbd  # noqa: F401
from . import replica  # noqa: F401
from . import scannet  # noqa: F401
from . import seven_scenes  # noqa: F401
from . import tum  # noqa: F401
