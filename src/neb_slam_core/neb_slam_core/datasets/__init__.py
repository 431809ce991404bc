"""Dataset loaders: one per format, one registry, one :class:`~neb_slam_core.types.RgbdFrame` type."""

from .base import Dataset, dataset_formats, loader_class, open_dataset, register

__all__ = ["Dataset", "dataset_formats", "loader_class", "open_dataset", "register"]
