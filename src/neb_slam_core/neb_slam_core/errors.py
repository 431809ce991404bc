"""Exceptions the core raises for bad input.

Every message names the file (or topic, or field) and what was expected, so that a user can fix
the input without reading a traceback.
"""

from __future__ import annotations

from pathlib import Path


class NebSlamError(Exception):
    """Base class of all errors raised deliberately by neb_slam_core."""


class DatasetError(NebSlamError):
    """A dataset folder, bag or file is missing, unreadable or malformed."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(problem if path is None else f"{path}: {problem}")


class UnreadableFrameError(DatasetError):
    """The colour or depth data of one frame cannot be read: an image file that is missing, truncated or
    not decodable, or a bag message that does not decode. The rest of the dataset may be fine.

    Loaders raise it from ``Dataset._load``, and ``Dataset.__getitem__`` sets ``index`` to the frame's
    index. A caller that can go on without the frame (``neb-slam run``) catches this type and skips the
    frame; every other caller gets the :class:`DatasetError` it is.
    """

    def __init__(self, path: str | Path | None, problem: str, index: int | None = None):
        super().__init__(path, problem)
        self.index = index


class ConfigError(NebSlamError):
    """A configuration value is missing, of the wrong type or out of range."""


class VocabularyError(DatasetError):
    """A bag-of-words vocabulary file is missing, malformed or of another format version."""
