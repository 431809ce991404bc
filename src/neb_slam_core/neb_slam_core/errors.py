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


class ConfigError(NebSlamError):
    """A configuration value is missing, of the wrong type or out of range."""


class VocabularyError(DatasetError):
    """A bag-of-words vocabulary file is missing, malformed or of another format version."""
